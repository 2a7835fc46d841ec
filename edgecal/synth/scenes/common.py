"""What the scene generators share: seeds and random streams, random cameras, placing a board in view.

Every scene is deterministic from its seed: :func:`scene_rng` gives each scene kind its own stream.
"""

from __future__ import annotations

import numpy as np

from edgecal.camera import CameraModel
from edgecal.geometry import rotation_about
from edgecal.synth.camera import camera_from_fov, pixel_rays
from edgecal.synth.clutter import clutter_background, uniform_background
from edgecal.synth.photometric import Photometric, random_photometric
from edgecal.targets import Board

#: A seed: an int, or a tuple of ints (e.g. (set seed, image index)).
SeedLike = int | tuple[int, ...]
#: A fixed value, or a (low, high) range drawn uniformly.
FloatOrRange = float | tuple[float, float]


def seed_list(seed: SeedLike) -> list[int]:
    """The seed as a list of ints (what numpy's generator and the truth's ``seed`` field take)."""
    return [int(v) for v in seed] if isinstance(seed, (tuple, list)) else [int(seed)]


def scene_rng(seed: SeedLike, tag: str) -> np.random.Generator:
    """The random stream of scene kind ``tag`` for ``seed``: scene kinds never share random numbers."""
    return np.random.default_rng(seed_list(seed) + [sum(ord(c) * 31 ** i for i, c in enumerate(tag)) % (2 ** 31)])


def pick(rng: np.random.Generator, value: FloatOrRange) -> float:
    """``value`` itself, or a uniform draw from a (low, high) range."""
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
        return camera_from_fov(size, pick(rng, hfov), tuple(params), off, float(rng.uniform(0.997, 1.003)),
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
    return camera_from_fov(size, pick(rng, hfov_deg), tuple(dist), off, float(rng.uniform(0.997, 1.003)))


def scene_photometric(rng: np.random.Generator, photometric: Photometric | str) -> Photometric:
    """Given conditions, or random ones of the named level (random_photometric)."""
    return photometric if isinstance(photometric, Photometric) else random_photometric(rng, photometric)


def scene_background(rng: np.random.Generator, size: tuple[int, int], background: str) -> tuple[np.ndarray, list[str]]:
    """The albedo behind the panels (h, w) and the distractors drawn on it: clutter, plain-clutter or uniform."""
    if background == "clutter":
        return clutter_background(rng, size)
    if background == "plain-clutter":
        return clutter_background(rng, size, distractors=[])
    if background == "uniform":
        return uniform_background(size, float(rng.uniform(0.3, 0.6))), []
    raise ValueError(f"unknown background {background!r} (clutter, plain-clutter, uniform)")


def squares_outline(board: Board, n: int = 12) -> np.ndarray:
    """Board-frame points (mm) along the outer edge of the squares area (what must be in the image)."""
    s = board.square_mm
    u0, v0, u1, v1 = -s, -s, board.cols * s, board.rows * s
    t = np.linspace(0.0, 1.0, n, endpoint=False)
    edges = [np.stack([u0 + (u1 - u0) * t, np.full(n, v0)], 1), np.stack([np.full(n, u1), v0 + (v1 - v0) * t], 1),
             np.stack([u1 - (u1 - u0) * t, np.full(n, v1)], 1), np.stack([np.full(n, u0), v1 - (v1 - v0) * t], 1)]
    uv = np.concatenate(edges)
    return np.concatenate([uv, np.zeros((len(uv), 1))], axis=1)


def board_fits(camera: CameraModel, pts_cam: np.ndarray, margin_px: float,
               taken: list[tuple[float, float, float, float]] | None = None
               ) -> tuple[bool, tuple[float, float, float, float]]:
    """Whether points (N, 3) in the camera frame project ``margin_px`` inside the image and their pixel box
    misses every box in ``taken``; and that box (x0, y0, x1, y1)."""
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
    outline = squares_outline(board)
    w, h = camera.image_size
    for _ in range(tries):
        roll = np.radians(pick(rng, roll_deg))
        tilt = np.radians(rng.uniform(0.0, tilt_max_deg)) if tilt_max_deg > 0 else 0.0
        phi = rng.uniform(0.0, 2 * np.pi)
        R = (rotation_about(np.array([np.cos(phi), np.sin(phi), 0.0]), tilt)
             @ rotation_about(np.array([0, 0, 1.0]), roll))
        # Where the centre goes: a random pixel, undistorted to a ray at depth z.
        px = np.array([[rng.uniform(0.1, 0.9) * (w - 1), rng.uniform(0.1, 0.9) * (h - 1)]])
        ray = pixel_rays(camera, px)[0]
        if not np.all(np.isfinite(ray)):
            continue
        t = ray * z - R @ centre
        ok, box = board_fits(camera, outline @ R.T + t, margin_px, taken)
        if ok:
            return R, t, box
    return None


