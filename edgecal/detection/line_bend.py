"""What a lens's bent grid lines do to the X-junction fit: the shift of its straight-line model, predicted
from the board's own corners.

The X-junction fit (subpixel.xjunction_fit) models a corner as two straight edges over a disc of radius
r. Through a lens that bends straight lines (a fisheye most) an edge is an arc of curvature kappa, and the
straight line fitted to it over the disc sits where the arc is on average: its offset at the corner is the
mean of kappa s^2 / 2 over the disc's length of edge, s in [-r, r], i.e. kappa r^2 / 6, towards the arc's
centre of curvature. The corner is the two fitted lines' intersection, so it moves by the shift d with
n_k . d = kappa_k r^2 / 6 for both lines k (n_k its unit normal towards its centre). Measured on rendered
fisheye hand-held sessions (150-200 deg, edgecal.synth.handheld): inner corners' error 0.033 px RMS, of
which this prediction explains most (regression gain 0.85, correlation 0.84); taken off, 0.019 px.

The curvature comes from the grid: a perspective view keeps a straight line straight, so a bend of a
board's row or column of corners is the lens's. Each line's corners are fitted by a polynomial in their
index (a cubic from five corners on, a parabola for three or four: the fit averages the corners' noise),
x and y alike (a perspective line x(j), y(j) share one rational function of j, so a straight line fits
straight), and the curvature vector taken off its derivatives. At a line's first and last corner the
curvature is read at the next corner inwards: a cubic's second derivative extrapolated to its ends is
mostly noise (rim corners then got worse, 0.040 -> 0.61 px RMS; read inwards 0.040 -> 0.026).

Pure functions: corners, ids and disc radii in, shifts out; one numba pass over a board's lines (the plain
reference is in tests/test_line_bend.py).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from edgecal.detection.subpixel import id_grid, solve_spd

# Share of kappa r^2 by which the fitted line sits off a bent edge at the corner: the mean of s^2 / 2 over
# s uniform in [-r, r], in units of r^2.
BEND_SHIFT_SHARE = 1.0 / 6.0
# Corners a line needs before it is fitted by a cubic (fewer: a parabola; under three: no curvature).
_CUBIC_MIN_CORNERS = 5


def line_curvatures(xy: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """(N, 2, 2) 1/px: for every corner ``xy`` (N, 2; ``ids`` (N, 2): col, row) of one board, [:, 0] along
    its row and [:, 1] along its column, the line's curvature vector (pointing to the centre of curvature)
    from the polynomial fit of the line's corners (module docstring); NaN where the line has fewer than
    three corners."""
    xy = np.ascontiguousarray(xy, dtype=np.float64).reshape(-1, 2)
    ids = np.ascontiguousarray(ids, dtype=np.int64).reshape(-1, 2)
    if len(xy) < 3:
        return np.full((len(xy), 2, 2), np.nan)
    return _board_curvatures(xy, ids, _CUBIC_MIN_CORNERS)


@njit(cache=True, nogil=True)
def _board_curvatures(xy: np.ndarray, ids: np.ndarray, cubic_min: int) -> np.ndarray:
    """line_curvatures of N >= 3 corners: the board's rows, then its columns, laid out as lines for
    _line_curvature_kernel and its curvatures read back per corner (one numba pass: the layout's numpy
    calls cost more than the fits)."""
    n = xy.shape[0]
    curvatures = np.full((n, 2, 2), np.nan)
    grid, lo_c, lo_r = id_grid(xy, ids, 0, n, 0)  # (rows, cols, 2)
    lo = (lo_c, lo_r)
    for axis in range(2):
        # the rows as lines (axis 0), then the columns
        points = grid if axis == 0 else np.ascontiguousarray(grid.transpose((1, 0, 2)))
        if points.shape[1] < 3:
            continue
        bend = _line_curvature_kernel(points, cubic_min)
        for i in range(n):
            line = ids[i, 1 - axis] - lo[1 - axis]
            along = ids[i, axis] - lo[axis]
            curvatures[i, axis, 0] = bend[line, along, 0]
            curvatures[i, axis, 1] = bend[line, along, 1]
    return curvatures


@njit(cache=True, nogil=True)
def _line_curvature_kernel(points: np.ndarray, cubic_min: int) -> np.ndarray:
    """(L, n, 2): the curvature vector at each index of L lines of n points (L, n, 2; NaN where a corner is
    missing), from a least-squares polynomial in the centred index (a cubic from ``cubic_min`` corners, a
    parabola from three), read one index inwards at a line's first and last corner; NaN on a line of
    fewer than three corners. One pass over a board's lines (numpy's batched fits cost ~0.25 ms a board)."""
    n_lines, n_along = points.shape[0], points.shape[1]
    out = np.full((n_lines, n_along, 2), np.nan)
    half = 0.5 * (n_along - 1)
    normal = np.empty((4, 4))
    rhs = np.empty((2, 4))
    coef = np.empty((2, 4))
    for li in range(n_lines):
        count = 0
        first = -1
        last = -1
        for k in range(n_along):
            if math.isfinite(points[li, k, 0]):
                count += 1
                if first < 0:
                    first = k
                last = k
        if count < 3:
            continue
        m = 4 if count >= cubic_min else 3
        normal[:] = 0.0
        rhs[:] = 0.0
        for k in range(n_along):
            if not math.isfinite(points[li, k, 0]):
                continue
            t = k - half
            for a in range(m):
                ta = t ** a
                rhs[0, a] += ta * points[li, k, 0]
                rhs[1, a] += ta * points[li, k, 1]
                for b in range(m):
                    normal[a, b] += ta * t ** b
        for c in range(2):
            coef[c, :m] = solve_spd(normal[:m, :m].copy(), rhs[c, :m].copy())
        for k in range(n_along):
            at = min(max(k, first + 1), max(last - 1, first + 1), n_along - 1)
            t = at - half
            d1x = d1y = d2x = d2y = 0.0
            for a in range(1, m):
                d1x += a * coef[0, a] * t ** (a - 1)
                d1y += a * coef[1, a] * t ** (a - 1)
            for a in range(2, m):
                d2x += a * (a - 1) * coef[0, a] * t ** (a - 2)
                d2y += a * (a - 1) * coef[1, a] * t ** (a - 2)
            speed2 = d1x * d1x + d1y * d1y
            if not speed2 > 0.0:
                continue
            # the second derivative's part across the tangent, over the speed squared
            along = (d2x * d1x + d2y * d1y) / speed2
            out[li, k, 0] = (d2x - along * d1x) / speed2
            out[li, k, 1] = (d2y - along * d1y) / speed2
    return out


def bend_shift(xy: np.ndarray, ids: np.ndarray, angles: np.ndarray, radius: np.ndarray) -> np.ndarray:
    """(N, 2) px: where the X-junction fit puts each corner of a bent grid relative to the true junction
    (subtract it), for one board's corners ``xy`` (N, 2), ``ids`` (N, 2: col, row), the directions of its row
    and column there ``angles`` (N, 2) radians (subpixel.grid_line_angles) and the fit's disc radii ``radius``
    (N,) px. A line with fewer than three corners (no curvature known) counts as straight; where the two
    lines are too close to parallel to intersect well the shift is 0."""
    angles = np.ascontiguousarray(np.asarray(angles, dtype=np.float64).reshape(-1, 2))
    radius = np.ascontiguousarray(np.asarray(radius, dtype=np.float64).reshape(-1))
    return _shift_from_curvatures(line_curvatures(xy, ids), angles, radius)


@njit(cache=True, nogil=True)
def _shift_from_curvatures(curvatures: np.ndarray, angles: np.ndarray, radius: np.ndarray) -> np.ndarray:
    """bend_shift from the lines' curvature vectors (N, 2, 2), directions (N, 2) and disc radii (N,), per
    corner (the numpy expressions it replaced, in their order): each line's offset n . kappa x
    BEND_SHIFT_SHARE x r^2 (0 where unknown), the two lines' intersection moved by them."""
    n = curvatures.shape[0]
    out = np.zeros((n, 2))
    for i in range(n):
        n00 = -math.sin(angles[i, 0])
        n01 = math.cos(angles[i, 0])
        n10 = -math.sin(angles[i, 1])
        n11 = math.cos(angles[i, 1])
        r2 = radius[i] ** 2
        o0 = (n00 * curvatures[i, 0, 0] + n01 * curvatures[i, 0, 1]) * BEND_SHIFT_SHARE * r2
        o1 = (n10 * curvatures[i, 1, 0] + n11 * curvatures[i, 1, 1]) * BEND_SHIFT_SHARE * r2
        if not math.isfinite(o0):
            o0 = 0.0
        if not math.isfinite(o1):
            o1 = 0.0
        det = n00 * n11 - n01 * n10
        if abs(det) > 0.1:                    # the lines meet at more than ~6 deg
            out[i, 0] = (o0 * n11 - o1 * n01) / det
            out[i, 1] = (n00 * o1 - n10 * o0) / det
    return out
