"""Completing a grid: corners the probe missed are predicted from their neighbours and verified.

Noise, glare or a shadow can make the probe reject a few true corners, which leaves holes (or a missing
outer row) in a grid. Each missing label is predicted by a homography fitted to the nearby labelled
corners (local, so lens distortion does not matter), refined to sub-pixel, and accepted only if the probe
confirms a chessboard corner there and the refinement stayed near the prediction. Rows and columns are
added at the grid's sides the same way (each point extrapolated along its own grid line, the homography
its second chance), so a grid grows up to the board's edge and stops at its margin.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
from numba import njit

from edgecal.detection.candidates import snap_to_saddle
from edgecal.detection.levels import Level
from edgecal.detection.params import DetectorParams
from edgecal.detection.probe import (
    EDGE_ACROSS_RAY,
    M_ANGLE_ERR,
    M_CONTRAST,
    M_SIGN_FRAC,
    N_MEASURES,
    probe_candidates,
    probe_quality,
    probe_radii,
    probe_reach,
    ring_prefilter,
)
from edgecal.detection.subpixel import FINAL_CRITERIA, SEARCH_CRITERIA, nearest_of, refine_corners

# Where the squares beyond a grid line are sampled, as fractions of one grid step outwards (0.5 = their
# centre). The outermost squares of many printed boards are cut narrower than the others, so the centre
# alone can miss them; next to the line the corners' blur mixes both sides: several depths are tried.
BEYOND_STEP_FRACTIONS = (0.2, 0.35, 0.5)


@njit(cache=True, nogil=True, inline="always")
def _pairwise_sum(a: np.ndarray) -> float:
    """numpy's add.reduce of a short contiguous float64 row (its pairwise summation, exactly, below 128
    elements): the same sums as the numpy arithmetic these kernels replaced."""
    n = a.shape[0]
    if n < 8:
        res = 0.0
        for i in range(n):
            res += a[i]
        return res
    r = a[:8].copy()
    i = 8
    while i < n - (n % 8):
        for j in range(8):
            r[j] += a[i + j]
        i += 8
    res = ((r[0] + r[1]) + (r[2] + r[3])) + ((r[4] + r[5]) + (r[6] + r[7]))
    while i < n:
        res += a[i]
        i += 1
    return res


@njit(cache=True, nogil=True)
def _hole_systems(dense: np.ndarray, lo_u: int, lo_v: int, holes: np.ndarray, off: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The DLT systems of the holes (B, 2) whose neighbours at the label offsets ``off`` (N, 2) hold at least
    4 corners of ``dense`` (dense_labels, label (lo_u, lo_v) at [0, 0]) on two rows and two columns.

    Returns (which holes (K,), their systems (K, 2N, 9), the neighbours' centroids (K, 2) and scales (K,)):
    each set normalised (centroid, mean distance sqrt(2)) for conditioning, as Hartley's DLT does; a missing
    neighbour contributes zero rows (no effect on the null space). The arithmetic is that of the numpy
    expressions it replaced, in the same order (identical systems).
    """
    nu, nv = dense.shape[0], dense.shape[1]
    n_off = off.shape[0]
    b_all = holes.shape[0]
    which = np.empty(b_all, np.int64)
    systems = np.zeros((b_all, 2 * n_off, 9))
    means = np.zeros((b_all, 2))
    scales = np.zeros(b_all)
    dst = np.empty((n_off, 2))
    w = np.empty(n_off)
    dist = np.empty(n_off)
    k = 0
    for b in range(b_all):
        count = 0
        lo0 = np.inf
        hi0 = -np.inf
        lo1 = np.inf
        hi1 = -np.inf
        for n in range(n_off):
            u = holes[b, 0] + off[n, 0] - lo_u
            v = holes[b, 1] + off[n, 1] - lo_v
            x = np.nan
            y = np.nan
            if 0 <= u < nu and 0 <= v < nv:
                x = dense[u, v, 0]
                y = dense[u, v, 1]
            if math.isfinite(x) and math.isfinite(y):
                dst[n, 0] = x
                dst[n, 1] = y
                w[n] = 1.0
                count += 1
                lo0 = min(lo0, float(off[n, 0]))
                hi0 = max(hi0, float(off[n, 0]))
                lo1 = min(lo1, float(off[n, 1]))
                hi1 = max(hi1, float(off[n, 1]))
            else:
                dst[n, 0] = 0.0  # np.nan_to_num
                dst[n, 1] = 0.0
                w[n] = 0.0
        # at least 4 corners, on two distinct labels along each axis (not a single row or column)
        if count < 4 or not (lo0 < hi0 and lo1 < hi1):
            continue
        total = max(float(count), 1.0)
        m0 = dst[0, 0] * w[0]
        m1 = dst[0, 1] * w[0]
        for n in range(1, n_off):
            m0 += dst[n, 0] * w[n]
            m1 += dst[n, 1] * w[n]
        m0 = m0 / total
        m1 = m1 / total
        for n in range(n_off):
            dx = dst[n, 0] - m0
            dy = dst[n, 1] - m1
            dist[n] = math.sqrt(dx * dx + dy * dy) * w[n]
        scale = math.sqrt(2.0) / max(_pairwise_sum(dist) / total, 1e-9)
        for n in range(n_off):
            d0 = (dst[n, 0] - m0) * scale
            d1 = (dst[n, 1] - m1) * scale
            x = float(off[n, 0])
            y = float(off[n, 1])
            wn = w[n]
            r1 = systems[k, n]
            r2 = systems[k, n_off + n]
            r1[0] = x * wn
            r1[1] = y * wn
            r1[2] = 1.0 * wn
            r1[3] = 0.0 * wn
            r1[4] = 0.0 * wn
            r1[5] = 0.0 * wn
            r1[6] = -d0 * x * wn
            r1[7] = -d0 * y * wn
            r1[8] = -d0 * wn
            r2[0] = 0.0 * wn
            r2[1] = 0.0 * wn
            r2[2] = 0.0 * wn
            r2[3] = x * wn
            r2[4] = y * wn
            r2[5] = 1.0 * wn
            r2[6] = -d1 * x * wn
            r2[7] = -d1 * y * wn
            r2[8] = -d1 * wn
        which[k] = b
        means[k, 0] = m0
        means[k, 1] = m1
        scales[k] = scale
        k += 1
    return which[:k], systems[:k], means[:k], scales[:k]


@njit(cache=True, nogil=True)
def _null_vectors(systems: np.ndarray) -> np.ndarray:
    """(K, 9): the unit vector h minimising |A h| for each DLT system A of ``systems`` (K, R, 9): the
    eigenvector of A^T A of the smallest eigenvalue (LAPACK's, one 9x9 per system; numpy's batched SVD of
    the systems, the same vectors to ~1e-14 up to sign, took twice as long: its per-matrix overhead).
    The systems are normalised (_hole_systems), so squaring their condition costs no accuracy that matters."""
    out = np.empty((systems.shape[0], 9))
    for k in range(systems.shape[0]):
        a = systems[k]
        out[k] = np.linalg.eigh(a.T @ a)[1][:, 0]
    return out


# The hole (label offset 0) and its four diagonal neighbours (label offsets): the point and the spacing there.
_HOMOGRAPHY_PROBE = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0], [1.0, -1.0]])


@njit(cache=True, nogil=True, error_model="numpy")
def _probe_points(h: np.ndarray, means: np.ndarray, scales: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where the homographies ``h`` (K, 3, 3) of normalised image points (_hole_systems' centroids ``means``
    (K, 2) and ``scales`` (K,) undone: H = T^-1 Hn) put the hole (label offset 0) and its four diagonal
    neighbours (_HOMOGRAPHY_PROBE): the hole's point (K, 2) and the distance to the nearest of the four
    (K,) (inf or NaN on a homography's horizon). One pass: numpy's batched products cost more than it."""
    k_n = h.shape[0]
    pts = np.empty((k_n, 2))
    near = np.empty(k_n)
    q = np.empty((_HOMOGRAPHY_PROBE.shape[0], 2))
    for k in range(k_n):
        inv = 1.0 / scales[k]
        for j in range(_HOMOGRAPHY_PROBE.shape[0]):
            u = _HOMOGRAPHY_PROBE[j, 0]
            v = _HOMOGRAPHY_PROBE[j, 1]
            w = h[k, 2, 0] * u + h[k, 2, 1] * v + h[k, 2, 2]
            x = (h[k, 0, 0] * u + h[k, 0, 1] * v + h[k, 0, 2]) * inv + means[k, 0] * w
            y = (h[k, 1, 0] * u + h[k, 1, 1] * v + h[k, 1, 2]) * inv + means[k, 1] * w
            q[j, 0] = x / w
            q[j, 1] = y / w
        pts[k, 0] = q[0, 0]
        pts[k, 1] = q[0, 1]
        best = np.inf
        nan = False
        for j in range(1, q.shape[0]):
            dx = q[j, 0] - q[0, 0]
            dy = q[j, 1] - q[0, 1]
            d = math.sqrt(dx * dx + dy * dy)  # (NaN on the horizon, where hypot could give inf)
            if math.isnan(d):
                nan = True
            elif d < best:
                best = d
        near[k] = np.nan if nan else best
    return pts, near


def dense_labels(grid: dict[tuple[int, int], np.ndarray], margin: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """The grid as a dense array (U, V, 2) over its labels' span plus ``margin`` on every side, NaN where a
    label is missing, and the label (u, v) of its element [0, 0]."""
    return dense_labels_of(*grid_arrays(grid), margin)


def dense_labels_of(keys: np.ndarray, xy: np.ndarray, margin: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """dense_labels of the grid whose labels are ``keys`` (N, 2) int and points ``xy`` (N, 2) (no dict to
    build where the arrays are at hand)."""
    lo = keys.min(axis=0) - margin
    span = keys.max(axis=0) - lo + 1 + margin
    dense = np.full((span[0], span[1], 2), np.nan)
    dense[keys[:, 0] - lo[0], keys[:, 1] - lo[1]] = xy
    return dense, lo


def _label_span(dense: np.ndarray, lo: np.ndarray) -> tuple[int, int, int, int]:
    """The first and last labels (u0, v0, u1, v1) of a grid's dense_labels ``dense`` (margin 2) from ``lo``."""
    u0, v0 = (int(c) for c in lo + 2)
    u1, v1 = (int(c) for c in lo + np.array(dense.shape[:2]) - 3)
    return u0, v0, u1, v1


def _side_predictions(dense: np.ndarray, lo: np.ndarray, grow_u: bool, grow_v: bool
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The new outer lines of a grid's dense_labels ``dense`` (margin 2; label ``lo`` at [0, 0]): with
    ``grow_u`` the two beyond its first and last u, with ``grow_v`` those beyond its v (_side_labels), each
    point extrapolated along its own grid line (_extrapolate): (labels (K, 2), outward steps (K, 2),
    points (K, 2), nearest-corner distances (K,), predicted (K,) bool)."""
    labels, outward = _side_labels(*_label_span(dense, lo), grow_u, grow_v)
    return (labels, outward, *_extrapolate(dense, int(lo[0]), int(lo[1]), labels, outward))


def grid_arrays(grid: dict[tuple[int, int], np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """A grid's labels (N, 2) int64 and points (N, 2) float64, in the dict's order. (np.fromiter and
    np.concatenate: np.array of the lists of tuples and of points cost twice as much.)"""
    n = len(grid)
    if n == 0:
        return np.zeros((0, 2), np.int64), np.zeros((0, 2))
    keys = np.fromiter(itertools.chain.from_iterable(grid), np.int64, 2 * n).reshape(n, 2)
    return keys, np.concatenate(list(grid.values())).astype(np.float64, copy=False).reshape(n, 2)


def predict_holes(grid: dict[tuple[int, int], np.ndarray], holes: list[tuple[int, int]]
                  ) -> tuple[list[np.ndarray], list[tuple[int, int]], list[float]]:
    """Where the grid's missing labels ``holes`` lie: each from a homography of its own neighbourhood
    (lens distortion is local), the nearest ring of 8 first, the 5x5 one when that ring holds fewer than 4
    corners or only one row or column. All holes in one batched fit. Returns (points, their labels,
    nearest-corner distances there); holes with no usable neighbourhood or on a homography's horizon are
    left out."""
    if not holes:
        return [], [], []
    dense, lo = dense_labels(grid)
    out_p, out_s = _predict_from_dense(dense, lo, np.asarray(holes, dtype=np.int64))
    ok = np.isfinite(out_p).all(axis=1) & np.isfinite(out_s)
    return ([out_p[i] for i in np.nonzero(ok)[0]], [holes[i] for i in np.nonzero(ok)[0]],
            [float(out_s[i]) for i in np.nonzero(ok)[0]])


def _predict_from_dense(dense: np.ndarray, lo: np.ndarray, hl: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """predict_holes on the grid's dense_labels (margin 2) for the labels ``hl`` (B, 2): points (B, 2) and
    nearest-corner distances (B,), NaN (or inf) where a hole has no usable neighbourhood."""
    out_p = np.full((len(hl), 2), np.nan)
    out_s = np.full(len(hl), np.nan)
    todo = np.ones(len(hl), dtype=bool)
    for reach in (1, 2):
        idx = np.nonzero(todo)[0]
        if len(idx) == 0:
            break
        which, systems, means, scales = _hole_systems(dense, int(lo[0]), int(lo[1]),
                                                      np.ascontiguousarray(hl[idx]), _RING_OFFSETS[reach])
        if not len(which):
            continue
        b = idx[which]
        out_p[b], out_s[b] = _probe_points(_null_vectors(systems).reshape(-1, 3, 3), means, scales)
        todo[b] = False
    return out_p, out_s


def _ring_offsets(reach: int) -> np.ndarray:
    """Label offsets (N, 2) of the (2 reach + 1)^2 neighbourhood without its centre, u-major."""
    du, dv = np.meshgrid(np.arange(-reach, reach + 1), np.arange(-reach, reach + 1), indexing="ij")
    off = np.stack([du.ravel(), dv.ravel()], axis=1)
    return off[(off != 0).any(axis=1)]


_RING_OFFSETS = {reach: _ring_offsets(reach) for reach in (1, 2)}
# The outward steps (du, dv) of _side_labels' four lines, sorted.
_OUTWARD_STEPS = ((-1, 0), (0, -1), (0, 1), (1, 0))


def _cells_beyond(grid: dict[tuple[int, int], np.ndarray], line: list[tuple[int, int]],
                  outward: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """The squares just outside a grid line, in order along it: one per pair of neighbouring labels of the
    line both in the grid (a square lies between them; between labels two apart lies a corner, not a
    square), as the midpoint of the pair (K, 2) and that of the pair's points one square outwards (K, 2);
    _cell_values samples the squares between them. (Made once for all of BEYOND_STEP_FRACTIONS.)"""
    du, dv = outward
    along = (1 - abs(du), 1 - abs(dv))
    place = {uv: uv[0] * along[0] + uv[1] * along[1] for uv in line}
    ordered = sorted(line, key=place.__getitem__)
    # Each line point stepped one square outwards, extrapolated along its own grid line (quadratic when two
    # inner points are known: fisheye lenses bend the lines too much for one homography to reach outside).
    outer: list[np.ndarray | None] = []
    for u, v in ordered:
        p0 = grid.get((u, v))
        p1 = grid.get((u - du, v - dv))
        p2 = grid.get((u - 2 * du, v - 2 * dv))
        if p0 is None or p1 is None:
            outer.append(None)
        elif p2 is None:
            outer.append(2.0 * p0 - p1)
        else:
            outer.append(3.0 * p0 - 3.0 * p1 + p2)
    mids = []
    beyond = []
    for k in range(len(ordered) - 1):
        a0, a1 = grid.get(ordered[k]), grid.get(ordered[k + 1])
        b0, b1 = outer[k], outer[k + 1]
        if a0 is None or a1 is None or b0 is None or b1 is None or place[ordered[k + 1]] - place[ordered[k]] != 1:
            continue
        mids.append(0.5 * (a0 + a1))
        beyond.append(0.5 * (b0 + b1))
    return np.array(mids, dtype=np.float64).reshape(-1, 2), np.array(beyond, dtype=np.float64).reshape(-1, 2)


def _cell_values(cells: tuple[np.ndarray, np.ndarray], smooth: np.ndarray, fraction: float) -> np.ndarray | None:
    """Mean intensity of the squares ``cells`` (_cells_beyond) sampled ``fraction`` of a grid step outwards
    from the line. None: a square outside the image."""
    mid, beyond = cells
    vals, inside = _cell_means(smooth, mid + fraction * (beyond - mid))
    return vals if inside else None


@njit(cache=True, nogil=True)
def _cell_means(smooth: np.ndarray, cells: np.ndarray) -> tuple[np.ndarray, bool]:
    """The mean of the 3x3 pixels round each cell (M, 2: x, y rounded half to even), and whether all cells
    lie inside the image (False: the means are not all there). The mean is summed as numpy's
    smooth[...].mean() sums nine values (pairwise: eight accumulators, then the ninth) in smooth's dtype,
    so that it is the same to the bit (one numba pass: a numpy mean per cell cost more than the test)."""
    hh, ww = smooth.shape
    out = np.empty(cells.shape[0])
    for k in range(cells.shape[0]):
        x = cells[k, 0]
        y = cells[k, 1]
        if not (1 <= x < ww - 2 and 1 <= y < hh - 2):
            return out[:k], False
        xi = int(np.rint(x))
        yi = int(np.rint(y))
        r0 = smooth[yi - 1]
        r1 = smooth[yi]
        r2 = smooth[yi + 1]
        total = (((r0[xi - 1] + r0[xi]) + (r0[xi + 1] + r1[xi - 1])) + ((r1[xi] + r1[xi + 1]) + (r2[xi - 1] + r2[xi])))
        out[k] = (total + r2[xi + 1]) / np.float32(9.0)
    return out, True


def squares_beyond_alternate(grid: dict[tuple[int, int], np.ndarray], line: list[tuple[int, int]],
                             outward: tuple[int, int], smooth: np.ndarray, min_contrast: float) -> bool:
    """Whether the squares just outside a grid line alternate black/white, as they must at a row of corners.

    A board's outermost squares meet its white margin in points the probe can take for X-corners (the
    margin is white on both sides, the background beyond may be dark). Such a line is geometrically a
    perfect grid row; what gives it away is the uniform margin beyond it. This is the positive evidence a
    new outer line needs; squares that cannot be measured (outside the image) count as alternating, but a
    line with fewer than two squares between its confirmed corners has none: where a dark background
    comes close behind a narrow margin, the probe confirms every other point of the margin's line (those
    next to a black square), and three such points on a board of five columns made it a 5x5 grid that
    matched no board (bench/live.py's robot sequences: the 5x4 board missed in 114 of 120 images).
    """
    cells = _cells_beyond(grid, line, outward)
    for fraction in BEYOND_STEP_FRACTIONS:
        vals = _cell_values(cells, smooth, fraction)
        if vals is None:
            return True
        if len(vals) < 2:
            return False
        diffs = np.diff(vals)
        alternating = np.sum(diffs[1:] * diffs[:-1] < 0)
        strong = np.abs(diffs) >= 0.5 * min_contrast
        if strong.mean() >= 0.7 and alternating >= 0.7 * (len(diffs) - 1):
            return True
    return False


def squares_beyond_uniform(grid: dict[tuple[int, int], np.ndarray], line: list[tuple[int, int]],
                           outward: tuple[int, int], smooth: np.ndarray, min_contrast: float) -> bool:
    """Whether the squares just outside a grid line are one uniform area (a board's margin): the evidence
    needed to remove a line already in a grid (where extrapolation is poor, e.g. at a fisheye rim, cells
    land anywhere; that is not uniform, and the line stays)."""
    cells = _cells_beyond(grid, line, outward)
    for fraction in BEYOND_STEP_FRACTIONS:
        vals = _cell_values(cells, smooth, fraction)
        if vals is None or len(vals) < 3 or np.mean(np.abs(np.diff(vals)) < min_contrast) < 0.7:
            return False
    return True


def trim_false_edges(grid: dict[tuple[int, int], np.ndarray], smooth: np.ndarray,
                     min_contrast: float) -> dict[tuple[int, int], np.ndarray]:
    """Drop outer rows/columns with a uniform area beyond them (see squares_beyond_uniform)."""
    grid = dict(grid)
    changed = True
    while changed and len(grid) >= 4:
        changed = False
        us = [u for u, _ in grid]
        vs = [v for _, v in grid]
        for axis, value, outward in ((0, min(us), (-1, 0)), (0, max(us), (1, 0)),
                                     (1, min(vs), (0, -1)), (1, max(vs), (0, 1))):
            line = [k for k in grid if k[axis] == value]
            # A lone point out on a line of its own is never trusted; longer lines must have squares beyond.
            if len(line) < 2 or squares_beyond_uniform(grid, line, outward, smooth, min_contrast):
                for k in line:
                    del grid[k]
                changed = True
                break
    return grid


def verify_predictions(level: Level, preds: np.ndarray, spacing: np.ndarray, params: DetectorParams,
                       pinned: np.ndarray, accepted: np.ndarray | None = None, criteria: tuple = FINAL_CRITERIA,
                       window: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Refine predicted corners and keep those the probe confirms near their prediction.

    Returns (refined (M, 2), good (M,) bool, quality (M,) as probe_quality). A point the probe already
    accepted within 0.4 x spacing of a prediction is taken as it is (grouping may have missed the link,
    e.g. along a line a fisheye lens bends hard). Predictions that are ``pinned`` down independently
    (holes inside a grid: neighbours on all sides; a tracked board: the pose) only need the probe to see
    a corner there (thresholds relaxed further); the others (new rows outside a grid) must pass the probe
    properly, and are refined and probed only where a ring round them crosses dark/bright four times
    (ring_prefilter without its symmetry test). Either way the refinement must stay within 0.25 x spacing
    of the prediction. ``window``: the square size each refinement window is made for
    (subpixel.window_spacing), default ``spacing``. The probe reads ``level``'s gradients round the refined
    points only (Level.gradients_near).
    """
    smooth = level.smooth
    if accepted is not None and len(accepted):
        d, j = nearest_of(np.ascontiguousarray(preds, np.float64), np.ascontiguousarray(accepted, np.float64))
        snap = d < 0.4 * spacing
        preds = np.where(snap[:, None], accepted[np.maximum(j, 0)], preds)
    h, w = smooth.shape
    inside = ((preds[:, 0] > 2) & (preds[:, 1] > 2) & (preds[:, 0] < w - 3) & (preds[:, 1] < h - 3))
    radii = probe_radii(spacing, params)
    # A new outer line's prediction where no ring round it crosses dark/bright four times has no corner
    # within reach of its refinement (most of them: the board's margin), so it is not refined or probed
    # (a hole's prediction is pinned by neighbours all round: the probe alone decides there).
    inside &= pinned | ring_prefilter(smooth, np.ascontiguousarray(preds, np.float64), radii,
                                      0.5 * params.min_contrast, False)
    refined = preds.copy()
    ok = np.zeros(len(preds), dtype=bool)
    meas = np.zeros((len(preds), N_MEASURES))  # (quality 0 where not probed)
    if inside.any():
        sizes = spacing if window is None else window
        refined[inside] = refine_corners(smooth, preds[inside], sizes[inside], criteria=criteria)
        gx, gy = level.gradients_near(refined[inside], probe_reach(radii[inside], params))
        ok[inside], _dirs, meas[inside] = probe_candidates(
            gx, gy, smooth, np.ascontiguousarray(refined[inside]), np.ascontiguousarray(radii[inside]),
            params.probe_angles, params.probe_inner_radius_px, EDGE_ACROSS_RAY,
            math.radians(params.angle_diff_max_deg), params.sign_fraction, params.min_contrast * 0.5,
            params.min_peak_ratio * 0.8)
    pinned_ok = ((meas[:, M_ANGLE_ERR] < math.radians(1.5 * params.angle_diff_max_deg))
                 & (meas[:, M_SIGN_FRAC] >= 0.6) & (meas[:, M_CONTRAST] >= 0.5 * params.min_contrast))
    near = np.linalg.norm(refined - preds, axis=1) < 0.25 * spacing
    return refined, (ok | (pinned & pinned_ok)) & near & inside, probe_quality(meas, params)


@njit(cache=True, nogil=True)
def _side_labels(u0: int, v0: int, u1: int, v1: int, grow_u: bool, grow_v: bool) -> tuple[np.ndarray, np.ndarray]:
    """complete_grid's new outer lines of the labels u0..u1 x v0..v1, side by side: labels (K, 2) and each
    one's outward step (K, 2), int64. With ``grow_u`` the lines u0 - 1 and u1 + 1 (over v0..v1, outward -u
    and +u), then with ``grow_v`` the lines v0 - 1 and v1 + 1 (over u0..u1, -v and +v)."""
    nv = v1 - v0 + 1
    nu = u1 - u0 + 1
    k = (2 * nv if grow_u else 0) + (2 * nu if grow_v else 0)
    labels = np.empty((k, 2), np.int64)
    outward = np.zeros((k, 2), np.int64)
    i = 0
    for axis in range(2):  # 0: the new u lines (over v), 1: the new v lines (over u)
        if not (grow_u if axis == 0 else grow_v):
            continue
        lo, hi = (u0, u1) if axis == 0 else (v0, v1)
        first, last = (v0, v1) if axis == 0 else (u0, u1)
        for line, step in ((lo - 1, -1), (hi + 1, 1)):
            for t in range(first, last + 1):
                labels[i, axis] = line
                labels[i, 1 - axis] = t
                outward[i, axis] = step
                i += 1
    return labels, outward


@njit(cache=True, nogil=True)
def _extrapolate(dense: np.ndarray, lo_u: int, lo_v: int, labels: np.ndarray, outward: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Predict new outer lines, each point one step ``outward`` (K, 2: du, dv per label) along its own
    grid line, for the labels (K, 2) on the grid's dense_labels ``dense`` (label (lo_u, lo_v) at [0, 0]).

    Quadratic extrapolation from the three nearest points of that line (linear from two): unlike a homography
    it follows lines that a fisheye lens bends. Returns (points (K, 2), nearest-corner distances (K,),
    predicted (K,) bool: False where the line's two nearest points are not both there).
    """
    n = labels.shape[0]
    nu, nv = dense.shape[0], dense.shape[1]
    pts = np.zeros((n, 2))
    spacing = np.zeros(n)
    ok = np.zeros(n, dtype=np.bool_)
    for i in range(n):
        du = outward[i, 0]
        dv = outward[i, 1]
        u = labels[i, 0] - lo_u
        v = labels[i, 1] - lo_v
        x0, y0 = _dense_at(dense, nu, nv, u - du, v - dv)
        x1, y1 = _dense_at(dense, nu, nv, u - 2 * du, v - 2 * dv)
        if not (math.isfinite(x0) and math.isfinite(x1)):
            continue
        x2, y2 = _dense_at(dense, nu, nv, u - 3 * du, v - 3 * dv)
        if not math.isfinite(x2):
            nx, ny = 2.0 * x0 - x1, 2.0 * y0 - y1
        else:
            nx, ny = 3.0 * x0 - 3.0 * x1 + x2, 3.0 * y0 - 3.0 * y1 + y2
        d = math.hypot(nx - x0, ny - y0)
        for su in (1, -1):
            qx, qy = _dense_at(dense, nu, nv, u - du + su * dv, v - dv + su * du)
            if math.isfinite(qx):
                d = min(d, math.hypot(qx - x0, qy - y0))
        pts[i, 0] = nx
        pts[i, 1] = ny
        spacing[i] = d
        ok[i] = True
    return pts, spacing, ok


@njit(cache=True, nogil=True, inline="always")
def _dense_at(dense: np.ndarray, nu: int, nv: int, u: int, v: int) -> tuple[float, float]:
    """dense[u, v] (NaN outside)."""
    if u < 0 or v < 0 or u >= nu or v >= nv:
        return np.nan, np.nan
    return dense[u, v, 0], dense[u, v, 1]


class _HolePredictions:
    """_predict_from_dense for one grid's completion, each hole's prediction made once per neighbourhood.

    A hole's homography uses nothing but the grid's corners within two labels of it (each hole's fit is its
    own: the batched arithmetic and SVD are per hole), so a hole whose 5x5 neighbourhood did not change since
    the last round predicts the same point: it is looked up by that neighbourhood's values. A fragment of
    clutter with dozens of holes no grid corner reaches spent most of its completion refitting them.
    """

    def __init__(self) -> None:
        self._seen: dict[bytes, tuple[float, float, float]] = {}

    def predict(self, dense: np.ndarray, lo: np.ndarray, holes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(points (B, 2), spacing (B,)) of _predict_from_dense for the holes (B, 2) of ``dense`` (margin 2)."""
        keys = []
        new = []
        for i, (u, v) in enumerate((holes - lo).tolist()):
            key = b"%d,%d:" % (u + lo[0], v + lo[1]) + dense[u - 2:u + 3, v - 2:v + 3].tobytes()
            keys.append(key)
            if key not in self._seen:
                new.append(i)
        if new:
            sel = np.array(new)
            got_p, got_s = _predict_from_dense(dense, lo, holes[sel])
            for i, (x, y), sp in zip(new, got_p.tolist(), got_s.tolist()):
                self._seen[keys[i]] = (x, y, sp)
        out = np.array([self._seen[k] for k in keys], dtype=np.float64).reshape(-1, 3)
        return out[:, :2], out[:, 2]


class _VerifiedPredictions:
    """verify_predictions for one grid's completion, each distinct prediction verified once.

    Completion predicts every hole and side again in each round, and a prediction the grid did not change
    (a hole or a side that failed, far from what was added) comes out bit for bit the same: its refinement
    and probe would too (each point is refined and probed on its own), so they are looked up instead (on
    bench/live.py's hard frames about 40 % of the predictions, and the whole last round).
    """

    def __init__(self, level: Level, params: DetectorParams, accepted: np.ndarray | None, criteria: tuple) -> None:
        self._level = level
        self._params = params
        self._accepted = accepted
        self._criteria = criteria
        self._index: dict[tuple[float, float, float, bool], int] = {}  # prediction -> row of the results
        self._refined = np.zeros((0, 2))
        self._good = np.zeros(0, dtype=bool)

    def verify(self, preds: np.ndarray, spacing: np.ndarray, pinned: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(refined (M, 2), good (M,) bool) of verify_predictions for predictions (M, 2) with their
        nearest-corner distances (M,) and pinned flags (M,)."""
        keys = list(zip(preds[:, 0].tolist(), preds[:, 1].tolist(), spacing.tolist(), pinned.tolist()))
        index = self._index
        rows: list[int] = []
        new: list[int] = []
        n = len(self._good)
        for i, k in enumerate(keys):
            row = index.get(k)
            if row is None:
                row = index[k] = n + len(new)
                new.append(i)
            rows.append(row)
        if new:
            sel = np.array(new)
            refined, good, _quality = verify_predictions(self._level, preds[sel], spacing[sel], self._params,
                                                         pinned[sel], self._accepted, self._criteria)
            if n == 0 and len(new) == len(keys):
                self._refined, self._good = refined, good
                return refined.copy(), good.copy()
            self._refined = np.concatenate([self._refined, refined])
            self._good = np.concatenate([self._good, good])
        at = np.array(rows, dtype=np.int64)
        return self._refined[at], self._good[at]


def grid_may_continue(grid: dict[tuple[int, int], np.ndarray], smooth: np.ndarray, params: DetectorParams) -> bool:
    """Whether complete_grid could grow the grid by a line, told from its predictions alone on the image's
    smoothed level ``smooth`` (no gradients, no refinement): a side where most of the points predicted one
    line beyond it (as many as complete_grid must confirm there), each snapped to its saddle, pass the
    search's ring pre-filter at the probe's radius (four crossings, point-symmetric: an X-corner), and the
    squares beyond them alternate (squares_beyond_alternate). Where a board's outer squares are cut short or
    its margin is narrow, rings round the points beyond its border cross dark/bright four times too, but
    not point-symmetrically."""
    labels, outward, pts, spacing, ok = _side_predictions(*dense_labels(grid), True, True)
    pts = snap_to_saddle(smooth, np.ascontiguousarray(pts), 3)
    ok &= ring_prefilter(smooth, pts, probe_radii(spacing, params), 0.5 * params.min_contrast)
    # the four outward steps in np.unique's order (np.unique(outward, axis=0) cost more than the whole test;
    # a side without labels has no point seen and is skipped)
    for out in _OUTWARD_STEPS:
        side = (outward == out).all(axis=1)
        seen = np.flatnonzero(side & ok)
        if len(seen) < max(2, 0.6 * side.sum()):
            continue
        line = list(map(tuple, labels[seen].tolist()))
        trial = dict(grid)
        trial.update(zip(line, pts[seen]))
        if squares_beyond_alternate(trial, line, out, smooth, params.min_contrast):
            return True
    return False


def line_predictions(dense: np.ndarray, lo: np.ndarray, labels: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each of the ``labels`` (B, 2) predicted along the grid lines through it, from each of its four sides
    (_OUTWARD_STEPS), on a grid's dense_labels ``dense`` (label ``lo`` at [0, 0]): quadratic from the three
    nearest corners on that side, linear from two (_extrapolate). Returns (points (B, 4, 2), nearest-corner
    distances (B, 4), predicted (B, 4) bool)."""
    steps = len(_OUTWARD_STEPS)
    repeated = np.repeat(np.asarray(labels, dtype=np.int64).reshape(-1, 2), steps, axis=0)
    outward = np.tile(np.array(_OUTWARD_STEPS, dtype=np.int64), (len(repeated) // steps, 1))
    pts, spacing, ok = _extrapolate(dense, int(lo[0]), int(lo[1]), repeated, outward)
    return pts.reshape(-1, steps, 2), spacing.reshape(-1, steps), ok.reshape(-1, steps)


def _take_line_predictions(grid: dict[tuple[int, int], np.ndarray], dense: np.ndarray, lo: np.ndarray,
                           holes: np.ndarray, verified: _VerifiedPredictions) -> bool:
    """The holes (B, 2) of ``grid`` (its dense_labels ``dense``, ``lo``) that no homography prediction filled,
    predicted again along each of the grid lines through them (line_predictions) and verified as a new
    outer line's points are (not pinned: the probe's full test and the ring pre-filter); a hole takes its
    first confirmed prediction when every confirmed one lands on the same corner (within a quarter of the
    spacing). Whether any was added.

    At a fisheye's rim the squares shrink too fast for a homography of the 3x3 (or 5x5) neighbourhood: its
    predictions for the outermost holes miss them by a quarter of a square or more, from where their
    refinement does not reach the corner, while the board's own lines, bent as they are, still run through
    it (the 190-degree set with faint added noise: one board in eight left with six holes)."""
    pts, spacing, ok = line_predictions(dense, lo, holes)
    pts, spacing, ok = pts.reshape(-1, 2), spacing.reshape(-1), ok.reshape(-1)
    at = np.flatnonzero(ok)
    if not len(at):
        return False
    alt, alt_good = verified.verify(pts[at], spacing[at], np.zeros(len(at), dtype=bool))
    owner = at // len(_OUTWARD_STEPS)
    added = False
    for hole in np.unique(owner[alt_good]).tolist():
        mine = np.flatnonzero((owner == hole) & alt_good)
        first = alt[mine[0]]
        if (np.linalg.norm(alt[mine] - first, axis=1) <= 0.25 * spacing[at][mine]).all():
            grid[(int(holes[hole, 0]), int(holes[hole, 1]))] = first
            added = True
    return added


def _side_points_from_homographies(dense: np.ndarray, lo: np.ndarray, labels: list[tuple[int, int]],
                                   hole_predictions: _HolePredictions, verified: _VerifiedPredictions
                                   ) -> dict[tuple[int, int], np.ndarray]:
    """A new outer line's ``labels`` whose extrapolation along their own grid lines was not confirmed,
    predicted again by a homography of the grid's corners within two labels (as holes are) and verified as
    before: those confirmed, by label.

    The quadratic extrapolation carries three corners' noise, amplified (coefficients 3, -3, 1: about 4x a
    corner's); on small noisy squares it missed the next corner by 2-3 px, beyond what the refinement and
    the ring pre-filter reach. The homography averages a dozen corners, at the price of not following a
    lens's bend, which the extrapolation does: it is the second chance, only for a line partly confirmed."""
    if not labels:
        return {}
    pts, spacing = hole_predictions.predict(dense, lo, np.array(labels, dtype=np.int64))
    ok = np.flatnonzero(np.isfinite(pts).all(axis=1) & np.isfinite(spacing))
    if not len(ok):
        return {}
    refined, good = verified.verify(pts[ok], spacing[ok], np.zeros(len(ok), dtype=bool))
    return {labels[ok[k]]: refined[k] for k in np.flatnonzero(good)}


def complete_grid(grid: dict[tuple[int, int], np.ndarray], level: Level, max_dim: int, params: DetectorParams,
                  accepted: np.ndarray | None = None) -> dict[tuple[int, int], np.ndarray]:
    """Fill holes and grow the grid at its sides (up to ``max_dim`` labels per axis) on ``level``; returns a
    new dict.

    ``accepted``: points the probe accepted on this level, tried first at every predicted position.
    """
    grid = dict(grid)
    smooth = level.smooth
    # the grid's corners get their final refinement once the board is known (SEARCH_CRITERIA here)
    verified = _VerifiedPredictions(level, params, accepted, SEARCH_CRITERIA)
    hole_predictions = _HolePredictions()
    for _ in range(2 * max_dim + 2):
        dense, lo = dense_labels(grid)
        u0, v0, u1, v1 = _label_span(dense, lo)
        added = False
        # Holes: each from a homography of its own neighbourhood (lens distortion is local).
        holes = np.argwhere(~np.isfinite(dense[2:-2, 2:-2, 0])) + (u0, v0)
        hole_p, hole_s = hole_predictions.predict(dense, lo, holes)
        found = np.isfinite(hole_p).all(axis=1) & np.isfinite(hole_s)
        # (the labels as tuples of Python ints straight from .tolist(): per-element int() cost more than the
        # refinement bookkeeping it fed)
        preds = [hole_p[found]]
        keys = list(map(tuple, holes[found].tolist()))
        spac = [hole_s[found]]
        # Sides: a whole new row or column, each point extrapolated along its own grid line. (Each side as
        # its length and outward step; its labels made in one numba pass, _side_labels.)
        grow_u, grow_v = u1 - u0 + 1 < max_dim, v1 - v0 + 1 < max_dim
        sides = ([(v1 - v0 + 1, (-1, 0)), (v1 - v0 + 1, (1, 0))] if grow_u else []) \
            + ([(u1 - u0 + 1, (0, -1)), (u1 - u0 + 1, (0, 1))] if grow_v else [])
        groups: list[tuple[int, int, tuple[int, int] | None]] = [(len(keys), 0, None)]
        if sides:
            side_labels, _side_out, side_p, side_s, side_ok = _side_predictions(dense, lo, grow_u, grow_v)
            # the extrapolated points of all sides at once, cut where each side's labels start
            ok_at = np.flatnonzero(side_ok)
            cuts = np.searchsorted(ok_at, np.cumsum([0] + [length for length, _o in sides])).tolist()
            for k, (length, outward) in enumerate(sides):
                if cuts[k] == cuts[k + 1]:
                    continue
                on_side = ok_at[cuts[k]:cuts[k + 1]]
                preds.append(side_p[on_side])
                keys.extend(map(tuple, side_labels[on_side].tolist()))
                spac.append(side_s[on_side])
                groups.append((len(keys), length, outward))
        if not keys:
            break
        n_holes = groups[0][0]
        refined, good = verified.verify(np.concatenate(preds), np.concatenate(spac),
                                        np.arange(len(keys)) < n_holes)
        start = 0
        for end, side_length, side_outward in groups:
            first, start = start, end
            # the confirmed points of this group, found once (not tested point by point in Python)
            sel = (np.flatnonzero(good[first:end]) + first).tolist()
            points = {keys[i]: refined[i] for i in sel}
            if side_outward is not None:
                needed = max(2, 0.6 * side_length)
                if 0 < len(points) < needed:
                    points.update(_side_points_from_homographies(
                        dense, lo, [keys[i] for i in range(first, end) if not good[i]], hole_predictions, verified))
                # A side line is taken only when most of it is confirmed and squares lie beyond it.
                if len(points) < needed:
                    continue
                trial = dict(grid)
                trial.update(points)
                if not squares_beyond_alternate(trial, list(points), side_outward, smooth, params.min_contrast):
                    continue
            grid.update(points)
            added = added or bool(points)
        if not added and len(holes):
            # the last resort for holes no homography reaches: the grid lines through them
            added = _take_line_predictions(grid, dense, lo, holes, verified)
        if not added:
            break
    return grid
