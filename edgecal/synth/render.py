"""Ray-casting planar panels (chessboards and plain plates) through a distorted pinhole camera.

The scene is a list of :class:`Panel` in the world frame. Rays are cast through every pixel *corner*
(exact inverse distortion, see camera.py) and each corner gets a label: which panel is in front and
which cell of its pattern it falls in (a square, or a margin strip). A pixel whose four corners share
one label lies entirely inside one convex cell, so it is uniform and costs nothing more. Every other
pixel (an edge, an X-junction, a panel outline, an occlusion boundary) is supersampled with n x n
stratified, jittered rays, so the pixel value is its true area average (box filter) to ~1/n^2; the
jitter is a fixed hash of the pixel, so renders are deterministic and the estimate unbiased.

The output of this module is linear radiance (albedo x 1); photometric.py turns it into an 8-bit image.
Printed side: a board's pattern faces the side opposite its normal x_axis × y_axis (the board's z axis
points away from a camera that sees the pattern, as in OpenCV); from behind, a panel shows ``back_albedo``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from edgecal.synth.camera import CameraModel
from edgecal.targets import Board, Target

# Columns of the packed per-panel array handed to the kernels (camera frame, mm).
_O, _EX, _EY, _N = 0, 3, 6, 9
_UMIN, _VMIN, _UMAX, _VMAX = 12, 13, 14, 15
_SQUARE, _COLS, _ROWS = 16, 17, 18
_BLACK, _WHITE, _BACK, _FRONT = 19, 20, 21, 22
_NCOL = 23


@dataclass(frozen=True)
class Panel:
    """A flat rectangle in the world frame, optionally printed with a chessboard.

    ``origin_mm`` is the board's inner corner (0, 0) (or any reference point of a plain panel);
    ``extent_mm`` = (umin, vmin, umax, vmax) is the rectangle along ``x_axis``/``y_axis`` relative to it.
    ``board`` is None for a plain panel (uniform ``white_albedo`` on its front).
    """

    name: str
    origin_mm: np.ndarray
    x_axis: np.ndarray
    y_axis: np.ndarray
    extent_mm: tuple[float, float, float, float]
    board: Board | None = None
    black_albedo: float = 0.06
    white_albedo: float = 0.85
    back_albedo: float = 0.55

    @property
    def normal(self) -> np.ndarray:
        """Unit normal x_axis × y_axis; the printed side faces -normal."""
        return np.cross(self.x_axis, self.y_axis)


def board_panel_extent(board: Board, margin_mm: float | None = None) -> tuple[float, float, float, float]:
    """Extent of a board's panel: the squares plus a white margin (default: one square, at least 6 mm)."""
    s = board.square_mm
    m = max(s, 6.0) if margin_mm is None else float(margin_mm)
    return (-s - m, -s - m, board.cols * s + m, board.rows * s + m)


def panels_from_target(target: Target, R_world_target: np.ndarray = np.eye(3),
                       t_world_target_mm: np.ndarray = np.zeros(3), *,
                       extents: dict[str, tuple[float, float, float, float]] | None = None,
                       margin_mm: float | None = None, black_albedo: float = 0.06,
                       white_albedo: float = 0.85) -> list[Panel]:
    """One printed Panel per board of ``target``, placed in the world by the pose T_world_target.

    ``extents`` overrides the panel rectangle of named boards (e.g. a whole face of the calibration box).
    """
    R = np.asarray(R_world_target, dtype=np.float64)
    t = np.asarray(t_world_target_mm, dtype=np.float64).ravel()
    out = []
    for b in target.boards:
        ext = (extents or {}).get(b.name) or board_panel_extent(b, margin_mm)
        out.append(Panel(b.name, R @ b.origin_mm + t, R @ b.x_axis, R @ b.y_axis, tuple(float(v) for v in ext),
                         b, black_albedo, white_albedo))
    return out


def pack_panels(panels: list[Panel], R_cam_world: np.ndarray, t_cam_world_mm: np.ndarray) -> np.ndarray:
    """The (P, 23) float64 array of panels in the camera frame that the kernels read."""
    R = np.asarray(R_cam_world, dtype=np.float64)
    t = np.asarray(t_cam_world_mm, dtype=np.float64).ravel()
    arr = np.zeros((len(panels), _NCOL))
    for i, p in enumerate(panels):
        o = R @ np.asarray(p.origin_mm, dtype=np.float64) + t
        ex = R @ np.asarray(p.x_axis, dtype=np.float64)
        ey = R @ np.asarray(p.y_axis, dtype=np.float64)
        n = np.cross(ex, ey)
        arr[i, _O:_O + 3] = o
        arr[i, _EX:_EX + 3] = ex
        arr[i, _EY:_EY + 3] = ey
        arr[i, _N:_N + 3] = n
        arr[i, _UMIN:_VMAX + 1] = p.extent_mm
        if p.board is not None:
            arr[i, _SQUARE] = p.board.square_mm
            arr[i, _COLS] = p.board.cols
            arr[i, _ROWS] = p.board.rows
        arr[i, _BLACK] = p.black_albedo
        arr[i, _WHITE] = p.white_albedo
        arr[i, _BACK] = p.back_albedo
        # The camera (origin) sees the printed side when it lies on the -normal side of the plane.
        arr[i, _FRONT] = 1.0 if float(n @ o) > 0.0 else 0.0
    return arr


@njit(cache=True, nogil=True)
def _hit(x: float, y: float, panels: np.ndarray) -> tuple[int, int, int, float]:
    """Front-most panel hit by the ray (x, y, 1): (panel, cell i, cell j, albedo); panel -1 = background."""
    best_t = np.inf
    best = -1
    bu = 0.0
    bv = 0.0
    for p in range(panels.shape[0]):
        nx = panels[p, 9]
        ny = panels[p, 10]
        nz = panels[p, 11]
        den = nx * x + ny * y + nz
        if abs(den) < 1e-15:
            continue
        t = (nx * panels[p, 0] + ny * panels[p, 1] + nz * panels[p, 2]) / den
        if t <= 0.0 or t >= best_t:
            continue
        dx = t * x - panels[p, 0]
        dy = t * y - panels[p, 1]
        dz = t - panels[p, 2]
        u = dx * panels[p, 3] + dy * panels[p, 4] + dz * panels[p, 5]
        v = dx * panels[p, 6] + dy * panels[p, 7] + dz * panels[p, 8]
        if u < panels[p, 12] or u > panels[p, 14] or v < panels[p, 13] or v > panels[p, 15]:
            continue
        best_t = t
        best = p
        bu = u
        bv = v
    if best < 0:
        return -1, 0, 0, 0.0
    if panels[best, 22] == 0.0:
        return best, -99, -99, panels[best, 21]
    s = panels[best, 16]
    if s <= 0.0:
        return best, 0, 0, panels[best, 20]
    cols = int(panels[best, 17])
    rows = int(panels[best, 18])
    # Cells: squares -1..cols-1 / -1..rows-1, margins clamped to -2 and cols / rows (all cells convex).
    i = int(np.floor(bu / s))
    j = int(np.floor(bv / s))
    i = min(max(i, -2), cols)
    j = min(max(j, -2), rows)
    if i < -1 or i > cols - 1 or j < -1 or j > rows - 1:
        return best, i, j, panels[best, 20]
    if (i + j) % 2 == 0:
        return best, i, j, panels[best, 19]
    return best, i, j, panels[best, 20]


@njit(cache=True, nogil=True)
def _hash01(a: int, b: int, c: int) -> float:
    """A fixed pseudo-random number in [0, 1) from three integers (splitmix64-style mixing)."""
    h = (a * 0x9E3779B1 + b * 0x85EBCA77 + c * 0xC2B2AE3D + 0x27D4EB2F) & 0xFFFFFFFFFFFF
    h ^= h >> 23
    h = (h * 0x2127599BF4325C37) & 0xFFFFFFFFFFFF
    h ^= h >> 27
    h = (h * 0x94D049BB1331) & 0xFFFFFFFFFFFF
    h ^= h >> 21
    return (h & 0xFFFFFF) / 16777216.0


@njit(cache=True, nogil=True)
def _raycast(rx: np.ndarray, ry: np.ndarray, panels: np.ndarray, background: np.ndarray, n_ss: int,
             out: np.ndarray, coverage: np.ndarray) -> int:
    """Fill ``out`` (h, w) with the area-averaged albedo; returns the number of supersampled pixels."""
    gh, gw = rx.shape
    labels = np.empty((gh, gw), dtype=np.int64)
    albedo = np.zeros((gh, gw), dtype=np.float64)
    for i in range(gh):
        for j in range(gw):
            x = rx[i, j]
            y = ry[i, j]
            if x != x or y != y:
                labels[i, j] = -2  # outside the camera model's valid range
                continue
            p, ci, cj, a = _hit(x, y, panels)
            labels[i, j] = -1 if p < 0 else (p * 1000 + (ci + 100)) * 1000 + (cj + 100)
            albedo[i, j] = a
    h = gh - 1
    w = gw - 1
    n_edge = 0
    inv = 1.0 / (n_ss * n_ss)
    for i in range(h):
        for j in range(w):
            l00 = labels[i, j]
            bg = background[i, j]
            if l00 == labels[i, j + 1] and l00 == labels[i + 1, j] and l00 == labels[i + 1, j + 1] and l00 != -2:
                if l00 < 0:
                    out[i, j] = bg
                    coverage[i, j] = 0.0
                else:
                    out[i, j] = albedo[i, j]
                    coverage[i, j] = 1.0
                continue
            n_edge += 1
            x00 = rx[i, j]
            x10 = rx[i, j + 1]
            x01 = rx[i + 1, j]
            x11 = rx[i + 1, j + 1]
            y00 = ry[i, j]
            y10 = ry[i, j + 1]
            y01 = ry[i + 1, j]
            y11 = ry[i + 1, j + 1]
            if x00 != x00 or x10 != x10 or x01 != x01 or x11 != x11:
                out[i, j] = bg
                coverage[i, j] = 0.0
                continue
            acc = 0.0
            cov = 0.0
            for si in range(n_ss):
                for sj in range(n_ss):
                    # Stratified jitter: one sample per sub-cell, position fixed by a hash of the pixel.
                    k = si * n_ss + sj
                    a = (sj + _hash01(i, j, 2 * k)) / n_ss
                    b = (si + _hash01(i, j, 2 * k + 1)) / n_ss
                    wa = 1.0 - a
                    wb = 1.0 - b
                    x = wb * (wa * x00 + a * x10) + b * (wa * x01 + a * x11)
                    y = wb * (wa * y00 + a * y10) + b * (wa * y01 + a * y11)
                    p, ci, cj, alb = _hit(x, y, panels)
                    if p >= 0:
                        acc += alb
                        cov += 1.0
                    else:
                        acc += bg
            out[i, j] = acc * inv
            coverage[i, j] = cov * inv
    return n_edge


def render_radiance(camera: CameraModel, panels: list[Panel], R_cam_world: np.ndarray,
                    t_cam_world_mm: np.ndarray, background: np.ndarray | float = 0.5,
                    supersampling: int = 12) -> tuple[np.ndarray, np.ndarray]:
    """Area-averaged albedo image (h, w) float32 of ``panels`` over ``background``, and panel coverage.

    ``background`` is a float (uniform) or an (h, w) array of albedo in [0, 1] seen behind the panels.
    ``supersampling`` is n: edge pixels get n x n rays.
    """
    w, h = camera.size
    if np.isscalar(background):
        bg = np.full((h, w), float(background), dtype=np.float32)
    else:
        bg = np.ascontiguousarray(background, dtype=np.float32)
        if bg.shape != (h, w):
            raise ValueError(f"background has shape {bg.shape}, the camera image is {(h, w)}")
    rx, ry = camera.corner_ray_grid()
    packed = pack_panels(panels, R_cam_world, t_cam_world_mm)
    out = np.empty((h, w), dtype=np.float32)
    coverage = np.empty((h, w), dtype=np.float32)
    if len(panels) == 0:
        return bg.copy(), np.zeros((h, w), dtype=np.float32)
    _raycast(rx, ry, packed, bg, int(supersampling), out, coverage)
    return out, coverage


def visible_mask(camera: CameraModel, panels: list[Panel], R_cam_world: np.ndarray,
                 t_cam_world_mm: np.ndarray, panel_index: int, points_world: np.ndarray) -> np.ndarray:
    """For points on panel ``panel_index``: True where its printed side faces the camera and no other
    panel is in front of it (ray test through the point itself)."""
    R = np.asarray(R_cam_world, dtype=np.float64)
    t = np.asarray(t_cam_world_mm, dtype=np.float64).ravel()
    packed = pack_panels(panels, R, t)
    pts = np.asarray(points_world, dtype=np.float64).reshape(-1, 3) @ R.T + t
    return _visible_kernel(np.ascontiguousarray(pts), packed, int(panel_index))


@njit(cache=True, nogil=True)
def _visible_kernel(pts: np.ndarray, panels: np.ndarray, own: int) -> np.ndarray:
    out = np.zeros(pts.shape[0], dtype=np.bool_)
    if panels[own, 22] == 0.0:
        return out
    for k in range(pts.shape[0]):
        z = pts[k, 2]
        if z <= 0.0:
            continue
        x = pts[k, 0] / z
        y = pts[k, 1] / z
        ok = True
        for p in range(panels.shape[0]):
            if p == own:
                continue
            nx = panels[p, 9]
            ny = panels[p, 10]
            nz = panels[p, 11]
            den = nx * x + ny * y + nz
            if abs(den) < 1e-15:
                continue
            t = (nx * panels[p, 0] + ny * panels[p, 1] + nz * panels[p, 2]) / den
            # A panel flush with this one (a robot face under a board) does not occlude it.
            if t <= 0.0 or t >= z - 1e-6 * z - 1e-3:
                continue
            dx = t * x - panels[p, 0]
            dy = t * y - panels[p, 1]
            dz = t - panels[p, 2]
            u = dx * panels[p, 3] + dy * panels[p, 4] + dz * panels[p, 5]
            v = dx * panels[p, 6] + dy * panels[p, 7] + dz * panels[p, 8]
            if panels[p, 12] <= u <= panels[p, 14] and panels[p, 13] <= v <= panels[p, 15]:
                ok = False
                break
        out[k] = ok
    return out
