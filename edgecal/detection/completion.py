"""Completing a grid: corners the probe missed are predicted from their neighbours and verified.

Noise, glare or a shadow can make the probe reject a few true corners, which leaves holes (or a missing
outer row) in a grid. Each missing label is predicted by a homography fitted to the nearby labelled
corners (local, so lens distortion does not matter), refined to sub-pixel, and accepted only if the probe
confirms a chessboard corner there and the refinement stayed near the prediction. Rows and columns are
added at the grid's sides the same way, so a grid grows up to the board's edge and stops at its margin.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from edgecal.detection.params import DetectorParams
from edgecal.detection.probe import (EDGE_ACROSS_RAY, M_ANGLE_ERR, M_CONTRAST, M_SIGN_FRAC, probe_candidates,
                                     probe_quality, probe_radii)
from edgecal.detection.subpixel import refine_corners

# Where the squares beyond a grid line are sampled, as fractions of one grid step outwards (0.5 = their
# centre). The outermost squares of many printed boards are cut narrower than the others, so the centre
# alone can miss them; next to the line the corners' blur mixes both sides: several depths are tried.
BEYOND_STEP_FRACTIONS = (0.2, 0.35, 0.5)


def _local_homography(grid: dict[tuple[int, int], np.ndarray], u_lo: int, u_hi: int, v_lo: int,
                      v_hi: int) -> np.ndarray | None:
    """Homography label -> image fitted to the corners with labels in [u_lo, u_hi] x [v_lo, v_hi]."""
    src, dst = [], []
    for (a, b), xy in grid.items():
        if u_lo <= a <= u_hi and v_lo <= b <= v_hi:
            src.append((a, b))
            dst.append(xy)
    if len(src) < 4:
        return None
    src_a = np.asarray(src, np.float64)
    if len(np.unique(src_a[:, 0])) < 2 or len(np.unique(src_a[:, 1])) < 2:
        return None
    h, _ = cv2.findHomography(src_a, np.asarray(dst, np.float64), 0)
    return h


def _apply(h: np.ndarray, labels: np.ndarray) -> np.ndarray:
    p = np.c_[labels, np.ones(len(labels))] @ h.T
    with np.errstate(divide="ignore", invalid="ignore"):  # a point on the horizon: inf, rejected later
        return p[:, :2] / p[:, 2:3]


def _predict(h: np.ndarray, labels: list[tuple[int, int]]) -> tuple[np.ndarray, np.ndarray]:
    """Image positions of ``labels`` and the distance to the nearest neighbouring corner there, pixels."""
    lab = np.asarray(labels, np.float64)
    p = _apply(h, lab)
    # the nearest of the eight neighbours: on a slanted board a diagonal one can be the closest
    steps = [np.linalg.norm(_apply(h, lab + d) - p, axis=1)
             for d in ((1.0, 0.0), (0.0, 1.0), (1.0, 1.0), (1.0, -1.0))]
    return p, np.min(steps, axis=0)


def _cells_beyond(grid: dict[tuple[int, int], np.ndarray], line: list[tuple[int, int]],
                  outward: tuple[int, int], smooth: np.ndarray, fraction: float) -> np.ndarray | None:
    """Mean intensity of the squares just outside a grid line, in order along it, sampled ``fraction`` of a
    grid step outwards (None: not measurable, e.g. outside the image or too short)."""
    du, dv = outward
    along = (1 - abs(du), 1 - abs(dv))
    ordered = sorted(line, key=lambda l: l[0] * along[0] + l[1] * along[1])
    # Each line point stepped one square outwards, extrapolated along its own grid line (quadratic when two
    # inner points are known: fisheye lenses bend the lines too much for one homography to reach outside).
    outer = []
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
    cells = []
    for k in range(len(ordered) - 1):
        a0, a1 = grid.get(ordered[k]), grid.get(ordered[k + 1])
        b0, b1 = outer[k], outer[k + 1]
        if a0 is None or a1 is None or b0 is None or b1 is None:
            continue
        mid = 0.5 * (a0 + a1)
        cells.append(mid + fraction * (0.5 * (b0 + b1) - mid))
    if len(cells) < 3:
        return None
    hh, ww = smooth.shape
    vals = []
    for x, y in cells:
        if not (1 <= x < ww - 2 and 1 <= y < hh - 2):
            return None
        xi, yi = int(round(x)), int(round(y))
        vals.append(float(smooth[yi - 1:yi + 2, xi - 1:xi + 2].mean()))
    return np.asarray(vals)


def squares_beyond_alternate(grid: dict[tuple[int, int], np.ndarray], line: list[tuple[int, int]],
                             outward: tuple[int, int], smooth: np.ndarray, min_contrast: float) -> bool:
    """Whether the squares just outside a grid line alternate black/white, as they must at a row of corners.

    A board's outermost squares meet its white margin in points the probe can take for X-corners (the
    margin is white on both sides, the background beyond may be dark). Such a line is geometrically a
    perfect grid row; what gives it away is the uniform margin beyond it. This is the positive evidence a
    new outer line needs; squares that cannot be measured (outside the image) count as alternating.
    """
    for fraction in BEYOND_STEP_FRACTIONS:
        vals = _cells_beyond(grid, line, outward, smooth, fraction)
        if vals is None:
            return True
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
    for fraction in BEYOND_STEP_FRACTIONS:
        vals = _cells_beyond(grid, line, outward, smooth, fraction)
        if vals is None or np.mean(np.abs(np.diff(vals)) < min_contrast) < 0.7:
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


def verify_predictions(smooth: np.ndarray, gx: np.ndarray, gy: np.ndarray, preds: np.ndarray,
                       spacing: np.ndarray, params: DetectorParams, pinned: np.ndarray,
                       accepted: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Refine predicted corners and keep those the probe confirms near their prediction.

    Returns (refined (M, 2), good (M,) bool, quality (M,) as probe_quality). A point the probe already
    accepted within 0.4 x spacing of a prediction is taken as it is (grouping may have missed the link,
    e.g. along a line a fisheye lens bends hard). Predictions that are ``pinned`` down independently
    (holes inside a grid: neighbours on all sides; a tracked board: the pose) only need the probe to see
    a corner there (thresholds relaxed further); the others (new rows outside a grid) must pass the probe
    properly. Either way the refinement must stay within 0.25 x spacing of the prediction.
    """
    if accepted is not None and len(accepted):
        from scipy.spatial import cKDTree

        d, j = cKDTree(accepted).query(preds)
        snap = d < 0.4 * spacing
        preds = np.where(snap[:, None], accepted[np.minimum(j, len(accepted) - 1)], preds)
    h, w = smooth.shape
    inside = ((preds[:, 0] > 2) & (preds[:, 1] > 2) & (preds[:, 0] < w - 3) & (preds[:, 1] < h - 3))
    refined = preds.copy()
    if inside.any():
        refined[inside] = refine_corners(smooth, preds[inside], spacing[inside])
    radii = probe_radii(spacing, params)
    ok, _dirs, meas = probe_candidates(
        gx, gy, smooth, np.ascontiguousarray(refined), np.ascontiguousarray(radii), params.probe_angles,
        params.probe_inner_radius_px, EDGE_ACROSS_RAY, math.radians(params.angle_diff_max_deg),
        params.sign_fraction, params.min_contrast * 0.5, params.min_peak_ratio * 0.8)
    pinned_ok = ((meas[:, M_ANGLE_ERR] < math.radians(1.5 * params.angle_diff_max_deg))
                 & (meas[:, M_SIGN_FRAC] >= 0.6) & (meas[:, M_CONTRAST] >= 0.5 * params.min_contrast))
    near = np.linalg.norm(refined - preds, axis=1) < 0.25 * spacing
    return refined, (ok | (pinned & pinned_ok)) & near & inside, probe_quality(meas, params)


def _extrapolate(grid: dict[tuple[int, int], np.ndarray], labels: list[tuple[int, int]],
                 outward: tuple[int, int]) -> tuple[list[np.ndarray], list[float], list[tuple[int, int]]]:
    """Predict a new outer line one step ``outward``, each point along its own grid line.

    Quadratic extrapolation from the three nearest points of that line (linear from two): unlike a homography
    it follows lines that a fisheye lens bends. Returns (points, nearest-corner distances, their labels).
    """
    du, dv = outward
    pts, spacing, keys = [], [], []
    for u, v in labels:
        p0 = grid.get((u - du, v - dv))
        p1 = grid.get((u - 2 * du, v - 2 * dv))
        p2 = grid.get((u - 3 * du, v - 3 * dv))
        if p0 is None or p1 is None:
            continue
        new = 2.0 * p0 - p1 if p2 is None else 3.0 * p0 - 3.0 * p1 + p2
        along = [grid.get((u - du + dv, v - dv + du)), grid.get((u - du - dv, v - dv - du))]
        dists = [float(np.hypot(*(new - p0)))] + [float(np.hypot(*(q - p0))) for q in along if q is not None]
        pts.append(new)
        spacing.append(min(dists))
        keys.append((u, v))
    return pts, spacing, keys


def complete_grid(grid: dict[tuple[int, int], np.ndarray], smooth: np.ndarray, gx: np.ndarray,
                  gy: np.ndarray, max_dim: int, params: DetectorParams,
                  accepted: np.ndarray | None = None) -> dict[tuple[int, int], np.ndarray]:
    """Fill holes and grow the grid at its sides (up to ``max_dim`` labels per axis); returns a new dict.

    ``accepted``: points the probe accepted on this level, tried first at every predicted position.
    """
    grid = dict(grid)
    for _ in range(2 * max_dim + 2):
        us = [u for u, _ in grid]
        vs = [v for _, v in grid]
        u0, u1, v0, v1 = min(us), max(us), min(vs), max(vs)
        added = False
        # Holes: each from a homography of its own neighbourhood (lens distortion is local).
        holes = [(u, v) for u in range(u0, u1 + 1) for v in range(v0, v1 + 1) if (u, v) not in grid]
        preds, keys, spac = [], [], []
        for (u, v) in holes:
            # the nearest ring of neighbours first: under strong lens distortion a wider patch is not planar
            h = _local_homography(grid, u - 1, u + 1, v - 1, v + 1)
            if h is None:
                h = _local_homography(grid, u - 2, u + 2, v - 2, v + 2)
            if h is not None:
                p, sp = _predict(h, [(u, v)])
                if not (np.isfinite(p).all() and np.isfinite(sp).all()):
                    continue  # on the horizon of the local homography: no prediction
                preds.append(p[0])
                keys.append((u, v))
                spac.append(sp[0])
        # Sides: a whole new row or column, each point extrapolated along its own grid line.
        sides = []
        if u1 - u0 + 1 < max_dim:
            sides += [([(u0 - 1, v) for v in range(v0, v1 + 1)], (-1, 0)),
                      ([(u1 + 1, v) for v in range(v0, v1 + 1)], (1, 0))]
        if v1 - v0 + 1 < max_dim:
            sides += [([(u, v0 - 1) for u in range(u0, u1 + 1)], (0, -1)),
                      ([(u, v1 + 1) for u in range(u0, u1 + 1)], (0, 1))]
        groups: list[tuple[int, list | None, tuple[int, int] | None]] = [(len(keys), None, None)]
        for labels, outward in sides:
            p, sp, ok_labels = _extrapolate(grid, labels, outward)
            if not ok_labels:
                continue
            preds.extend(p)
            keys.extend(ok_labels)
            spac.extend(sp)
            groups.append((len(keys), labels, outward))
        if not keys:
            break
        n_holes = groups[0][0]
        refined, good, _quality = verify_predictions(smooth, gx, gy, np.asarray(preds), np.asarray(spac), params,
                                np.arange(len(keys)) < n_holes, accepted)
        start = 0
        for end, labels, outward in groups:
            sel = range(start, end)
            start = end
            if labels is not None:
                # A side line is taken only when most of it is confirmed and squares lie beyond it.
                if sum(good[i] for i in sel) < max(2, 0.6 * len(labels)):
                    continue
                trial = dict(grid)
                trial.update({keys[i]: refined[i] for i in sel if good[i]})
                line = [keys[i] for i in sel if good[i]]
                if not squares_beyond_alternate(trial, line, outward, smooth, params.min_contrast):
                    continue
            for i in sel:
                if good[i]:
                    grid[keys[i]] = refined[i]
                    added = True
        if not added:
            break
    return grid
