"""A hand-held calibration session: a fixed camera (or stereo pair) and a flat board a person moves
from pose to pose, holding it still for a moment at each (the way one collects calibration views).

Consecutive frames overlap: while the board is held, it trembles by a fraction of a pixel; between two
poses it moves smoothly over a few frames, so most frames are near-duplicates of their neighbours and
some are in motion. This is what ``edgecal collect`` must sort out; the truth of every frame (cameras,
board pose, moving or held) comes with it.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import cv2
import numpy as np

from edgecal.camera import CameraModel
from edgecal.geometry import rotation_about
from edgecal.synth.camera import camera_from_fov, pixel_rays, stereo_right_pose
from edgecal.synth.panels import Panel, board_panel_extent
from edgecal.synth.photometric import Photometric
from edgecal.synth.scenes.common import SeedLike, board_fits, scene_photometric, scene_rng, squares_outline
from edgecal.synth.view import RenderedView, render_view
from edgecal.targets import Board, planar_target

TREMOR_DEG = 0.01     # hand tremor while held: rotation (1-sigma) ...
TREMOR_MM = 0.03      # ... and translation; well under a pixel at calibration distances


@dataclass(frozen=True)
class HandheldRig:
    """The cameras: ``right`` is None for one camera; X_right = R_right_left X_left + T_right_left_mm."""

    left: CameraModel
    right: CameraModel | None
    R_right_left: np.ndarray
    T_right_left_mm: np.ndarray
    board: Board


@dataclass
class HandheldFrame:
    """One frame: the left (or only) view, the right view (stereo), and whether the board was moving."""

    index: int
    stamp_ns: int
    left: RenderedView
    right: RenderedView | None
    moving: bool


def handheld_rig(seed: SeedLike, size: tuple[int, int] = (640, 480), stereo: bool = True,
                 baseline_mm: float = 80.0, cols: int = 9, rows: int = 6, square_mm: float = 30.0) -> HandheldRig:
    """Two (or one) cameras with mild distortion, the right one ``baseline_mm`` to the right, toed in slightly."""
    rng = scene_rng(seed, "handheld-rig")
    def camera(name: str) -> CameraModel:
        dist = (rng.uniform(-0.15, -0.05), rng.uniform(0.0, 0.05), rng.normal(0, 3e-4), rng.normal(0, 3e-4), 0.0)
        off = (float(rng.normal(0, 0.01 * size[0])), float(rng.normal(0, 0.01 * size[1])))
        return camera_from_fov(size, float(rng.uniform(58.0, 66.0)), dist, off, 1.0)
    left = camera("left")
    right = camera("right") if stereo else None
    R = rotation_about(np.array([0.0, 1.0, 0.0]), np.radians(float(rng.uniform(-1.5, 1.5))))
    T = np.array([-baseline_mm, float(rng.normal(0, 0.5)), float(rng.normal(0, 0.5))])
    board = planar_target(cols, rows, square_mm, name="board0").boards[0]
    return HandheldRig(left, right, R, T, board)


# Where a person takes the board, in turn: the image's middle, its four corners and four edges
# (fractions of width and height), near and far, tilted a little and a lot.
PLACES = ((0.5, 0.5), (0.12, 0.12), (0.88, 0.88), (0.88, 0.12), (0.12, 0.88), (0.5, 0.1), (0.1, 0.5),
          (0.5, 0.9), (0.9, 0.5))
TILTS_DEG = (5.0, 45.0, 25.0, 40.0)


def _key_poses(rng: np.random.Generator, rig: HandheldRig, n: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """``n`` poses (R_left_board, t_left_board_mm) spread over position, distance and tilt, all in view.

    Pose k goes to PLACES[k % 9] (jittered), alternately far and near, with a tilt from TILTS_DEG about a
    random axis; where it does not fit it is pulled toward the middle and shrunk until it does.
    """
    outline = squares_outline(rig.board)
    b = rig.board
    w, h = rig.left.image_size
    f = float(np.sqrt(rig.left.fx * rig.left.fy))
    centre = np.array([(b.cols - 1) * b.square_mm / 2.0, (b.rows - 1) * b.square_mm / 2.0, 0.0])
    poses: list[tuple[np.ndarray, np.ndarray]] = []
    for k in range(n):
        place = np.array(PLACES[k % len(PLACES)]) + rng.normal(0, 0.03, 2)
        # far and near in turn; the tilt cycles on pairs of poses, so that near poses get every tilt too
        sq = (0.022 if k % 2 == 0 else 0.1) * w * float(rng.uniform(0.9, 1.1))
        tilt = np.radians(TILTS_DEG[(k // 2) % len(TILTS_DEG)] + float(rng.normal(0, 3.0)))
        phi = float(rng.uniform(0, 2 * np.pi))
        roll = np.radians(float(rng.uniform(-20.0, 20.0)))
        R = (rotation_about(np.array([np.cos(phi), np.sin(phi), 0.0]), tilt)
             @ rotation_about(np.array([0, 0, 1.0]), roll))
        for _ in range(60):
            z = f * b.square_mm / sq
            # a stereo pair: aim so that the place is midway between the board's positions in the two images
            shift = 0.0 if rig.right is None else 0.5 * f * float(np.linalg.norm(rig.T_right_left_mm)) / z
            ray = pixel_rays(rig.left, np.array([[place[0] * (w - 1) + shift, place[1] * (h - 1)]]))[0]
            t = ray * z - R @ centre
            ok = np.all(np.isfinite(t)) and board_fits(rig.left, outline @ R.T + t, 6.0)[0]
            if ok and rig.right is not None:
                Rr, tr = stereo_right_pose(R, t, rig.R_right_left, rig.T_right_left_mm)
                ok = board_fits(rig.right, outline @ Rr.T + tr, 6.0)[0]
            if ok:
                poses.append((R, t))
                break
            place = 0.5 + 0.93 * (place - 0.5)
            sq *= 0.97
        else:
            raise ValueError(f"a {b.cols}x{b.rows} board does not fit a {w}x{h} image at pose {k}")
    return poses


def _interpolate(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray], s: float
                 ) -> tuple[np.ndarray, np.ndarray]:
    """The pose a fraction ``s`` of the way from ``a`` to ``b`` (rotation along the geodesic)."""
    rel = cv2.Rodrigues(a[0].T @ b[0])[0]
    return a[0] @ cv2.Rodrigues(rel * s)[0], (1 - s) * a[1] + s * b[1]


def handheld_sequence(seed: SeedLike, rig: HandheldRig, n_poses: int = 12, hold_frames: int = 5,
                      move_frames: int = 4, fps: float = 30.0, photometric: Photometric | str = "clean",
                      supersampling: int = 4) -> Iterator[HandheldFrame]:
    """Render the session frame by frame: at each of ``n_poses`` poses the board is held for
    ``hold_frames`` frames, then carried to the next over ``move_frames`` frames (smoothstep)."""
    rng = scene_rng(seed, "handheld")
    poses = _key_poses(rng, rig, n_poses)
    phot = scene_photometric(rng, photometric)
    b = rig.board
    panel = Panel(b.name, np.zeros(3), np.array([1.0, 0, 0]), np.array([0, 1.0, 0]),
                  board_panel_extent(b, 1.0 * b.square_mm), b, 0.08, 0.85)
    background = float(rng.uniform(0.35, 0.55))
    index = 0
    for k, pose in enumerate(poses):
        steps: list[tuple[tuple[np.ndarray, np.ndarray], bool]] = []
        for _ in range(hold_frames):
            jitter = rotation_about(rng.normal(size=3), np.radians(rng.normal(0, TREMOR_DEG)))
            steps.append(((jitter @ pose[0], pose[1] + rng.normal(0, TREMOR_MM, 3)), False))
        if k + 1 < len(poses):
            for m in range(1, move_frames + 1):
                s = m / (move_frames + 1)
                steps.append((_interpolate(pose, poses[k + 1], s * s * (3 - 2 * s)), True))
        for (R, t), moving in steps:
            left = render_view(rig.left, [panel], R, t, background=background, photometric=phot, rng=rng,
                               supersampling=supersampling, extra={"category": "handheld", "moving": moving},
                               camera_name="left")
            right = None
            if rig.right is not None:
                Rr, tr = stereo_right_pose(R, t, rig.R_right_left, rig.T_right_left_mm)
                right = render_view(rig.right, [panel], Rr, tr, background=background, photometric=phot,
                                    rng=rng, supersampling=supersampling,
                                    extra={"category": "handheld", "moving": moving}, camera_name="right")
            yield HandheldFrame(index, int(round(index * 1e9 / fps)), left, right, moving)
            index += 1
