"""Ray-casting planar panels (chessboards and plain plates) through a camera of any lens model.

The scene is a list of :class:`~edgecal.synth.panels.Panel` in the world frame. Rays are cast through every
pixel *corner* (the lens model's exact inverse, edgecal.camera.unproject; fisheye rays may point behind the camera
plane, so a 190 degree lens renders too; see camera.py) and each corner gets a label: which panel is in front and
which cell of its pattern it falls in (a square, or a margin strip). A pixel whose four corners share
one label lies entirely inside one convex cell, so it is uniform and costs nothing more. Every other
pixel (an edge, an X-junction, a panel outline, an occlusion boundary) is supersampled with n x n
stratified, jittered rays, so the pixel value is its true area average (box filter) to ~1/n^2; the
jitter is a fixed hash of the pixel, so renders are deterministic and the estimate unbiased.

The output of this module is linear radiance (albedo x 1); photometric.py turns it into an 8-bit image.
The panels and their packed array are panels.py's.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from edgecal.camera import CameraModel
from edgecal.synth.camera import corner_ray_grid
from edgecal.synth.panels import (
    BACK,
    BBOX,
    BLACK,
    COLS,
    FRONT,
    ROWS,
    SQUARE,
    WHITE,
    Panel,
    outside_panel,
    pack_panels,
    panel_uv,
    ray_plane,
)


@njit(cache=True, nogil=True)
def _hit(x: float, y: float, z: float, panels: np.ndarray) -> tuple[int, int, int, float, float, float]:
    """Front-most panel hit by the ray (x, y, z): (panel, cell i, cell j, albedo, u, v); panel -1 = background.

    Pinhole grids have z = 1 (the arithmetic is then that of the ray (x, y, 1)); fisheye rays are unit
    vectors, possibly with z <= 0.
    """
    best_t = np.inf
    best = -1
    bu = 0.0
    bv = 0.0
    for p in range(panels.shape[0]):
        if z > 0.0:
            xz = x / z
            yz = y / z
            if (xz < panels[p, BBOX] or xz > panels[p, BBOX + 2] or yz < panels[p, BBOX + 1]
                    or yz > panels[p, BBOX + 3]):
                continue
        elif panels[p, BBOX] > -np.inf:
            continue  # the panel lies entirely in front of the camera plane; this ray does not
        t = ray_plane(x, y, z, panels, p)
        if t <= 0.0 or t >= best_t:
            continue
        u, v = panel_uv(t, x, y, z, panels, p)
        if outside_panel(u, v, panels, p):
            continue
        best_t = t
        best = p
        bu = u
        bv = v
    if best < 0:
        return -1, 0, 0, 0.0, 0.0, 0.0
    if panels[best, FRONT] == 0.0:
        return best, -99, -99, panels[best, BACK], bu, bv
    s = panels[best, SQUARE]
    if s <= 0.0:
        return best, 0, 0, panels[best, WHITE], bu, bv
    cols = int(panels[best, COLS])
    rows = int(panels[best, ROWS])
    # Cells: squares -1..cols-1 / -1..rows-1, margins clamped to -2 and cols / rows (all cells convex).
    i = int(np.floor(bu / s))
    j = int(np.floor(bv / s))
    i = min(max(i, -2), cols)
    j = min(max(j, -2), rows)
    if i < -1 or i > cols - 1 or j < -1 or j > rows - 1:
        return best, i, j, panels[best, WHITE], bu, bv
    if (i + j) % 2 == 0:
        return best, i, j, panels[best, BLACK], bu, bv
    return best, i, j, panels[best, WHITE], bu, bv


@njit(cache=True, nogil=True)
def _hash01(a: int, b: int, c: int) -> float:
    """A fixed pseudo-random number in [0, 1) from three small non-negative integers.

    32-bit mixing with multipliers below 2^31, so no int64 product can overflow (bit-exact everywhere).
    """
    h = ((a * 73856093) ^ (b * 19349663) ^ (c * 83492791)) & 0xFFFFFFFF
    h ^= h >> 16
    h = (h * 0x7FEB352D) & 0xFFFFFFFF
    h ^= h >> 15
    h = (h * 0x2C1B3C6D) & 0xFFFFFFFF
    h ^= h >> 16
    return (h >> 8) / 16777216.0


@njit(cache=True, nogil=True)
def _negative_area(c: float, ga: float, gb: float) -> float:
    """Area of {(a, b) in [0, 1]^2 : c + ga a + gb b < 0} (clip the unit square by a half-plane)."""
    px = np.array([0.0, 1.0, 1.0, 0.0])
    py = np.array([0.0, 0.0, 1.0, 1.0])
    qx = np.empty(8)
    qy = np.empty(8)
    n = 0
    for k in range(4):
        x0, y0 = px[k], py[k]
        x1, y1 = px[(k + 1) % 4], py[(k + 1) % 4]
        f0 = c + ga * x0 + gb * y0
        f1 = c + ga * x1 + gb * y1
        if f0 < 0.0:
            qx[n] = x0
            qy[n] = y0
            n += 1
        if (f0 < 0.0) != (f1 < 0.0):
            t = f0 / (f0 - f1)
            qx[n] = x0 + t * (x1 - x0)
            qy[n] = y0 + t * (y1 - y0)
            n += 1
    area = 0.0
    for k in range(n):
        area += qx[k] * qy[(k + 1) % n] - qx[(k + 1) % n] * qy[k]
    return 0.5 * abs(area)


@njit(cache=True, nogil=True)
def _supersample(i: int, j: int, rx: np.ndarray, ry: np.ndarray, rz: np.ndarray, panels: np.ndarray, bg: float,
                 n: int) -> tuple[float, float]:
    """Box-filtered albedo and panel coverage of pixel (i, j) from n x n stratified, jittered rays."""
    x00 = rx[i, j]
    x10 = rx[i, j + 1]
    x01 = rx[i + 1, j]
    x11 = rx[i + 1, j + 1]
    y00 = ry[i, j]
    y10 = ry[i, j + 1]
    y01 = ry[i + 1, j]
    y11 = ry[i + 1, j + 1]
    z00 = rz[i, j]
    z10 = rz[i, j + 1]
    z01 = rz[i + 1, j]
    z11 = rz[i + 1, j + 1]
    acc = 0.0
    cov = 0.0
    for si in range(n):
        for sj in range(n):
            # One sample per sub-cell, at a position fixed by a hash of the pixel (deterministic, unbiased).
            k = si * n + sj
            a = (sj + _hash01(i, j, 2 * k)) / n
            b = (si + _hash01(i, j, 2 * k + 1)) / n
            wa = 1.0 - a
            wb = 1.0 - b
            x = wb * (wa * x00 + a * x10) + b * (wa * x01 + a * x11)
            y = wb * (wa * y00 + a * y10) + b * (wa * y01 + a * y11)
            z = wb * (wa * z00 + a * z10) + b * (wa * z01 + a * z11)
            p, _ci, _cj, alb, _u, _v = _hit(x, y, z, panels)
            if p >= 0:
                acc += alb
                cov += 1.0
            else:
                acc += bg
    inv = 1.0 / (n * n)
    return acc * inv, cov * inv


@njit(cache=True, nogil=True)
def _raycast(rx: np.ndarray, ry: np.ndarray, rz: np.ndarray, panels: np.ndarray, background: np.ndarray, n_ss: int,
             n_junction: int, out: np.ndarray, coverage: np.ndarray) -> int:
    """Fill ``out`` (h, w) with the area-averaged albedo; returns the number of supersampled pixels.

    Pixel kinds: uniform (four equal corner labels) -> the cell's albedo; one straight square edge
    (two adjacent cells of one board) -> exact area on each side of the edge line, from an affine fit of
    the board coordinate across the pixel; X-junctions (3+ labels) -> n_junction^2 rays; anything else
    (panel outlines, occlusion boundaries) -> n_ss^2 rays.
    """
    gh, gw = rx.shape
    labels = np.empty((gh, gw), dtype=np.int64)
    albedo = np.zeros((gh, gw), dtype=np.float64)
    gu = np.zeros((gh, gw), dtype=np.float64)
    gv = np.zeros((gh, gw), dtype=np.float64)
    for i in range(gh):
        for j in range(gw):
            x = rx[i, j]
            y = ry[i, j]
            if x != x or y != y:
                labels[i, j] = -2  # outside the camera model's valid range
                continue
            p, ci, cj, a, u, v = _hit(x, y, rz[i, j], panels)
            labels[i, j] = -1 if p < 0 else (p * 1000 + (ci + 100)) * 1000 + (cj + 100)
            albedo[i, j] = a
            gu[i, j] = u
            gv[i, j] = v
    h = gh - 1
    w = gw - 1
    n_sampled = 0
    for i in range(h):
        for j in range(w):
            l00 = labels[i, j]
            l10 = labels[i, j + 1]
            l01 = labels[i + 1, j]
            l11 = labels[i + 1, j + 1]
            bg = background[i, j]
            if l00 == l10 and l00 == l01 and l00 == l11 and l00 != -2:
                out[i, j] = bg if l00 < 0 else albedo[i, j]
                coverage[i, j] = 0.0 if l00 < 0 else 1.0
                continue
            if l00 == -2 or l10 == -2 or l01 == -2 or l11 == -2:
                out[i, j] = bg
                coverage[i, j] = 0.0
                continue
            # Distinct labels among the four corners.
            la = l00
            lb = l00
            n_lab = 1
            for lab in (l10, l01, l11):
                if lab != la and (n_lab == 1 or lab != lb):
                    if n_lab == 1:
                        lb = lab
                    n_lab += 1
            if n_lab == 2 and la >= 0 and lb >= 0 and la // 1000000 == lb // 1000000:
                p = la // 1000000
                ia = (la // 1000) % 1000 - 100
                ja = la % 1000 - 100
                ib = (lb // 1000) % 1000 - 100
                jb = lb % 1000 - 100
                s = panels[p, SQUARE]
                if s > 0.0 and ia != -99 and ((abs(ia - ib) == 1 and ja == jb) or (abs(ja - jb) == 1 and ia == ib)):
                    # One straight grid line u = k s (or v = k s) crosses the pixel.
                    g = gu if ia != ib else gv
                    edge = s * max(ia, ib) if ia != ib else s * max(ja, jb)
                    f00 = g[i, j] - edge
                    f10 = g[i, j + 1] - edge
                    f01 = g[i + 1, j] - edge
                    f11 = g[i + 1, j + 1] - edge
                    ga = 0.5 * ((f10 - f00) + (f11 - f01))
                    gb = 0.5 * ((f01 - f00) + (f11 - f10))
                    c = 0.25 * (f00 + f10 + f01 + f11) - 0.5 * ga - 0.5 * gb
                    low = _negative_area(c, ga, gb)  # the part in the cell with the smaller index
                    # Albedo of each cell, from a corner that lies in it.
                    a_low = 0.0
                    a_high = 0.0
                    for (ii, jj) in ((i, j), (i, j + 1), (i + 1, j), (i + 1, j + 1)):
                        if (g[ii, jj] - edge) < 0.0:
                            a_low = albedo[ii, jj]
                        else:
                            a_high = albedo[ii, jj]
                    out[i, j] = low * a_low + (1.0 - low) * a_high
                    coverage[i, j] = 1.0
                    continue
            p00 = l00 // 1000000
            one_panel = (l00 >= 0 and l10 // 1000000 == p00 and l01 // 1000000 == p00
                         and l11 // 1000000 == p00 and l10 >= 0 and l01 >= 0 and l11 >= 0)
            n_square_cells = 0
            if one_panel and panels[p00, SQUARE] > 0.0:
                cols = int(panels[p00, COLS])
                rows = int(panels[p00, ROWS])
                for lab in (l00, l10, l01, l11):
                    ci = (lab // 1000) % 1000 - 100
                    cj = lab % 1000 - 100
                    if -1 <= ci <= cols - 1 and -1 <= cj <= rows - 1:
                        n_square_cells += 1
            n_sampled += 1
            # Junctions of the squares (X inside, T on the border) decide corner positions: sample densely.
            dense = n_lab >= 3 and one_panel and n_square_cells >= 1
            val, cov = _supersample(i, j, rx, ry, rz, panels, bg, n_junction if dense else n_ss)
            out[i, j] = val
            coverage[i, j] = cov
    return n_sampled


@njit(cache=True, nogil=True)
def _raycast_every_pixel(rx: np.ndarray, ry: np.ndarray, rz: np.ndarray, panels: np.ndarray, background: np.ndarray,
                         n_ss: int,
                         out: np.ndarray) -> None:
    for i in range(out.shape[0]):
        for j in range(out.shape[1]):
            if rx[i, j] != rx[i, j] or rx[i, j + 1] != rx[i, j + 1] or rx[i + 1, j] != rx[i + 1, j] \
                    or rx[i + 1, j + 1] != rx[i + 1, j + 1]:
                out[i, j] = background[i, j]
                continue
            out[i, j] = _supersample(i, j, rx, ry, rz, panels, background[i, j], n_ss)[0]


def render_radiance_reference(camera: CameraModel, panels: list[Panel], R_cam_world: np.ndarray,
                              t_cam_world_mm: np.ndarray, background: float = 0.5, n: int = 24) -> np.ndarray:
    """Brute-force reference for tests: every pixel averaged over n x n jittered rays, no shortcuts."""
    w, h = camera.image_size
    bg = np.full((h, w), float(background), dtype=np.float32)
    rx, ry, rz = corner_ray_grid(camera)
    out = np.empty((h, w), dtype=np.float32)
    _raycast_every_pixel(rx, ry, rz, pack_panels(panels, R_cam_world, t_cam_world_mm), bg, int(n), out)
    return out


def render_radiance(camera: CameraModel, panels: list[Panel], R_cam_world: np.ndarray,
                    t_cam_world_mm: np.ndarray, background: np.ndarray | float = 0.5,
                    supersampling: int = 12, junction_supersampling: int = 32) -> tuple[np.ndarray, np.ndarray]:
    """Area-averaged albedo image (h, w) float32 of ``panels`` over ``background``, and panel coverage.

    ``background`` is a float (uniform) or an (h, w) array of albedo in [0, 1] seen behind the panels.
    ``supersampling`` is n: outline and occlusion pixels get n x n rays; X-junction pixels get
    ``junction_supersampling``^2; straight square edges are integrated exactly.
    """
    w, h = camera.image_size
    if np.isscalar(background):
        # np.isscalar does not narrow the type for mypy
        bg = np.full((h, w), float(background), dtype=np.float32)  # type: ignore[arg-type]
    else:
        bg = np.ascontiguousarray(background, dtype=np.float32)
        if bg.shape != (h, w):
            raise ValueError(f"background has shape {bg.shape}, the camera image is {(h, w)}")
    rx, ry, rz = corner_ray_grid(camera)
    packed = pack_panels(panels, R_cam_world, t_cam_world_mm)
    out = np.empty((h, w), dtype=np.float32)
    coverage = np.empty((h, w), dtype=np.float32)
    if len(panels) == 0:
        return bg.copy(), np.zeros((h, w), dtype=np.float32)
    _raycast(rx, ry, rz, packed, bg, int(supersampling), int(max(supersampling, junction_supersampling)), out, coverage)
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
def _unoccluded(x: float, y: float, z: float, panels: np.ndarray, own: int) -> bool:
    """No panel but ``own`` crosses the segment from the camera to the point (x, y, z) (any direction)."""
    dist = np.sqrt(x * x + y * y + z * z)
    for p in range(panels.shape[0]):
        if p == own:
            continue
        t = ray_plane(x, y, z, panels, p)
        # as for points in front: a panel flush with this one (within 1e-3 mm) does not occlude it
        if t <= 0.0 or t >= 1.0 - 1e-6 - 1e-3 / dist:
            continue
        u, v = panel_uv(t, x, y, z, panels, p)
        if not outside_panel(u, v, panels, p):
            return False
    return True


@njit(cache=True, nogil=True)
def _visible_kernel(pts: np.ndarray, panels: np.ndarray, own: int) -> np.ndarray:
    out = np.zeros(pts.shape[0], dtype=np.bool_)
    if panels[own, FRONT] == 0.0:
        return out
    for k in range(pts.shape[0]):
        z = pts[k, 2]
        if z <= 0.0:
            # beside or behind the camera plane (a fisheye sees it): the ray is the point itself, t in (0, 1)
            out[k] = _unoccluded(pts[k, 0], pts[k, 1], z, panels, own)
            continue
        x = pts[k, 0] / z
        y = pts[k, 1] / z
        ok = True
        for p in range(panels.shape[0]):
            if p == own:
                continue
            t = ray_plane(x, y, 1.0, panels, p)  # the ray (x, y, 1): t is a depth
            # A panel flush with this one (a robot face under a board) does not occlude it.
            if t <= 0.0 or t >= z - 1e-6 * z - 1e-3:
                continue
            u, v = panel_uv(t, x, y, 1.0, panels, p)
            if not outside_panel(u, v, panels, p):
                ok = False
                break
        out[k] = ok
    return out
