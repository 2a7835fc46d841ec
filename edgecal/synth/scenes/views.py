"""Scenes of one camera and planar boards: a board in good or poor conditions, cut by the border or
hidden behind a plate, several boards side by side, and clutter without a board."""

from __future__ import annotations

import numpy as np

from edgecal.geometry import rotation_about
from edgecal.synth.camera import pixel_rays
from edgecal.synth.clutter import clutter_background
from edgecal.synth.panels import Panel, board_panel_extent
from edgecal.synth.photometric import Photometric, random_photometric
from edgecal.synth.scenes.common import (
    FloatOrRange,
    SeedLike,
    pick,
    place_board,
    random_camera,
    scene_background,
    scene_photometric,
    scene_rng,
    seed_list,
)
from edgecal.synth.view import RenderedView, render_view
from edgecal.targets import planar_target


def planar_view(seed: SeedLike, *, size: tuple[int, int] = (640, 480), cols: int = 9, rows: int = 6,
                square_mm: float = 25.0, square_px: FloatOrRange = (15.0, 45.0),
                tilt_max_deg: float = 50.0, photometric: Photometric | str = "normal",
                background: str = "clutter", distortion: str = "mild", supersampling: int = 12,
                border_px: float = 4.0) -> RenderedView:
    """One ``cols`` x ``rows`` board (world frame = board frame) at a random pose, fully in view.

    Raises ValueError when a board of that many squares cannot fit the image at ``square_px``.
    """
    rng = scene_rng(seed, "planar")
    camera = random_camera(rng, size, distortion=distortion)
    board = planar_target(cols, rows, square_mm, name="board0").boards[0]
    sq = pick(rng, square_px)
    pose = place_board(rng, camera, board, sq, tilt_max_deg)
    if pose is None:
        # A smaller tilt is the only freedom left; if even a flat board does not fit, say so.
        pose = place_board(rng, camera, board, sq, min(tilt_max_deg, 10.0), roll_deg=(-10.0, 10.0))
    if pose is None:
        raise ValueError(f"a {cols}x{rows} board with {sq:.0f} px squares ({(cols + 1) * sq:.0f} x "
                         f"{(rows + 1) * sq:.0f} px) does not fit a {size[0]}x{size[1]} image; "
                         f"use fewer corners or smaller squares")
    R, t, _box = pose
    bg, distractors = scene_background(rng, size, background)
    phot = scene_photometric(rng, photometric)
    white = float(rng.uniform(0.75, 0.92))
    black = float(rng.uniform(0.03, 0.15))
    panels = [Panel("board0", np.zeros(3), np.array([1.0, 0, 0]), np.array([0, 1.0, 0]),
                    board_panel_extent(board, float(rng.uniform(0.5, 1.5)) * square_mm), board, black, white)]
    tilt = float(np.degrees(np.arccos(np.clip(R[2, 2], -1, 1))))
    return render_view(camera, panels, R, t, background=bg, photometric=phot, rng=rng,
                       supersampling=supersampling, border_px=border_px,
                       extra={"category": "planar", "seed": seed_list(seed) + ["planar"], "square_px_nominal": sq,
                              "tilt_deg": tilt, "distractors": distractors})


def negative_view(seed: SeedLike, *, size: tuple[int, int] = (640, 480), photometric: Photometric | str = "normal",
                  distractors: list[str] | None = None) -> RenderedView:
    """Clutter with checker-like distractors (2..5 unless given) and no board: 0 boards in the truth."""
    rng = scene_rng(seed, "negative")
    camera = random_camera(rng, size)
    if distractors is None:
        from edgecal.synth.clutter import DISTRACTORS
        distractors = [DISTRACTORS[int(i)] for i in rng.integers(0, len(DISTRACTORS), int(rng.integers(2, 6)))]
        if "checker" not in distractors:
            distractors[0] = "checker"
    bg, drawn = clutter_background(rng, size, distractors=distractors)
    phot = scene_photometric(rng, photometric)
    return render_view(camera, [], np.eye(3), np.zeros(3), background=bg, photometric=phot, rng=rng,
                       extra={"category": "negative", "seed": seed_list(seed) + ["negative"], "distractors": drawn})


MULTI_GRIDS = ((5, 3), (6, 4), (7, 5), (4, 3), (8, 5), (3, 3))


def multi_view(seed: SeedLike, *, size: tuple[int, int] = (1280, 800), n_boards: int | tuple[int, int] = (2, 3),
               square_px: FloatOrRange = (12.0, 40.0), tilt_max_deg: float = 40.0,
               photometric: Photometric | str = "normal", background: str = "clutter",
               supersampling: int = 12, border_px: float = 4.0,
               grids: tuple[tuple[int, int], ...] | None = None) -> RenderedView:
    """2..3 boards of different grids and square sizes, side by side (no overlap), world = camera frame.

    ``grids``: the boards' inner corners (cols, rows) instead of a random pick of MULTI_GRIDS (sizes may
    repeat: several boards of one size); ``n_boards`` is then ignored.
    """
    rng = scene_rng(seed, "multi")
    camera = random_camera(rng, size)
    n = int(n_boards) if not isinstance(n_boards, (tuple, list)) else int(rng.integers(n_boards[0], n_boards[1] + 1))
    if grids is None:
        grids = tuple(MULTI_GRIDS[int(i)] for i in rng.permutation(len(MULTI_GRIDS))[:n])
    panels: list[Panel] = []
    taken: list[tuple[float, float, float, float]] = []
    for k, (cols, rows) in enumerate(grids):
        square_mm = float(rng.choice([15.0, 20.0, 25.0, 30.0]))
        board = planar_target(cols, rows, square_mm, name=f"board{k}_{cols}x{rows}").boards[0]
        pose = None
        for _ in range(4):
            # Shrink the squares when the free space is too small for this one.
            pose = place_board(rng, camera, board, pick(rng, square_px), tilt_max_deg, margin_px=3.0,
                               taken=[(a - 8, b - 8, c + 8, d + 8) for a, b, c, d in taken], tries=150)
            if pose is not None:
                break
        if pose is None:
            continue
        R, t, box = pose
        taken.append(box)
        margin = float(rng.uniform(0.4, 1.0)) * square_mm
        panels.append(Panel(board.name, t + R @ np.zeros(3), R[:, 0].copy(), R[:, 1].copy(),
                            board_panel_extent(board, margin), board, float(rng.uniform(0.03, 0.15)),
                            float(rng.uniform(0.75, 0.92))))
    bg, distractors = scene_background(rng, size, background)
    phot = scene_photometric(rng, photometric)
    return render_view(camera, panels, np.eye(3), np.zeros(3), background=bg, photometric=phot, rng=rng,
                       supersampling=supersampling, border_px=border_px,
                       extra={"category": "multi", "seed": seed_list(seed) + ["multi"], "distractors": distractors})


def hard_view(seed: SeedLike, *, size: tuple[int, int] = (640, 480), cols: int = 9, rows: int = 6,
              square_px: FloatOrRange = (8.0, 25.0), tilt_max_deg: float = 70.0) -> RenderedView:
    """A planar view in poor conditions: steep tilt, small squares, low contrast, uneven light, heavy noise."""
    view = planar_view(seed, size=size, cols=cols, rows=rows, square_px=square_px, tilt_max_deg=tilt_max_deg,
                       photometric=random_photometric(scene_rng(seed, "hard"), "hard"))
    view.truth["category"] = "hard"
    return view


def partial_view(seed: SeedLike, *, size: tuple[int, int] = (640, 480), cols: int = 9, rows: int = 6,
                 square_mm: float = 25.0, square_px: FloatOrRange = (20.0, 45.0),
                 visible_fraction: tuple[float, float] = (0.3, 0.9), tilt_max_deg: float = 40.0,
                 photometric: Photometric | str = "normal", background: str = "clutter") -> RenderedView:
    """One board cut by the image border: only ``visible_fraction`` of its corners are in view
    (``complete`` is false in the truth)."""
    rng = scene_rng(seed, "partial")
    camera = random_camera(rng, size)
    board = planar_target(cols, rows, square_mm, name="board0").boards[0]
    sq = pick(rng, square_px)
    f = float(np.sqrt(camera.fx * camera.fy))
    z = f * square_mm / sq
    centre = np.array([(cols - 1) * square_mm / 2.0, (rows - 1) * square_mm / 2.0, 0.0])
    pts = board.board_points_mm()
    w, h = size
    border = 4.0
    for _ in range(500):
        R = (rotation_about(np.array([*rng.normal(size=2), 0.0]), np.radians(rng.uniform(0, tilt_max_deg)))
             @ rotation_about(np.array([0, 0, 1.0]), rng.uniform(-np.pi, np.pi)))
        ray = pixel_rays(camera, np.array([[rng.uniform(-0.2, 1.2) * w, rng.uniform(-0.2, 1.2) * h]]))[0]
        if not np.all(np.isfinite(ray)):
            continue
        t = ray * z - R @ centre
        cam_pts = pts @ R.T + t
        if np.any(cam_pts[:, 2] <= 1.0):
            continue
        px = camera.project(cam_pts)
        inside = ((px[:, 0] >= border) & (px[:, 0] <= w - 1 - border)
                  & (px[:, 1] >= border) & (px[:, 1] <= h - 1 - border))
        if visible_fraction[0] <= inside.mean() <= visible_fraction[1]:
            break
    else:
        raise ValueError(f"no pose of a {cols}x{rows} board with {sq:.0f} px squares shows "
                         f"{visible_fraction[0]:.0%}..{visible_fraction[1]:.0%} of its corners")
    bg, distractors = scene_background(rng, size, background)
    panels = [Panel("board0", np.zeros(3), np.array([1.0, 0, 0]), np.array([0, 1.0, 0]),
                    board_panel_extent(board, square_mm), board, float(rng.uniform(0.03, 0.15)),
                    float(rng.uniform(0.75, 0.92)))]
    return render_view(camera, panels, R, t, background=bg, photometric=scene_photometric(rng, photometric), rng=rng,
                       border_px=border, extra={"category": "partial", "seed": seed_list(seed) + ["partial"],
                                                "square_px_nominal": sq, "distractors": distractors})


def occluded_view(seed: SeedLike, *, size: tuple[int, int] = (640, 480), cols: int = 9, rows: int = 6,
                  square_mm: float = 25.0, square_px: FloatOrRange = (20.0, 40.0),
                  cover: tuple[float, float] = (0.15, 0.4), photometric: Photometric | str = "normal",
                  background: str = "clutter") -> RenderedView:
    """One board partly hidden behind a plain plate held in front of it (``complete`` is false)."""
    rng = scene_rng(seed, "occluded")
    camera = random_camera(rng, size)
    board = planar_target(cols, rows, square_mm, name="board0").boards[0]
    sq = pick(rng, square_px)
    pose = place_board(rng, camera, board, sq, 35.0)
    if pose is None:
        raise ValueError(f"a {cols}x{rows} board with {sq:.0f} px squares does not fit a {size[0]}x{size[1]} image")
    R, t, (x0, y0, x1, y1) = pose
    # A plate parallel to the image, at 60..85 % of the board's depth, over one side of the board's box.
    depth = float((R @ np.array([(cols - 1) * square_mm / 2, (rows - 1) * square_mm / 2, 0.0]) + t)[2])
    d = depth * float(rng.uniform(0.6, 0.85))
    frac = float(rng.uniform(*cover))
    side = int(rng.integers(0, 4))
    bw, bh = x1 - x0, y1 - y0
    rect = [(x0 - 40, y0 - 40, x0 + frac * bw, y1 + 40), (x1 - frac * bw, y0 - 40, x1 + 40, y1 + 40),
            (x0 - 40, y0 - 40, x1 + 40, y0 + frac * bh), (x0 - 40, y1 - frac * bh, x1 + 40, y1 + 40)][side]
    corners = pixel_rays(camera, np.array([[rect[0], rect[1]], [rect[2], rect[3]]])) * d
    Rt = R.T  # camera -> world (board) frame
    origin = Rt @ (corners[0] - t)
    extent = (0.0, 0.0, float(corners[1, 0] - corners[0, 0]), float(corners[1, 1] - corners[0, 1]))
    plate = Panel("plate", origin, Rt @ np.array([1.0, 0, 0]), Rt @ np.array([0, 1.0, 0]), extent, None, 0.0,
                  float(rng.uniform(0.2, 0.7)), 0.5)
    panels = [Panel("board0", np.zeros(3), np.array([1.0, 0, 0]), np.array([0, 1.0, 0]),
                    board_panel_extent(board, square_mm), board, float(rng.uniform(0.03, 0.15)),
                    float(rng.uniform(0.75, 0.92))), plate]
    bg, distractors = scene_background(rng, size, background)
    return render_view(camera, panels, R, t, background=bg, photometric=scene_photometric(rng, photometric), rng=rng,
                       extra={"category": "occluded", "seed": seed_list(seed) + ["occluded"],
                              "square_px_nominal": sq, "distractors": distractors})
