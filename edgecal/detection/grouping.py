"""Step 6: grouping accepted corners into grids (Eq. 6) verified by the cross-ratio (Eq. 7-8).

Every accepted point carries its four border directions. A point is linked, along each direction, to the
nearest accepted point that lies close to that line (Eq. 6, with the distance threshold growing with the
step so one rule serves 8 px and 150 px squares) and that has a direction pointing back. Only mutual links
survive. A breadth-first walk over the links gives every point integer grid labels (u, v): a step along a
point's direction k moves by one label along the axis that k belongs to, and the cyclic order of the four
directions carries the axes from point to point. Every run of four consecutive points on a grid line must
have the cross-ratio of four equally spaced points, 4/3 (Eq. 8); points that break it are removed.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

CROSS_RATIO_EQUAL_STEPS = 4.0 / 3.0  # Cr of positions 0, 1, 2, 3 (Eq. 7)


def cross_ratio(x1: float, x2: float, x3: float, x4: float) -> float:
    """Eq. (7): the cross-ratio of four positions along a line."""
    return (x3 - x1) * (x4 - x2) / ((x3 - x2) * (x4 - x1))


@njit(cache=True, nogil=True)
def _angle_dist(a: float, b: float) -> float:
    d = abs(a - b) % (2.0 * math.pi)
    return min(d, 2.0 * math.pi - d)


@njit(cache=True, nogil=True)
def link_neighbours(pts: np.ndarray, dirs: np.ndarray, max_step: np.ndarray, line_frac: float,
                    line_min: float, angle_tol: float, max_step_ratio: float) -> np.ndarray:
    """Mutual nearest neighbours of every point along each of its four directions (Eq. 6).

    pts (K, 2), dirs (K, 4) sorted radians, max_step (K,) longest step considered from each point.
    Returns nbr (K, 4) int64: the index linked along direction k, or -1.
    """
    k_pts = pts.shape[0]
    cand = np.full((k_pts, 4), -1, dtype=np.int64)
    back = np.full((k_pts, 4), -1, dtype=np.int64)
    step = np.zeros((k_pts, 4))
    for i in range(k_pts):
        for k in range(4):
            c = math.cos(dirs[i, k])
            s = math.sin(dirs[i, k])
            best_t = 1e18
            best_j = -1
            best_m = -1
            for j in range(k_pts):
                if j == i:
                    continue
                vx = pts[j, 0] - pts[i, 0]
                vy = pts[j, 1] - pts[i, 1]
                t = vx * c + vy * s
                if t <= 1.0 or t > max_step[i] or t >= best_t:
                    continue
                perp = abs(vx * s - vy * c)
                if perp > max(line_min, line_frac * t):
                    continue
                # j must have a border direction pointing back at i.
                back_angle = math.atan2(-vy, -vx)
                m_best = -1
                d_best = angle_tol
                for m in range(4):
                    d = _angle_dist(dirs[j, m], back_angle)
                    if d < d_best:
                        d_best = d
                        m_best = m
                if m_best < 0:
                    continue
                best_t = t
                best_j = j
                best_m = m_best
            cand[i, k] = best_j
            back[i, k] = best_m
            step[i, k] = best_t
    nbr = np.full((k_pts, 4), -1, dtype=np.int64)
    for i in range(k_pts):
        for k in range(4):
            j = cand[i, k]
            if j < 0:
                continue
            m = back[i, k]
            if cand[j, m] != i:
                continue
            # A link much longer than the opposite one skipped a missing corner.
            opp = step[i, (k + 2) % 4]
            if cand[i, (k + 2) % 4] >= 0 and step[i, k] > max_step_ratio * opp:
                continue
            opp_j = step[j, (m + 2) % 4]
            if cand[j, (m + 2) % 4] >= 0 and step[i, k] > max_step_ratio * opp_j:
                continue
            nbr[i, k] = j
    return nbr


@njit(cache=True, nogil=True)
def label_components(nbr: np.ndarray, order: np.ndarray, alive: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Breadth-first grid labelling over mutual links.

    Returns (labels (K, 3) int: component, u, v; -1 component for unlabelled points, axis (K,) int: the
    index of each point's +u direction). Seeds are taken in ``order``; dead points are skipped. A link whose
    far end already carries another label is ignored (the walk that got there first wins; the cross-ratio
    check then catches wrong labels).
    """
    k_pts = nbr.shape[0]
    labels = np.full((k_pts, 3), -1, dtype=np.int64)
    axis = np.zeros(k_pts, dtype=np.int64)
    du = np.array([1, 0, -1, 0])
    dv = np.array([0, 1, 0, -1])
    queue = np.empty(k_pts, dtype=np.int64)
    # label -> point of the current component; labels stay within +-k_pts of the seed
    span = 2 * k_pts + 1
    used = dict()
    used[0] = 0
    comp = 0
    for seed in order:
        if not alive[seed] or labels[seed, 0] >= 0:
            continue
        labels[seed, 0] = comp
        labels[seed, 1] = 0
        labels[seed, 2] = 0
        axis[seed] = 0
        used.clear()
        used[k_pts * span + k_pts] = seed
        head = 0
        tail = 1
        queue[0] = seed
        while head < tail:
            i = queue[head]
            head += 1
            for k in range(4):
                j = nbr[i, k]
                if j < 0 or not alive[j] or labels[j, 0] >= 0:
                    continue
                rel = (k - axis[i]) % 4
                u = labels[i, 1] + du[rel]
                v = labels[i, 2] + dv[rel]
                key = (u + k_pts) * span + (v + k_pts)
                if key in used:
                    continue
                back = -1
                for m in range(4):
                    if nbr[j, m] == i:
                        back = m
                        break
                if back < 0:
                    continue
                labels[j, 0] = comp
                labels[j, 1] = u
                labels[j, 2] = v
                axis[j] = (back - (rel + 2)) % 4
                used[key] = j
                queue[tail] = j
                tail += 1
        comp += 1
    return labels, axis


@njit(cache=True, nogil=True, error_model="numpy")
def cross_ratio_strikes(pts: np.ndarray, labels: np.ndarray, tolerance: float) -> np.ndarray:
    """Eq. (8) on every run of four consecutive labels along every grid row and column.

    Returns, per point, how many runs through it fail the check. Positions along a run are cumulative step
    lengths: exact for a straight line and, unlike a projection on the chord, unbiased when a lens bends it.
    pts (K, 2) float64, labels (K, 3) int64 (component, u, v; component -1 = none). One pass per component
    over its dense label array (error_model numpy: a zero step gives inf/NaN, a failed run, not an error).
    """
    k_pts = pts.shape[0]
    strikes = np.zeros(k_pts, dtype=np.int64)
    n_comp = 0
    for i in range(k_pts):
        n_comp = max(n_comp, labels[i, 0] + 1)
    big = 1 << 62
    lo = np.full((n_comp, 2), big, dtype=np.int64)
    hi = np.full((n_comp, 2), -big, dtype=np.int64)
    for i in range(k_pts):
        c = labels[i, 0]
        if c < 0:
            continue
        for a in range(2):
            lo[c, a] = min(lo[c, a], labels[i, 1 + a])
            hi[c, a] = max(hi[c, a], labels[i, 1 + a])
    run = np.empty(4, dtype=np.int64)
    for c in range(n_comp):
        if hi[c, 0] < lo[c, 0]:
            continue
        nu = hi[c, 0] - lo[c, 0] + 1
        nv = hi[c, 1] - lo[c, 1] + 1
        index = np.full((nv, nu), -1, dtype=np.int64)
        for i in range(k_pts):
            if labels[i, 0] == c:
                index[labels[i, 2] - lo[c, 1], labels[i, 1] - lo[c, 0]] = i
        for along_u in (True, False):  # rows, then columns
            n_lines = nv if along_u else nu
            length = nu if along_u else nv
            if length < 4:
                continue
            for line in range(n_lines):
                for start in range(length - 3):
                    ok = True
                    for t in range(4):
                        run[t] = index[line, start + t] if along_u else index[start + t, line]
                        ok = ok and run[t] >= 0
                    if not ok:
                        continue
                    x2 = math.hypot(pts[run[1], 0] - pts[run[0], 0], pts[run[1], 1] - pts[run[0], 1])
                    x3 = x2 + math.hypot(pts[run[2], 0] - pts[run[1], 0], pts[run[2], 1] - pts[run[1], 1])
                    x4 = x3 + math.hypot(pts[run[3], 0] - pts[run[2], 0], pts[run[3], 1] - pts[run[2], 1])
                    cr = x3 * (x4 - x2) / ((x3 - x2) * x4)
                    if not abs(cr - CROSS_RATIO_EQUAL_STEPS) / CROSS_RATIO_EQUAL_STEPS <= tolerance:
                        for t in range(4):
                            strikes[run[t]] += 1
    return strikes


def group_grids(pts: np.ndarray, dirs: np.ndarray, spacing: np.ndarray, score: np.ndarray,
                line_distance_px: float, reference_spacing_px: float, cross_ratio_tolerance: float,
                angle_tol: float = math.radians(25.0), max_rounds: int = 6) -> tuple[np.ndarray, np.ndarray]:
    """Link, label and verify: returns (labels (K, 3) component/u/v, -1 = not in a grid; nbr (K, 4))."""
    k_pts = len(pts)
    if k_pts == 0:
        return np.full((0, 3), -1, dtype=np.int64), np.full((0, 4), -1, dtype=np.int64)
    # Eq. (6)'s d_l, scaled with the step: d_l at the reference square size, as a fraction of the step.
    line_frac = max(0.08, line_distance_px / reference_spacing_px)
    max_step = 3.0 * spacing
    nbr = link_neighbours(np.ascontiguousarray(pts, np.float64), np.ascontiguousarray(dirs, np.float64),
                          np.ascontiguousarray(max_step, np.float64), line_frac, 1.0, angle_tol, 1.8)
    alive = np.ones(k_pts, dtype=bool)
    order = np.argsort(-score, kind="stable")
    labels = np.full((k_pts, 3), -1, dtype=np.int64)
    for _ in range(max_rounds):
        labels, _axis = label_components(nbr, order, alive)
        strikes = cross_ratio_strikes(np.ascontiguousarray(pts, np.float64), labels, cross_ratio_tolerance)
        if not strikes.any():
            break
        # Remove the worst offenders only: a wrong point sits in more failing runs than its neighbours;
        # good points removed with it come back in the completion step.
        alive &= strikes < strikes.max()
    return labels, nbr
