"""Ready-made scenes for tests, the demo and the benchmarks, each deterministic from a seed.

- :func:`planar_view`: one board, random tilt / roll / position, square size given in pixels;
- :func:`hard_view`, :func:`partial_view`, :func:`occluded_view`: the same in poor conditions, cut by the
  image border, partly hidden behind a plate;
- :func:`negative_view`: clutter with checker-like distractors and no board;
- :func:`multi_view`: 2..3 boards of different grids in one image;
- :func:`box_stereo`: the calibration box (configs/targets/box-100mm.yaml) seen by a stereo pair;
- :func:`robot_sequence`: a stereo rig at 30 fps watching a robot that carries three boards
  (configs/targets/robot-3boards.yaml), with the true T_rig_robot of every frame.

The square size in pixels is the *nominal* one: focal length x square_mm / depth of the board centre
(before tilt foreshortening), so a test can ask for "8 px squares" directly.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from edgecal.camera import CameraModel
from edgecal.config import packaged_config_path
from edgecal.geometry import look_at, rotation_about
from edgecal.synth.camera import (
    camera_from_fov,
    camera_json,
    pixel_rays,
    stereo_right_pose,
)
from edgecal.synth.clutter import clutter_background, uniform_background
from edgecal.synth.photometric import Photometric, random_photometric
from edgecal.synth.render import Panel, board_panel_extent, panels_from_target
from edgecal.synth.truth import PAIR_FORMAT, target_json
from edgecal.synth.view import RenderedView, render_view
from edgecal.targets import Board, Target, load_target, planar_target

#: A seed: an int, or a tuple of ints (e.g. (set seed, image index)).
SeedLike = int | tuple[int, ...]
#: A fixed value, or a (low, high) range drawn uniformly.
FloatOrRange = float | tuple[float, float]


def _seed_list(seed: SeedLike) -> list[int]:
    return [int(v) for v in seed] if isinstance(seed, (tuple, list)) else [int(seed)]


def _rng(seed: SeedLike, tag: str) -> np.random.Generator:
    # One independent stream per (scene kind, seed): scene kinds never share random numbers.
    return np.random.default_rng(_seed_list(seed) + [sum(ord(c) * 31 ** i for i, c in enumerate(tag)) % (2 ** 31)])


def _pick(rng: np.random.Generator, value: FloatOrRange) -> float:
    if isinstance(value, (tuple, list)):
        return float(rng.uniform(value[0], value[1]))
    return float(value)


def random_camera(rng: np.random.Generator, size: tuple[int, int] = (640, 480),
                  hfov_deg: FloatOrRange = (55.0, 72.0), distortion: str = "mild") -> CameraModel:
    """A plausible camera: random field of view, principal point near the centre, distortion level
    "none", "mild" (|k1| <= 0.15) or "strong" (barrel up to k1 = -0.3) of the radtan lens, or the lens models
    "rational" (a wide lens, 90-110 deg unless ``hfov_deg`` says otherwise) and "fisheye" (Kannala-Brandt,
    150-200 deg unless ``hfov_deg`` says otherwise)."""
    w, h = size
    if distortion in ("rational", "fisheye"):
        wide = distortion == "fisheye"
        hfov = (150.0, 200.0) if hfov_deg == (55.0, 72.0) and wide else (90.0, 110.0) if hfov_deg == (55.0, 72.0) \
            else hfov_deg
        if wide:
            params = [rng.uniform(-0.02, 0.04), rng.uniform(-0.01, 0.01), rng.uniform(-0.002, 0.002),
                      rng.uniform(-0.0005, 0.0005)]
        else:
            params = [rng.uniform(0.3, 0.5), rng.uniform(-0.08, 0.0), rng.normal(0, 5e-4), rng.normal(0, 5e-4),
                      rng.uniform(0.0, 0.02), rng.uniform(0.65, 0.85), rng.uniform(0.0, 0.04), rng.uniform(0.0, 0.008)]
        off = (float(rng.normal(0, 0.01 * w)), float(rng.normal(0, 0.01 * h)))
        return camera_from_fov(size, _pick(rng, hfov), tuple(params), off, float(rng.uniform(0.997, 1.003)),
                               distortion)
    dist = np.zeros(5)
    if distortion == "mild":
        dist[:4] = [rng.uniform(-0.15, 0.05), rng.uniform(-0.02, 0.05), rng.normal(0, 5e-4), rng.normal(0, 5e-4)]
    elif distortion == "strong":
        dist[:5] = [rng.uniform(-0.3, -0.15), rng.uniform(0.02, 0.1), rng.normal(0, 1e-3), rng.normal(0, 1e-3),
                    rng.uniform(-0.02, 0.0)]
    elif distortion != "none":
        raise ValueError(f"unknown distortion level {distortion!r} (none, mild, strong, rational, fisheye)")
    off = (float(rng.normal(0, 0.01 * w)), float(rng.normal(0, 0.01 * h)))
    return camera_from_fov(size, _pick(rng, hfov_deg), tuple(dist), off, float(rng.uniform(0.997, 1.003)))


def _photometric(rng: np.random.Generator, photometric: Photometric | str) -> Photometric:
    return photometric if isinstance(photometric, Photometric) else random_photometric(rng, photometric)


def _background(rng: np.random.Generator, size: tuple[int, int], background: str) -> tuple[np.ndarray, list[str]]:
    if background == "clutter":
        return clutter_background(rng, size)
    if background == "plain-clutter":
        return clutter_background(rng, size, distractors=[])
    if background == "uniform":
        return uniform_background(size, float(rng.uniform(0.3, 0.6))), []
    raise ValueError(f"unknown background {background!r} (clutter, plain-clutter, uniform)")


def _squares_outline(board: Board, n: int = 12) -> np.ndarray:
    """Board-frame points (mm) along the outer edge of the squares area (what must be in the image)."""
    s = board.square_mm
    u0, v0, u1, v1 = -s, -s, board.cols * s, board.rows * s
    t = np.linspace(0.0, 1.0, n, endpoint=False)
    edges = [np.stack([u0 + (u1 - u0) * t, np.full(n, v0)], 1), np.stack([np.full(n, u1), v0 + (v1 - v0) * t], 1),
             np.stack([u1 - (u1 - u0) * t, np.full(n, v1)], 1), np.stack([np.full(n, u0), v1 - (v1 - v0) * t], 1)]
    uv = np.concatenate(edges)
    return np.concatenate([uv, np.zeros((len(uv), 1))], axis=1)


def _fits(camera: CameraModel, pts_cam: np.ndarray, margin_px: float,
          taken: list[tuple[float, float, float, float]] | None = None) -> tuple[bool, tuple[float, float, float, float]]:
    if np.any(pts_cam[:, 2] <= 1.0):
        return False, (0, 0, 0, 0)
    px = camera.project(pts_cam)
    w, h = camera.image_size
    box = (float(px[:, 0].min()), float(px[:, 1].min()), float(px[:, 0].max()), float(px[:, 1].max()))
    if box[0] < margin_px or box[1] < margin_px or box[2] > w - 1 - margin_px or box[3] > h - 1 - margin_px:
        return False, box
    for o in taken or []:
        if box[0] < o[2] and o[0] < box[2] and box[1] < o[3] and o[1] < box[3]:
            return False, box
    return True, box


def place_board(rng: np.random.Generator, camera: CameraModel, board: Board, square_px: float,
                tilt_max_deg: float = 50.0, roll_deg: FloatOrRange = (-180.0, 180.0),
                margin_px: float = 3.0, taken: list | None = None,
                tries: int = 300) -> tuple[np.ndarray, np.ndarray, tuple[float, float, float, float]] | None:
    """A random pose (R_cam_board, t_cam_board_mm) that shows all of ``board``'s squares in the image.

    The board's centre is at the depth where a square measures ``square_px`` (nominal); the board is
    rolled in-plane, tilted by up to ``tilt_max_deg`` about a random in-plane axis, and shifted to a random
    place where its squares (plus ``margin_px``) fit and miss the boxes in ``taken``. None if nothing fits.
    """
    f = float(np.sqrt(camera.fx * camera.fy))
    z = f * board.square_mm / square_px
    centre = np.array([(board.cols - 1) * board.square_mm / 2.0, (board.rows - 1) * board.square_mm / 2.0, 0.0])
    outline = _squares_outline(board)
    w, h = camera.image_size
    for _ in range(tries):
        roll = np.radians(_pick(rng, roll_deg))
        tilt = np.radians(rng.uniform(0.0, tilt_max_deg)) if tilt_max_deg > 0 else 0.0
        phi = rng.uniform(0.0, 2 * np.pi)
        R = rotation_about(np.array([np.cos(phi), np.sin(phi), 0.0]), tilt) @ rotation_about(np.array([0, 0, 1.0]), roll)
        # Where the centre goes: a random pixel, undistorted to a ray at depth z.
        px = np.array([[rng.uniform(0.1, 0.9) * (w - 1), rng.uniform(0.1, 0.9) * (h - 1)]])
        ray = pixel_rays(camera, px)[0]
        if not np.all(np.isfinite(ray)):
            continue
        t = ray * z - R @ centre
        ok, box = _fits(camera, outline @ R.T + t, margin_px, taken)
        if ok:
            return R, t, box
    return None


def planar_view(seed: SeedLike, *, size: tuple[int, int] = (640, 480), cols: int = 9, rows: int = 6,
                square_mm: float = 25.0, square_px: FloatOrRange = (15.0, 45.0),
                tilt_max_deg: float = 50.0, photometric: Photometric | str = "normal",
                background: str = "clutter", distortion: str = "mild", supersampling: int = 12,
                border_px: float = 4.0) -> RenderedView:
    """One ``cols`` x ``rows`` board (world frame = board frame) at a random pose, fully in view.

    Raises ValueError when a board of that many squares cannot fit the image at ``square_px``.
    """
    rng = _rng(seed, "planar")
    camera = random_camera(rng, size, distortion=distortion)
    board = planar_target(cols, rows, square_mm, name="board0").boards[0]
    sq = _pick(rng, square_px)
    pose = place_board(rng, camera, board, sq, tilt_max_deg)
    if pose is None:
        # A smaller tilt is the only freedom left; if even a flat board does not fit, say so.
        pose = place_board(rng, camera, board, sq, min(tilt_max_deg, 10.0), roll_deg=(-10.0, 10.0))
    if pose is None:
        raise ValueError(f"a {cols}x{rows} board with {sq:.0f} px squares ({(cols + 1) * sq:.0f} x "
                         f"{(rows + 1) * sq:.0f} px) does not fit a {size[0]}x{size[1]} image; "
                         f"use fewer corners or smaller squares")
    R, t, _box = pose
    bg, distractors = _background(rng, size, background)
    phot = _photometric(rng, photometric)
    white = float(rng.uniform(0.75, 0.92))
    black = float(rng.uniform(0.03, 0.15))
    panels = [Panel("board0", np.zeros(3), np.array([1.0, 0, 0]), np.array([0, 1.0, 0]),
                    board_panel_extent(board, float(rng.uniform(0.5, 1.5)) * square_mm), board, black, white)]
    tilt = float(np.degrees(np.arccos(np.clip(R[2, 2], -1, 1))))
    return render_view(camera, panels, R, t, background=bg, photometric=phot, rng=rng,
                       supersampling=supersampling, border_px=border_px,
                       extra={"category": "planar", "seed": _seed_list(seed) + ["planar"], "square_px_nominal": sq,
                              "tilt_deg": tilt, "distractors": distractors})


def negative_view(seed: SeedLike, *, size: tuple[int, int] = (640, 480), photometric: Photometric | str = "normal",
                  distractors: list[str] | None = None) -> RenderedView:
    """Clutter with checker-like distractors (2..5 unless given) and no board: 0 boards in the truth."""
    rng = _rng(seed, "negative")
    camera = random_camera(rng, size)
    if distractors is None:
        from edgecal.synth.clutter import DISTRACTORS
        distractors = [DISTRACTORS[int(i)] for i in rng.integers(0, len(DISTRACTORS), int(rng.integers(2, 6)))]
        if "checker" not in distractors:
            distractors[0] = "checker"
    bg, drawn = clutter_background(rng, size, distractors=distractors)
    phot = _photometric(rng, photometric)
    return render_view(camera, [], np.eye(3), np.zeros(3), background=bg, photometric=phot, rng=rng,
                       extra={"category": "negative", "seed": _seed_list(seed) + ["negative"], "distractors": drawn})


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
    rng = _rng(seed, "multi")
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
            pose = place_board(rng, camera, board, _pick(rng, square_px), tilt_max_deg, margin_px=3.0,
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
    bg, distractors = _background(rng, size, background)
    phot = _photometric(rng, photometric)
    return render_view(camera, panels, np.eye(3), np.zeros(3), background=bg, photometric=phot, rng=rng,
                       supersampling=supersampling, border_px=border_px,
                       extra={"category": "multi", "seed": _seed_list(seed) + ["multi"], "distractors": distractors})


@dataclass
class StereoView:
    """A stereo pair of views of one scene and the pair truth (cameras, R_right_left, T_right_left_mm)."""

    left: RenderedView
    right: RenderedView
    pair: dict


def box_target() -> Target:
    """The calibration box of configs/targets/box-100mm.yaml."""
    return load_target(packaged_config_path("targets/box-100mm.yaml"))


def _box_face_extents(target: Target, cube_mm: float) -> dict[str, tuple[float, float, float, float]]:
    """Each board's panel = the whole cube face it lies on (in board coordinates)."""
    verts = np.array([[x, y, z] for x in (0, cube_mm) for y in (0, cube_mm) for z in (0, cube_mm)], dtype=float)
    out = {}
    for b in target.boards:
        d = verts - b.origin_mm
        on = np.abs(d @ b.normal) < 1e-6
        if on.sum() < 4:
            out[b.name] = board_panel_extent(b)
            continue
        u, v = d[on] @ b.x_axis, d[on] @ b.y_axis
        out[b.name] = (float(u.min()), float(v.min()), float(u.max()), float(v.max()))
    return out


def box_stereo(seed: SeedLike, *, size: tuple[int, int] = (1280, 800), distance_mm: FloatOrRange = (250.0, 350.0),
               baseline_mm: float = 70.0, photometric: Photometric | str = "normal", background: str = "clutter",
               target: Target | None = None, cube_mm: float = 100.0, supersampling: int = 12,
               border_px: float = 4.0, rig: RobotRig | None = None) -> StereoView:
    """The calibration box seen by a (nearly parallel) stereo rig; world frame = box frame.

    The rig looks at the box centre from the octant where all three printed faces are visible, with a
    random roll; the right camera sits ``baseline_mm`` along the left camera's x axis, slightly rotated.
    ``rig`` (e.g. :func:`robot_rig`) replaces the random cameras and extrinsics by its own, so the box
    calibrates the rig that a robot sequence uses.
    """
    rng = _rng(seed, "box")
    tgt = target or box_target()
    left_cam = random_camera(rng, size, hfov_deg=(55.0, 65.0))
    right_cam = random_camera(rng, size, hfov_deg=(55.0, 65.0))
    if rig is not None:
        left_cam, right_cam = rig.left, rig.right
        baseline_mm = float(np.linalg.norm(rig.T_right_left_mm))
    centre = np.full(3, cube_mm / 2.0)
    direction = -rng.uniform(0.7, 1.0, size=3)
    direction /= np.linalg.norm(direction)
    dist = _pick(rng, distance_mm)
    rig_eye = centre + dist * direction
    R0, _ = look_at(rig_eye, centre, up=np.array([0.0, 0.0, -1.0]))
    R_roll = rotation_about(np.array([0, 0, 1.0]), np.radians(rng.uniform(-15, 15)))
    R_left = R_roll @ R0
    # Parallel rig centred on the box: the left eye sits half a baseline to the left of the rig's axis.
    left_eye = rig_eye - R_left[0] * baseline_mm / 2.0
    t_left = -R_left @ left_eye
    R_rl = rotation_about(rng.normal(size=3), np.radians(rng.uniform(0.3, 1.5)))
    T_rl = -R_rl @ np.array([baseline_mm, 0.0, 0.0]) + rng.normal(0, 1.0, size=3)
    if rig is not None:
        R_rl, T_rl = np.asarray(rig.R_right_left, dtype=np.float64), np.asarray(rig.T_right_left_mm, dtype=np.float64)
    R_right, t_right = stereo_right_pose(R_left, t_left, R_rl, T_rl)
    white = float(rng.uniform(0.75, 0.92))
    black = float(rng.uniform(0.03, 0.12))
    panels = panels_from_target(tgt, extents=_box_face_extents(tgt, cube_mm), black_albedo=black, white_albedo=white)
    bg_l, distractors_l = _background(rng, size, background)
    bg_r, distractors_r = _background(rng, size, background)
    phot = _photometric(rng, photometric)
    common = {"category": "box_stereo", "seed": _seed_list(seed) + ["box"]}
    left = render_view(left_cam, panels, R_left, t_left, background=bg_l, photometric=phot, rng=rng,
                       supersampling=supersampling, border_px=border_px, target_frame="box", target_name=tgt.name,
                       extra={**common, "stereo_side": "left", "distractors": distractors_l}, camera_name="left")
    right = render_view(right_cam, panels, R_right, t_right, background=bg_r, photometric=phot, rng=rng,
                        supersampling=supersampling, border_px=border_px, target_frame="box",
                        target_name=tgt.name, extra={**common, "stereo_side": "right", "distractors": distractors_r},
                        camera_name="right")
    pair = {
        "format": PAIR_FORMAT,
        "units": {"length": "mm"},
        "convention": "X_right = R_right_left @ X_left + T_right_left_mm (camera frames, mm)",
        "left": camera_json(left_cam, "left", R_left, t_left),
        "right": camera_json(right_cam, "right", R_right, t_right),
        "R_right_left": R_rl.tolist(),
        "T_right_left_mm": T_rl.tolist(),
        "baseline_mm": float(np.linalg.norm(T_rl)),
        "distance_mm": float(np.linalg.norm(centre - left_eye)),
        "target": target_json(panels, "box", tgt.name),
        "seed": _seed_list(seed) + ["box"],
    }
    return StereoView(left, right, pair)


# ---------------------------------------------------------------------------------------------------
# The robot sequence


ROBOT_BODY_MM = (400.0, 300.0, 250.0)  # x, y, z extent of the block carrying the boards


def robot_target() -> Target:
    """The three boards on the robot body (configs/targets/robot-3boards.yaml)."""
    return load_target(packaged_config_path("targets/robot-3boards.yaml"))


def _body_panels(R_world_robot: np.ndarray, t_world_robot: np.ndarray, albedo: float) -> list[Panel]:
    """The six faces of the robot body, 0.5 mm inside the faces the boards are glued to."""
    lx, ly, lz = (v / 2.0 for v in ROBOT_BODY_MM)
    e = 0.5
    faces = [  # (centre in robot frame, x_axis, y_axis, half sizes)
        ((lx - e, 0, lz), (0, 1, 0), (0, 0, 1), (ly, lz)), ((-lx + e, 0, lz), (0, 1, 0), (0, 0, 1), (ly, lz)),
        ((0, ly - e, lz), (1, 0, 0), (0, 0, 1), (lx, lz)), ((0, -ly + e, lz), (1, 0, 0), (0, 0, 1), (lx, lz)),
        ((0, 0, 2 * lz - e), (1, 0, 0), (0, 1, 0), (lx, ly)), ((0, 0, e), (1, 0, 0), (0, 1, 0), (lx, ly)),
    ]
    out = []
    for k, (c, xa, ya, (hu, hv)) in enumerate(faces):
        out.append(Panel(f"body{k}", R_world_robot @ np.array(c, float) + t_world_robot,
                         R_world_robot @ np.array(xa, float), R_world_robot @ np.array(ya, float),
                         (-hu, -hv, hu, hv), None, 0.0, albedo, albedo))
    return out


@dataclass
class RobotFrame:
    """One frame of the robot sequence: the stereo views and the true robot pose in the rig (left camera)."""

    index: int
    stamp_ns: int
    left: RenderedView
    right: RenderedView
    R_rig_robot: np.ndarray
    t_rig_robot_mm: np.ndarray


@dataclass
class RobotRig:
    """The fixed stereo rig of a robot sequence (left camera = rig frame)."""

    left: CameraModel
    right: CameraModel
    R_left_world: np.ndarray
    t_left_world_mm: np.ndarray
    R_right_left: np.ndarray
    T_right_left_mm: np.ndarray

    def as_json(self) -> dict:
        """Rig truth: both cameras (poses in the world/floor frame) and the stereo extrinsics."""
        R_r, t_r = stereo_right_pose(self.R_left_world, self.t_left_world_mm, self.R_right_left, self.T_right_left_mm)
        return {"left": camera_json(self.left, "left", self.R_left_world, self.t_left_world_mm),
                "right": camera_json(self.right, "right", R_r, t_r),
                "R_right_left": self.R_right_left.tolist(), "T_right_left_mm": self.T_right_left_mm.tolist(),
                "baseline_mm": float(np.linalg.norm(self.T_right_left_mm)),
                "convention": "X_right = R_right_left @ X_left + T_right_left_mm (camera frames, mm)"}


# Field of view of the robot rig's cameras per lens model: a ~70 deg pinhole, or a 110-120 deg fisheye whose
# squares at the robot are still ~0.6 of the pinhole's (both rigs then meet the same pose accuracy).
ROBOT_HFOV_DEG = {"radtan": (68.0, 72.0), "fisheye": (110.0, 120.0), "rational": (85.0, 95.0)}


def robot_rig(seed: SeedLike, size: tuple[int, int] = (1280, 800), baseline_mm: float = 75.0,
              lens: str = "radtan") -> RobotRig:
    """The rig of :func:`robot_sequence`: 0.8 m from the robot's area, 0.65 m up, looking down at it (~0.95 m).

    ``lens``: radtan (mild distortion), fisheye or rational (random_camera's lens models)."""
    rng = _rng(seed, "robot-rig")
    level = "mild" if lens == "radtan" else lens
    left = random_camera(rng, size, hfov_deg=ROBOT_HFOV_DEG[lens], distortion=level)
    right = random_camera(rng, size, hfov_deg=ROBOT_HFOV_DEG[lens], distortion=level)
    R_l, t_l = look_at(np.array([-800.0, 0.0, 650.0]), np.array([0.0, 0.0, 150.0]), up=np.array([0.0, 0.0, 1.0]))
    R_rl = rotation_about(rng.normal(size=3), np.radians(rng.uniform(0.1, 0.5)))
    T_rl = -R_rl @ np.array([baseline_mm, 0.0, 0.0]) + rng.normal(0, 0.3, size=3)
    return RobotRig(left, right, R_l, t_l, R_rl, T_rl)


def robot_pose_world(time_s: float, phase: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """T_world_robot at ``time_s``: a smooth wander on the floor, turning to show front, left and top."""
    a, b, c, d, e = phase
    x = 120.0 * np.sin(2 * np.pi * time_s / 8.0 + a)
    y = 180.0 * np.sin(2 * np.pi * time_s / 11.0 + b)
    # Yaw swings around 45 deg off the rig axis, so the front and the left face both stay in view.
    yaw = np.pi - 0.78 + 0.3 * np.sin(2 * np.pi * time_s / 9.0 + c)
    pitch = np.radians(2.5) * np.sin(2 * np.pi * time_s / 3.0 + d)
    roll = np.radians(2.0) * np.sin(2 * np.pi * time_s / 4.0 + e)
    R = (rotation_about(np.array([0, 0, 1.0]), yaw) @ rotation_about(np.array([0, 1.0, 0]), pitch)
         @ rotation_about(np.array([1.0, 0, 0]), roll))
    return R, np.array([x, y, 5.0 * np.sin(2 * np.pi * time_s / 2.0 + a)])


def robot_sequence(seed: SeedLike, n_frames: int | None = None, *, fps: float = 30.0, size: tuple[int, int] = (1280, 800),
                   photometric: Photometric | str = "clean", supersampling: int = 8,
                   border_px: float = 4.0, exposure_ms: float = 0.0,
                   exposure_samples: int = 5, lens: str = "radtan") -> Iterator[RobotFrame]:
    """Frames of a stereo rig watching the robot (endless when ``n_frames`` is None; nothing is kept).

    The room (clutter, rig, lighting) is fixed for the whole sequence; the robot moves smoothly at
    about 1 m from the rig and each frame gets fresh sensor noise. T_rig_robot = T_rig_world T_world_robot.
    ``exposure_ms`` > 0 blurs the motion: each image averages ``exposure_samples`` instants of the
    exposure, and the truth (stamp_ns, T_rig_robot, corners) is the mid-exposure one.
    """
    rng = _rng(seed, "robot")
    rig = robot_rig(seed, size, lens=lens)
    tgt = robot_target()
    phase = rng.uniform(0, 2 * np.pi, size=5)
    bg_l, _ = clutter_background(rng, size, distractors=["text", "dots"])
    bg_r, _ = clutter_background(rng, size, distractors=["text", "dots"])
    phot = _photometric(rng, photometric)
    body_albedo = float(rng.uniform(0.25, 0.45))
    R_r, t_r = stereo_right_pose(rig.R_left_world, rig.t_left_world_mm, rig.R_right_left, rig.T_right_left_mm)
    rig_json = rig.as_json()
    k = 0
    while n_frames is None or k < n_frames:
        time_s = k / fps
        R_wr, t_wr = robot_pose_world(time_s, phase)

        def scene(R_wr: np.ndarray, t_wr: np.ndarray) -> list[Panel]:
            """The robot's boards and body at pose T_world_robot."""
            return (panels_from_target(tgt, R_wr, t_wr, margin_mm=10.0, black_albedo=0.06, white_albedo=0.85)
                    + _body_panels(R_wr, t_wr, body_albedo))

        panels = scene(R_wr, t_wr)
        exposure = None
        if exposure_ms > 0:
            offsets = (np.linspace(-0.5, 0.5, max(2, exposure_samples))) * exposure_ms * 1e-3
            exposure = [scene(*robot_pose_world(time_s + dt, phase)) for dt in offsets]
        extra = {"category": "robot", "seed": _seed_list(seed) + ["robot"], "frame": k, "exposure_ms": exposure_ms}
        noise = np.random.default_rng(_seed_list(seed) + [k])
        left = render_view(rig.left, panels, rig.R_left_world, rig.t_left_world_mm, background=bg_l, photometric=phot,
                           rng=noise, supersampling=supersampling, border_px=border_px, target_frame="world",
                           target_name=tgt.name, extra={**extra, "stereo_side": "left"}, exposure=exposure,
                           camera_name="left")
        right = render_view(rig.right, panels, R_r, t_r, background=bg_r, photometric=phot, rng=noise,
                            supersampling=supersampling, border_px=border_px, target_frame="world",
                            target_name=tgt.name, extra={**extra, "stereo_side": "right"}, exposure=exposure,
                            camera_name="right")
        R_rig_robot = rig.R_left_world @ R_wr
        t_rig_robot = rig.R_left_world @ t_wr + rig.t_left_world_mm
        for view in (left, right):
            view.truth["rig"] = rig_json
            view.truth["R_rig_robot"] = R_rig_robot.tolist()
            view.truth["t_rig_robot_mm"] = t_rig_robot.tolist()
        yield RobotFrame(k, int(round(k * 1e9 / fps)), left, right, R_rig_robot, t_rig_robot)
        k += 1


def hard_view(seed: SeedLike, *, size: tuple[int, int] = (640, 480), cols: int = 9, rows: int = 6,
              square_px: FloatOrRange = (8.0, 25.0), tilt_max_deg: float = 70.0) -> RenderedView:
    """A planar view in poor conditions: steep tilt, small squares, low contrast, uneven light, heavy noise."""
    view = planar_view(seed, size=size, cols=cols, rows=rows, square_px=square_px, tilt_max_deg=tilt_max_deg,
                       photometric=random_photometric(_rng(seed, "hard"), "hard"))
    view.truth["category"] = "hard"
    return view


def partial_view(seed: SeedLike, *, size: tuple[int, int] = (640, 480), cols: int = 9, rows: int = 6,
                 square_mm: float = 25.0, square_px: FloatOrRange = (20.0, 45.0),
                 visible_fraction: tuple[float, float] = (0.3, 0.9), tilt_max_deg: float = 40.0,
                 photometric: Photometric | str = "normal", background: str = "clutter") -> RenderedView:
    """One board cut by the image border: only ``visible_fraction`` of its corners are in view
    (``complete`` is false in the truth)."""
    rng = _rng(seed, "partial")
    camera = random_camera(rng, size)
    board = planar_target(cols, rows, square_mm, name="board0").boards[0]
    sq = _pick(rng, square_px)
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
        inside = ((px[:, 0] >= border) & (px[:, 0] <= w - 1 - border) & (px[:, 1] >= border) & (px[:, 1] <= h - 1 - border))
        if visible_fraction[0] <= inside.mean() <= visible_fraction[1]:
            break
    else:
        raise ValueError(f"no pose of a {cols}x{rows} board with {sq:.0f} px squares shows "
                         f"{visible_fraction[0]:.0%}..{visible_fraction[1]:.0%} of its corners")
    bg, distractors = _background(rng, size, background)
    panels = [Panel("board0", np.zeros(3), np.array([1.0, 0, 0]), np.array([0, 1.0, 0]),
                    board_panel_extent(board, square_mm), board, float(rng.uniform(0.03, 0.15)),
                    float(rng.uniform(0.75, 0.92)))]
    return render_view(camera, panels, R, t, background=bg, photometric=_photometric(rng, photometric), rng=rng,
                       border_px=border, extra={"category": "partial", "seed": _seed_list(seed) + ["partial"],
                                                "square_px_nominal": sq, "distractors": distractors})


def occluded_view(seed: SeedLike, *, size: tuple[int, int] = (640, 480), cols: int = 9, rows: int = 6,
                  square_mm: float = 25.0, square_px: FloatOrRange = (20.0, 40.0),
                  cover: tuple[float, float] = (0.15, 0.4), photometric: Photometric | str = "normal",
                  background: str = "clutter") -> RenderedView:
    """One board partly hidden behind a plain plate held in front of it (``complete`` is false)."""
    rng = _rng(seed, "occluded")
    camera = random_camera(rng, size)
    board = planar_target(cols, rows, square_mm, name="board0").boards[0]
    sq = _pick(rng, square_px)
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
    bg, distractors = _background(rng, size, background)
    return render_view(camera, panels, R, t, background=bg, photometric=_photometric(rng, photometric), rng=rng,
                       extra={"category": "occluded", "seed": _seed_list(seed) + ["occluded"],
                              "square_px_nominal": sq, "distractors": distractors})
