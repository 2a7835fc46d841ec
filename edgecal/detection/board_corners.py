"""A found board's final corners: refined once more (cornerSubPix, the rim again, the saddle fit), corners
that slid along an edge put back where their neighbours say, and an accepted board's corners polished by the
X-junction fit."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from edgecal.detection.completion import dense_labels_of, line_predictions, predict_holes
from edgecal.detection.line_bend import bend_shift
from edgecal.detection.params import DetectorParams
from edgecal.detection.subpixel import (
    grid_line_angles,
    nearest_spacing,
    refine_corners,
    refine_rim,
    saddle_refine,
    xjunction_fit,
    xjunction_radius,
)

# A final corner further than this fraction of a square from where its neighbours put it slid along an edge.
SLID_FRACTION = 0.2
# A kink (_kinked_corners) of this many times the slide threshold is looked at: a slid corner's own kink is 1.5x
# the second difference it makes there (3d against 2d).
KINK_FACTOR = 1.5
# A corner the X-junction fit did not place is fitted again from where a grid line through it puts it when
# that is at least this far from where it is (_refit_from_grid_lines).
REFIT_MIN_OFFSET_PX = 1.0
# ... in at most this many rounds, each from the corners placed before it.
REFIT_ROUNDS = 4


def final_corners(smooth: np.ndarray, xy: np.ndarray, ids: np.ndarray, p: DetectorParams,
                  spacing: np.ndarray | None = None) -> np.ndarray:
    """A board's final corners: cornerSubPix with the window from the grid's own spacing (``spacing``, or
    the corners' nearest-neighbour distances), the corners on the board's rim again with a smaller window
    where that continues the grid's lines better (refine_rim), then (refiner "saddle") the saddle fit.

    The cornerSubPix pass is needed even where ``xy`` come from cornerSubPix already (measured: without it
    a box_stereo board is lost and 37 corners of the real sets move by 3-10 px): completion's corners stop
    at 0.01 px or 12 iterations, and a corner that slid does not stop in 40.
    """
    spacing = nearest_spacing(xy) if spacing is None else spacing
    xy, window = refine_rim(smooth, refine_corners(smooth, xy, spacing), ids, spacing)
    return xy if p.subpixel_refiner == "cornersubpix" else saddle_refine(smooth, xy, window)


def provisional_corners(smooth: np.ndarray, xy: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """The corners of a board found at half resolution, which detector._refine_at_full_resolution refines
    again at full resolution (cornerSubPix twice, the saddle fit, slid corners put back): the search's
    corners ``xy`` (N, 2; ``ids`` (N, 2): col, row) with only the rim pass of final_corners (refine_rim).

    The rim pass cannot wait: on Bouguet's board, whose outer squares are cut short, a rim corner it leaves
    out starts 6-10 px off, beyond the full-resolution refinement's reach. The rest is done there only
    (which moved no final corner of bench/detect.py's images, noisy copies included, by more than 0.08 px).
    """
    xy = np.asarray(xy, dtype=np.float64)
    return refine_rim(smooth, xy, ids, nearest_spacing(xy))[0]


def polish_corners(grey: np.ndarray, smooth: np.ndarray, xy: np.ndarray, ids: np.ndarray, p: DetectorParams
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(corners, fitted (N,) bool, bend_px (N,), noise (N, 2, 2)): an accepted board's corners ``xy``
    (N, 2; ``ids`` (N, 2): col, row) from final_corners, moved by the X-junction fit on the raw image
    ``grey`` (refiner "xjunction"; unchanged otherwise), each in its disc (xjunction_radius on ``smooth``)
    from the grid's line directions there, and less the fit's shift on a lens-bent grid
    (line_bend.bend_shift); ``fitted``: the corners it placed (the others keep their start); ``bend_px``:
    the length of the shift taken off each (0 elsewhere); ``noise``: the fit's covariance per unit image
    noise variance (xjunction_fit; NaN where not placed).

    Only the corners a detection reports: the checks that accept a board (its regularity, whether it is
    part of a larger grid) keep working on final_corners' corners, so the X-junction fit changes where
    corners are, never which boards are found (on a box whose faces meet, corners moved by a few
    hundredths of a pixel let completion grow a board by a false line along the next face).
    """
    if p.subpixel_refiner != "xjunction" or not len(xy):
        return unpolished(xy)
    angles, radius = grid_line_angles(xy, ids), xjunction_radius(smooth, xy, ids)
    out, fitted, noise = xjunction_fit(grey, xy, angles, radius)
    # (each round's corners predict the next round's: a rim where several corners slid is put back in turns)
    rounds = 0
    while rounds < REFIT_ROUNDS and _refit_from_grid_lines(grey, smooth, out, ids, fitted, noise):
        rounds += 1
    if rounds:
        angles, radius = grid_line_angles(out, ids), xjunction_radius(smooth, out, ids)
    # the fit's straight lines sit off a lens-bent grid's edges (line_bend): the corners it placed put back
    shift = fitted[:, None] * bend_shift(out, ids, angles, radius)
    return out - shift, fitted, np.hypot(shift[:, 0], shift[:, 1]), noise


def _refit_from_grid_lines(grey: np.ndarray, smooth: np.ndarray, xy: np.ndarray, ids: np.ndarray, fitted: np.ndarray,
                           noise: np.ndarray) -> bool:
    """The corners ``xy`` (N, 2; ``ids`` (N, 2)) the X-junction fit did not place (``fitted`` False), started
    again from where the grid lines through them put them and fitted again; ``xy``, ``fitted`` and ``noise``
    (as xjunction_fit's) are updated in place for those it now places. Whether any was.

    A corner the fit does not place is often one cornerSubPix slid along an edge: at a fisheye's rim
    (squares thin and bent, the homographies that predict and resettle corners a quarter of a square off)
    such corners stayed 1-6 px off on boards found whole (synthetic 150-200 degree views of a 6x7 board:
    9 boards in 78 scored partial for it). Each is predicted from the placed corners alone, along each of
    its lines (completion.line_predictions), where that is more than REFIT_MIN_OFFSET_PX from it, and the
    fit is started there (not cornerSubPix first: from a start 1-2 px off on a rim's small squares its
    window reached the board's edge and ran off); it takes the first fit that lands within a quarter of a
    square of its prediction when every such fit lands on the same corner (within a pixel). The corners the
    fit placed are never moved, so which boards are found does not change.
    """
    todo = np.flatnonzero(~fitted)
    if not len(todo) or fitted.sum() < 3:
        return False
    dense, lo = dense_labels_of(ids[fitted], xy[fitted])
    preds, spacing, ok = line_predictions(dense, lo, ids[todo])
    # (a start its lines put where it already is gives the same corner: most rim corners a board's cut outer
    # squares leave without a disc)
    ok &= np.linalg.norm(preds - xy[todo][:, None], axis=2) > REFIT_MIN_OFFSET_PX
    found = np.full((len(todo), preds.shape[1], 2), np.nan)
    found_noise = np.full((len(todo), preds.shape[1], 2, 2), np.nan)
    for side in range(preds.shape[1]):
        use = np.flatnonzero(ok[:, side])
        if not len(use):
            continue
        start, step = preds[use, side], spacing[use, side]
        trial = xy.copy()
        trial[todo[use]] = start
        fit, placed, fit_noise = xjunction_fit(grey, start, grid_line_angles(trial, ids)[todo[use]],
                                               xjunction_radius(smooth, trial, ids)[todo[use]], math.inf)
        placed &= np.hypot(*(fit - start).T) < 0.25 * step
        found[use[placed], side] = fit[placed]
        found_noise[use[placed], side] = fit_noise[placed]
    refitted = False
    for k, i in enumerate(todo.tolist()):
        sides = np.flatnonzero(np.isfinite(found[k, :, 0]))
        if len(sides) and (np.hypot(*(found[k, sides] - found[k, sides[0]]).T) <= 1.0).all():
            xy[i], noise[i], fitted[i] = found[k, sides[0]], found_noise[k, sides[0]], True
            refitted = True
    return refitted


def unpolished(xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """polish_corners' result for corners ``xy`` (N, 2) it leaves as they are: none fitted, no bend, no fit
    noise (NaN)."""
    n = len(xy)
    return xy, np.zeros(n, dtype=bool), np.zeros(n), np.full((n, 2, 2), np.nan)


def resettle_slid_corners(smooth: np.ndarray, ids: np.ndarray, xy: np.ndarray, p: DetectorParams) -> np.ndarray:
    """Corners that slid along an edge, refined again from where their neighbours put them.

    On a steeply slanted board cornerSubPix is ill-conditioned along thin squares and can slide a corner
    along one of its edges by a good part of a square; the grid checks barely see a sideways slip of an
    outer corner. Each corner is predicted from a local homography of its neighbours (leaving it out, all
    corners in one batch); one further than SLID_FRACTION of a square from its prediction is refined again
    from the prediction, and the new position is kept when it agrees with the prediction better. Only the
    corners where a row or column kinks (_kinked_corners) are predicted.
    """
    out = np.array(xy, dtype=np.float64)
    ids = np.asarray(ids, dtype=np.int64)
    cols, rows = int(ids[:, 0].max()) + 1, int(ids[:, 1].max()) + 1
    if len(ids) != cols * rows or min(cols, rows) < 3:
        return out
    spacing = nearest_spacing(out)
    dense_spacing = np.empty((rows, cols))
    dense_spacing[ids[:, 1], ids[:, 0]] = spacing
    order = np.empty((rows, cols), dtype=np.int64)  # the corner at each (row, col)
    order[ids[:, 1], ids[:, 0]] = np.arange(len(ids))
    dense = np.empty((rows, cols, 2))
    for _ in range(3):  # a slid corner misleads its neighbours' predictions: repeat once it is back
        dense[ids[:, 1], ids[:, 0]] = out
        flagged = _kinked_corners(dense, dense_spacing)
        if not flagged.any():
            break
        sel = order[flagged]
        grid = dict(zip(map(tuple, np.asarray(ids).tolist()), out))
        preds, keys, _sp = predict_holes(grid, [(int(c), int(r)) for c, r in ids[sel]])
        if not keys:
            break
        sel = np.array([order[r, c] for c, r in keys])
        pred = np.asarray(preds)
        off = np.linalg.norm(out[sel] - pred, axis=1)
        slid = off > np.maximum(SLID_FRACTION * spacing[sel], 1.5)
        if not slid.any():
            break
        again = final_corners(smooth, pred[slid], ids[sel][slid], p, spacing[sel][slid])
        better = (np.linalg.norm(again - pred[slid], axis=1) < off[slid]) \
            & _settled(smooth, again, spacing[sel][slid])
        if not better.any():
            break
        out[sel[slid][better]] = again[better]
    return out


def _settled(smooth: np.ndarray, xy: np.ndarray, spacing: np.ndarray) -> np.ndarray:
    """(M,) bool: the corners ``xy`` (M, 2) that cornerSubPix, free to go anywhere, leaves within half the
    slide threshold: a corner. Where the lines' prediction misses the corner by more than half a window
    (a fisheye's rim: a board's outer corner 10 px off it on bench/calibrate's renders), the refinement
    from there runs off, keeps its start on the square's edge, and that start agrees with the prediction
    perfectly; from an edge point cornerSubPix runs off again."""
    moved = np.linalg.norm(refine_corners(smooth, xy, spacing, max_move_px=np.inf) - xy, axis=1)
    return moved < 0.5 * np.maximum(SLID_FRACTION * spacing, 1.5)


@njit(cache=True, nogil=True)
def _kinked_corners(dense: np.ndarray, spacing: np.ndarray) -> np.ndarray:
    """(rows, cols) bool: the corners of a full grid ``dense`` (rows, cols, 2) where its row or column kinks
    by more than KINK_FACTOR x max(SLID_FRACTION x ``spacing`` (rows, cols), 1.5) px: how far the line's
    second difference there departs from its neighbours' (linear through the next two at a line's second and
    last but one corner; on a line of 3 or 4 corners the second difference itself; a line's ends take their
    neighbour's). The cheap screen of resettle_slid_corners.

    A lens bends a line smoothly, so its second differences change slowly along it and cancel here, while a
    corner slid by d along an edge puts -2d into its own and d into its neighbours' (3d here, 2d at the
    neighbours; the second difference alone, 2d, flagged every corner of a fisheye's board: 748 of 720 in
    three rounds on the urban fisheye set, now 70, and two corners of its view 5 that sat on their junctions
    were "resettled" 12-14 px along an edge from a homography's poor prediction there)."""
    rows, cols = dense.shape[0], dense.shape[1]
    kink = np.zeros((rows, cols))
    for axis in range(2):
        n = rows if axis == 0 else cols
        m = cols if axis == 0 else rows
        if n < 3:
            continue
        d2 = np.zeros((n, 2))
        for j in range(m):
            for k in range(1, n - 1):
                r0, c0, r1, c1, r2, c2 = (k - 1, j, k, j, k + 1, j) if axis == 0 else (j, k - 1, j, k, j, k + 1)
                for q in range(2):
                    d2[k, q] = dense[r0, c0, q] - 2.0 * dense[r1, c1, q] + dense[r2, c2, q]
            for k in range(1, n - 1):
                ex = 0.0
                ey = 0.0
                if 2 <= k <= n - 3:
                    ex = 0.5 * (d2[k - 1, 0] + d2[k + 1, 0])
                    ey = 0.5 * (d2[k - 1, 1] + d2[k + 1, 1])
                elif k == 1 and n >= 5:
                    ex = 2.0 * d2[2, 0] - d2[3, 0]
                    ey = 2.0 * d2[2, 1] - d2[3, 1]
                elif k == n - 2 and n >= 5:
                    ex = 2.0 * d2[n - 3, 0] - d2[n - 4, 0]
                    ey = 2.0 * d2[n - 3, 1] - d2[n - 4, 1]
                d = math.hypot(d2[k, 0] - ex, d2[k, 1] - ey)
                r1, c1 = (k, j) if axis == 0 else (j, k)
                kink[r1, c1] = max(kink[r1, c1], d)
                if k == 1:
                    r0, c0 = (0, j) if axis == 0 else (j, 0)
                    kink[r0, c0] = max(kink[r0, c0], d)
                if k == n - 2:
                    r2, c2 = (n - 1, j) if axis == 0 else (j, n - 1)
                    kink[r2, c2] = max(kink[r2, c2], d)
    out = np.zeros((rows, cols), dtype=np.bool_)
    for r in range(rows):
        for c in range(cols):
            out[r, c] = kink[r, c] > KINK_FACTOR * max(SLID_FRACTION * spacing[r, c], 1.5)
    return out
