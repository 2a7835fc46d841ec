"""What a lens's bent grid lines do to the X-junction fit: the shift of its straight-line model, predicted
from the board's own corners.

The X-junction fit (subpixel.xjunction_refine) models a corner as two straight edges over a disc of radius
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

Pure functions: corners, ids and disc radii in, shifts out; a few array operations per board.
"""

from __future__ import annotations

import numpy as np

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
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    ids = np.asarray(ids, dtype=np.int64).reshape(-1, 2)
    curvatures = np.full((len(xy), 2, 2), np.nan)
    if len(xy) < 3:
        return curvatures
    lo = ids.min(axis=0)
    cols, rows = (ids.max(axis=0) - lo + 1).tolist()
    for axis, (n_lines, n_along) in enumerate(((rows, cols), (cols, rows))):
        if n_along < 3:
            continue
        line = ids[:, 1 - axis] - lo[1 - axis]            # which row (axis 0) or column (axis 1)
        along = ids[:, axis] - lo[axis]                     # the index along it
        points = np.full((n_lines, n_along, 2), np.nan)
        points[line, along] = xy
        present = np.isfinite(points[:, :, 0])
        count = present.sum(axis=1)
        j = np.arange(n_along, dtype=np.float64) - 0.5 * (n_along - 1)
        d1 = np.full((n_lines, n_along, 2), np.nan)
        d2 = np.full((n_lines, n_along, 2), np.nan)
        # where each corner's derivatives are read: its own index, the ends' one index inwards
        first = np.argmax(present, axis=1)
        last = n_along - 1 - np.argmax(present[:, ::-1], axis=1)
        at = np.clip(np.arange(n_along)[None, :], (first + 1)[:, None], np.maximum(last - 1, first + 1)[:, None])
        at = np.minimum(at, n_along - 1)                    # a line of one corner, the last (not fitted)
        t_at = j[at]
        for degree, use in ((3, count >= _CUBIC_MIN_CORNERS), (2, (count >= 3) & (count < _CUBIC_MIN_CORNERS))):
            if not use.any():
                continue
            coef = _weighted_polyfit(j, points[use], present[use], degree)        # (L, degree + 1, 2)
            d1[use], d2[use] = _derivatives(coef, t_at[use])
        speed2 = np.sum(d1 * d1, axis=2)
        tangent = d1 / np.sqrt(speed2)[..., None]
        curvature = (d2 - np.sum(d2 * tangent, axis=2)[..., None] * tangent) / speed2[..., None]
        curvatures[:, axis] = curvature[line, along]
    return curvatures


def _weighted_polyfit(j: np.ndarray, points: np.ndarray, present: np.ndarray, degree: int) -> np.ndarray:
    """Least-squares polynomials (L, degree + 1, 2; power 0 first) in ``j`` (n,) through the present points
    (L, n, 2; ``present`` (L, n) bool) of L lines, x and y alike."""
    vander = j[:, None] ** np.arange(degree + 1)[None, :]              # (n, degree + 1)
    w = present.astype(np.float64)
    normal = np.einsum("ln,na,nb->lab", w, vander, vander)
    rhs = np.einsum("ln,na,lnc->lac", w, vander, np.where(present[..., None], points, 0.0))
    return np.linalg.solve(normal, rhs)


def _derivatives(coef: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """First and second derivatives (L, n, 2) of the polynomials ``coef`` (L, degree + 1, 2) at ``t`` (L, n)."""
    powers = np.arange(coef.shape[1])
    p1 = np.where(powers >= 1, powers, 0)[None, None, :] * t[..., None] ** np.maximum(powers - 1, 0)
    p2 = np.where(powers >= 2, powers * (powers - 1), 0)[None, None, :] * t[..., None] ** np.maximum(powers - 2, 0)
    return np.einsum("lnp,lpc->lnc", p1, coef), np.einsum("lnp,lpc->lnc", p2, coef)


def bend_shift(xy: np.ndarray, ids: np.ndarray, angles: np.ndarray, radius: np.ndarray) -> np.ndarray:
    """(N, 2) px: where the X-junction fit puts each corner of a bent grid relative to the true junction
    (subtract it), for one board's corners ``xy`` (N, 2), ``ids`` (N, 2: col, row), the directions of its row
    and column there ``angles`` (N, 2) radians (subpixel.grid_line_angles) and the fit's disc radii ``radius``
    (N,) px. A line with fewer than three corners (no curvature known) counts as straight; where the two
    lines are too close to parallel to intersect well the shift is 0."""
    angles = np.asarray(angles, dtype=np.float64).reshape(-1, 2)
    curvatures = line_curvatures(xy, ids)
    normals = np.stack([-np.sin(angles), np.cos(angles)], axis=-1)                  # (N, 2 lines, 2)
    offset = np.sum(normals * curvatures, axis=-1) * BEND_SHIFT_SHARE * np.asarray(radius, np.float64)[:, None] ** 2
    offset = np.where(np.isfinite(offset), offset, 0.0)
    det = normals[:, 0, 0] * normals[:, 1, 1] - normals[:, 0, 1] * normals[:, 1, 0]
    ok = np.abs(det) > 0.1                    # the lines meet at more than ~6 deg
    safe = np.where(ok, det, 1.0)
    shift = np.stack([(offset[:, 0] * normals[:, 1, 1] - offset[:, 1] * normals[:, 0, 1]) / safe,
                      (normals[:, 0, 0] * offset[:, 1] - normals[:, 1, 0] * offset[:, 0]) / safe], axis=1)
    return np.where(ok[:, None], shift, 0.0)
