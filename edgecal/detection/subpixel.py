"""Step 5: sub-pixel localisation of accepted corners (cv2.cornerSubPix while searching; a saddle fit and an
X-junction model fit for the final corners, see saddle_refine, xjunction_fit and REFINERS).

cv2.cornerSubPix (gradient orthogonality: every gradient in the window is perpendicular to the vector from
the corner) is accurate to ~0.01 px on clean corners when its window holds only this corner's two edges,
so the window follows the local square size: half-width 0.5 x the nearest corner distance, 3..12 px
(smaller windows lose more to noise than they gain in isolation).
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from llvmlite import ir  # type: ignore[import-untyped]
from numba import njit, types
from numba.extending import intrinsic

FINAL_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 40, 0.001)
# Grid completion's predictions only need to be good to a few hundredths of a pixel (the probe works at
# that level); each board's corners get the full criteria once at the end. In noisy images cornerSubPix
# rarely reaches 0.001 px and runs all 40 iterations, the bulk of its cost. (The first refinement of the
# accepted points keeps the full criteria: grids grown from coarser seeds went astray on fisheye images,
# and with 20 iterations to 0.005 px an overexposed board with bloomed corners was lost.)
SEARCH_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 12, 0.01)


def subpixel_window(spacing: np.ndarray) -> np.ndarray:
    """Half-width of the refinement window for each local square size (pixels)."""
    # np.minimum/np.maximum: the same values as np.clip (NaN too) at a third of its call overhead
    return np.minimum(np.maximum(np.floor(0.5 * np.asarray(spacing)), 3), 12).astype(np.int64)


# A corner on a board's outer line sees, beyond it, a square of unknown extent: the outermost squares of
# many printed boards are cut short (Bouguet's 9x6 board: about half a square), and a window of half a
# square then reaches the board's edge, whose gradients pull the corner outwards by 1-3 px (34 of the 35
# corners a calibration of OpenCV's stereo sample dropped as outliers). Those corners are refined with the
# window of a square RIM_WINDOW_SCALE as large, but never below the window of a RIM_WINDOW_MIN_SPACING_PX
# square (smaller windows lose small squares to noise and blur: measured on the synthetic multi-board set).
RIM_WINDOW_SCALE = 0.7
RIM_WINDOW_MIN_SPACING_PX = 9.0


def on_board_rim(ids: np.ndarray, size: tuple[int, int] | None = None) -> np.ndarray:
    """(N,) bool: the corners of (N, 2) ids (col, row) on the outer lines of a board of ``size`` (cols, rows)
    inner corners, or (no size) of the grid the ids span."""
    ids = np.asarray(ids).reshape(-1, 2)
    if not len(ids):
        return np.zeros(0, dtype=bool)
    lo, hi = (ids.min(axis=0), ids.max(axis=0)) if size is None else (np.zeros(2), np.array(size) - 1)
    return ((ids == lo) | (ids == hi)).any(axis=1)


def window_spacing(spacing: np.ndarray, rim: np.ndarray) -> np.ndarray:
    """The square size each corner's refinement window is made for: ``spacing``, smaller on the rim."""
    spacing = np.asarray(spacing, dtype=np.float64)
    small = np.maximum(RIM_WINDOW_SCALE * spacing, np.minimum(spacing, RIM_WINDOW_MIN_SPACING_PX))
    return np.where(rim, small, spacing)


# The rim window is only needed where the full window reaches past the board's outer edge: a corner whose
# outer squares keep their colour as far out as its window reaches (plus RIM_EDGE_MARGIN_PX of blur) keeps
# the full window's result. Sampled on the smoothed image in the middle of each outer square (between the
# rim corner and its neighbours along the rim), against the colours of the same squares near the corner;
# the squares' contrast is taken from the inner squares beside them. A colour change of more than
# RIM_EDGE_CONTRAST of that contrast is an edge (the square ends within the window).
RIM_EDGE_MARGIN_PX = 2.0
RIM_EDGE_CONTRAST = 0.25
# A rim corner is also refined from where the grid lines through the next corners inwards put it, when those
# lines predict their own next corner (the worst of three parallel lines) this many times better than they
# disagree with the corner: a single miss is a poor measure of the lines' error (the ratio of two has heavy
# tails), and on a bent or noisy grid the extrapolation is no better than the corner.
RIM_LINE_TRUST = 4.0


@njit(cache=True, nogil=True, inline="always")
def _bilinear(img: np.ndarray, x: float, y: float) -> float:
    """img at (x, y) (bilinear; NaN outside the image)."""
    h, w = img.shape
    if not (0.0 <= x <= w - 1.001 and 0.0 <= y <= h - 1.001):
        return np.nan
    x0 = int(x)
    y0 = int(y)
    fx = x - x0
    fy = y - y0
    return ((img[y0, x0] * (1.0 - fx) + img[y0, x0 + 1] * fx) * (1.0 - fy)
            + (img[y0 + 1, x0] * (1.0 - fx) + img[y0 + 1, x0 + 1] * fx) * fy)


@njit(cache=True, nogil=True)
def _grid_point(grid: np.ndarray, r: int, c: int) -> tuple[float, float]:
    """The grid's corner at (row r, col c); NaN outside or missing."""
    if r < 0 or c < 0 or r >= grid.shape[0] or c >= grid.shape[1]:
        return np.nan, np.nan
    return grid[r, c, 0], grid[r, c, 1]


@njit(cache=True, nogil=True, inline="always")
def _rim_side(side: int, c: int, r: int, cols: int, rows: int) -> tuple[bool, int, int]:
    """Whether the corner (col c, row r) lies on outer line ``side`` (0 first column, 1 last column, 2 first
    row, 3 last row) of a cols x rows grid, and that side's inward step (dc, dr)."""
    if side == 0:
        return c == 0, 1, 0
    if side == 1:
        return c == cols - 1, -1, 0
    if side == 2:
        return r == 0, 0, 1
    return r == rows - 1, 0, -1


@njit(cache=True, nogil=True)
def _window_reaches_edge(smooth: np.ndarray, grid: np.ndarray, at: np.ndarray, half: np.ndarray
                         ) -> tuple[np.ndarray, np.ndarray]:
    """Per rim corner ``at`` (N, 2: col, row of ``grid`` (rows, cols, 2), NaN where missing) whether its
    cornerSubPix window of half-width ``half`` (N,) px sees an outer square end (see RIM_EDGE_MARGIN_PX),
    True where that cannot be told (neighbours missing, samples outside the image, no contrast); and the
    largest half-width (px) of a window that stays RIM_EDGE_MARGIN_PX inside the outer squares as far as
    they were seen to reach (sampled every pixel outwards; 0 where an outer square is not seen at all, inf
    where no edge was seen)."""
    rows, cols = grid.shape[0], grid.shape[1]
    n = at.shape[0]
    out = np.zeros(n, dtype=np.bool_)
    room = np.full(n, np.inf)
    for i in range(n):
        c = at[i, 0]
        r = at[i, 1]
        px, py = grid[r, c, 0], grid[r, c, 1]
        reaches = False
        for side in range(4):
            # outward step (dc, dr) of this side, and the direction along it
            on, dc, dr = _rim_side(side, c, r, cols, rows)
            dc, dr = -dc, -dr
            if not on:
                continue
            bx, by = _grid_point(grid, r - dr, c - dc)  # one step inwards
            if not (math.isfinite(px) and math.isfinite(bx)):
                reaches = True
                room[i] = 0.0
                break
            ux, uy = px - bx, py - by  # outward, one square
            un = math.hypot(ux, uy)
            if un == 0.0:  # two corners on one spot: no outward direction, as with a missing neighbour
                reaches = True
                room[i] = 0.0
                break
            reach = (abs(ux) + abs(uy)) / un  # a window's reach in that direction per px of half-width
            # how far out (in squares) the window reaches: its support in that direction, plus the blur margin
            t_max = (half[i] * reach + RIM_EDGE_MARGIN_PX) / un
            for along in (-1, 1):
                # to the middle of the outer square, along the rim: half the step to the neighbour on the rim,
                # or (at the board's corners, whose window also sees the square diagonally beyond) the
                # opposite neighbour's step reversed
                qx, qy = _grid_point(grid, r + along * abs(dc), c + along * abs(dr))
                vx, vy = 0.5 * (qx - px), 0.5 * (qy - py)
                if not math.isfinite(qx):
                    qx, qy = _grid_point(grid, r - along * abs(dc), c - along * abs(dr))
                    vx, vy = -0.5 * (qx - px), -0.5 * (qy - py)
                if not math.isfinite(qx):
                    continue
                inner = _bilinear(smooth, px - 0.5 * ux + vx, py - 0.5 * uy + vy)
                other = _bilinear(smooth, px - 0.5 * ux - vx, py - 0.5 * uy - vy)
                contrast = abs(inner - other)
                near = _bilinear(smooth, px + 0.25 * ux + vx, py + 0.25 * uy + vy)
                # the outer square has the colour opposite to the inner square beside it ...
                if not (abs(near - other) < 0.5 * contrast and contrast > 0.0):
                    reaches = True  # NaN comparisons land here too
                    room[i] = 0.0
                    continue
                # ... and keeps it as far as the window reaches
                steps = int(math.ceil((t_max - 0.25) * un))
                for k in range(1, steps + 1):
                    t = min(0.25 + k / un, t_max)
                    value = _bilinear(smooth, px + t * ux + vx, py + t * uy + vy)
                    if not abs(value - near) < RIM_EDGE_CONTRAST * contrast:
                        reaches = True
                        # the edge lies about half way to the first changed sample from the last unchanged one
                        edge = (t - 0.5 / un) * un
                        room[i] = min(room[i], max(0.0, (edge - RIM_EDGE_MARGIN_PX) / reach))
                        break
        out[i] = reaches
    return out, room


@njit(cache=True, nogil=True)
def id_grid(xy: np.ndarray, ids: np.ndarray, start: int, end: int, pad: int) -> tuple[np.ndarray, int, int]:
    """Corners ``start``..``end`` - 1 (at least one) of ``xy`` (N, 2) laid out by their ``ids`` (N, 2) int64
    (col, row): a grid (rows + 2 pad, cols + 2 pad, 2) over the ids' span with ``pad`` lines of NaN round it,
    NaN where a corner is missing, and the smallest col and row (at [pad, pad]). The first step of the
    numba kernels that walk a board's lines, in one pass."""
    lo_c, lo_r = ids[start, 0], ids[start, 1]
    hi_c, hi_r = lo_c, lo_r
    for i in range(start, end):
        lo_c = min(lo_c, ids[i, 0])
        lo_r = min(lo_r, ids[i, 1])
        hi_c = max(hi_c, ids[i, 0])
        hi_r = max(hi_r, ids[i, 1])
    grid = np.full((hi_r - lo_r + 1 + 2 * pad, hi_c - lo_c + 1 + 2 * pad, 2), np.nan)
    for i in range(start, end):
        grid[ids[i, 1] - lo_r + pad, ids[i, 0] - lo_c + pad, 0] = xy[i, 0]
        grid[ids[i, 1] - lo_r + pad, ids[i, 0] - lo_c + pad, 1] = xy[i, 1]
    return grid, lo_c, lo_r


@njit(cache=True, nogil=True)
def _rim_layout(xy: np.ndarray, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The rim corners' setup in one pass (its numpy calls cost more than the rim check they fed): for
    corners ``xy`` (N, 2) with ``ids`` (N, 2) int64 (col, row), the grid of _dense_grid, the indices (K,) of
    the corners on the rim of the grid the ids span (on_board_rim) and their (col, row) on that grid (K, 2)."""
    n = ids.shape[0]
    if n == 0:
        return np.full((0, 0, 2), np.nan), np.zeros(0, np.int64), np.zeros((0, 2), np.int64)
    grid, lo0, lo1 = id_grid(xy, ids, 0, n, 0)
    hi0, hi1 = lo0 + grid.shape[1] - 1, lo1 + grid.shape[0] - 1
    rim = np.zeros(n, np.bool_)
    k = 0
    for i in range(n):
        c = ids[i, 0]
        r = ids[i, 1]
        if c == lo0 or c == hi0 or r == lo1 or r == hi1:
            rim[i] = True
            k += 1
    which = np.empty(k, np.int64)
    at = np.empty((k, 2), np.int64)
    j = 0
    for i in range(n):
        if rim[i]:
            which[j] = i
            at[j, 0] = ids[i, 0] - lo0
            at[j, 1] = ids[i, 1] - lo1
            j += 1
    return grid, which, at


def refine_rim(smooth: np.ndarray, xy: np.ndarray, ids: np.ndarray, spacing: np.ndarray, every: bool = False
               ) -> tuple[np.ndarray, np.ndarray]:
    """A grid's refined corners ``xy`` (M, 2) with those on its rim whose full window reaches past the board's
    outer edge (_window_reaches_edge) refined again with a smaller window (window_spacing, smaller still
    where the outer squares were seen to end sooner), from where they are and from where the grid's lines
    put them (_rim_prediction), kept where that continues the grid's lines better (_rim_misfit); and the
    square size of the window each corner now has (for the saddle fit).

    Both windows are needed: the full one brings a corner that grouping or a prediction put a few pixels
    off back to it (a small one has less reach), the small one then leaves out the board's edge. The check
    against the grid's lines keeps the full window's result on an image whose corners are not clean
    X-junctions (bloom, erosion), where the small window can go astray instead. The start from the lines
    is for a corner the full window pulled further out than the small one reaches (Bouguet's stereo
    sample: 4-10 px; a synthetic board with outer squares cut to 0.35-0.45 of a square: 1-3.5 px, now
    0.02-0.07). Most boards have full outer squares (or a margin): their rim corners are left as they
    are, at the cost of a few samples each. ``every``: every rim corner gets the rim window's pass, the
    start from the grid's lines still only those whose window reaches the board's edge (tracking: its
    corners come from the search's criteria and this pass is their polish; without it a tracked rim corner
    of bench/corner_noise.py's clean renders stayed 0.9 px off).
    """
    xy = np.array(xy, dtype=np.float64)
    window = np.array(spacing, dtype=np.float64)
    ids = np.asarray(ids, dtype=np.int64).reshape(-1, 2)
    grid, which, at = _rim_layout(xy, ids)
    if not len(which):
        return xy, window
    need, room = _window_reaches_edge(np.ascontiguousarray(smooth, np.float32), grid, at,
                                      subpixel_window(window[which]).astype(np.float64))
    edge = need  # the board's edge seen within the window: these may be pulled beyond the rim window's reach
    if every:
        need = np.ones(len(which), dtype=bool)
    which, at, room, edge = which[need], at[need], room[need], edge[need]
    if not len(which):
        return xy, window
    # the rim window, and smaller where the outer squares were seen to end within it (never below the
    # window of a RIM_WINDOW_MIN_SPACING_PX square)
    small = window_spacing(window[which], np.ones(len(which), dtype=bool))
    small = np.minimum(small, np.maximum(2.0 * np.floor(room) + 1.0, np.minimum(small, RIM_WINDOW_MIN_SPACING_PX)))
    # The small window from the full window's result, and from where the grid's lines put the corner: a
    # corner the board's edge pulled further than the small window reaches stays pulled from the first.
    # The lines are trusted where they predict their own next corner RIM_LINE_TRUST times better than
    # they disagree with this one (on a bent or noisy grid the extrapolation is no better than the corner).
    # A board's corners are predicted by lines along its sides, whose corners were pulled too: those not
    # trusted are tried once more on the grid the first round put right.
    tried = np.zeros(len(which), dtype=bool)
    small_used = np.zeros(len(which), dtype=bool)
    for first in (True, False):
        pred, check = _rim_prediction(grid, at)
        best = xy[which].copy()
        best_misfit = _rim_misfit(grid, at, best)
        trusted = edge & ~tried & np.isfinite(check) & (RIM_LINE_TRUST * check < best_misfit)
        tried |= trusted
        for start, use in ((best.copy(), np.full(len(which), first)), (pred, trusted)):
            if not use.any():
                continue
            again = refine_corners(smooth, np.where(use[:, None], start, np.nan), small)
            # a refinement that ran off keeps its start
            moved = use & np.isfinite(again).all(axis=1) & (again != start).any(axis=1)
            misfit = np.where(moved, _rim_misfit(grid, at, again), np.inf)
            better = misfit < best_misfit
            best[better], best_misfit[better], small_used[better] = again[better], misfit[better], True
        changed = (best != xy[which]).any(axis=1)
        xy[which] = best
        if not changed.any() or tried.all():
            break
        grid, _lo = _dense_grid(xy, ids)
    window[which[small_used]] = small[small_used]
    return xy, window


@njit(cache=True, nogil=True)
def _rim_prediction(grid: np.ndarray, at: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where the grid lines through the next three corners inwards put each rim corner ``at`` (N, 2: col, row
    of ``grid`` (rows, cols, 2)): 3 a - 3 b + c per line (see _rim_misfit), averaged over the lines (two at a
    board's corner); and how well the same lines, and the parallel ones through the rim neighbours, predict
    their own first corner a from the three after it (the largest miss along the lines, px). NaN where no
    line has the four corners."""
    rows, cols = grid.shape[0], grid.shape[1]
    n = at.shape[0]
    out = np.full((n, 2), np.nan)
    check = np.full(n, np.nan)
    for i in range(n):
        c = at[i, 0]
        r = at[i, 1]
        sx = 0.0
        sy = 0.0
        worst = 0.0
        k = 0
        for side in range(4):
            on, dc, dr = _rim_side(side, c, r, cols, rows)
            if not on:
                continue
            ax, ay = _grid_point(grid, r + dr, c + dc)
            bx, by = _grid_point(grid, r + 2 * dr, c + 2 * dc)
            qx, qy = _grid_point(grid, r + 3 * dr, c + 3 * dc)
            px = 3.0 * ax - 3.0 * bx + qx
            py = 3.0 * ay - 3.0 * by + qy
            # the check on this line and the parallel ones through the rim neighbours (one miss alone is a
            # poor measure of the lines' error: the ratio of two such misses has heavy tails)
            miss = np.nan
            for along in (-1, 0, 1):
                r1 = r + along * abs(dc)
                c1 = c + along * abs(dr)
                a1x, a1y = _grid_point(grid, r1 + dr, c1 + dc)
                b1x, b1y = _grid_point(grid, r1 + 2 * dr, c1 + 2 * dc)
                q1x, q1y = _grid_point(grid, r1 + 3 * dr, c1 + 3 * dc)
                e1x, e1y = _grid_point(grid, r1 + 4 * dr, c1 + 4 * dc)
                lx, ly = a1x - b1x, a1y - b1y
                norm = max(math.hypot(lx, ly), 1e-9)
                m = abs((a1x - (3.0 * b1x - 3.0 * q1x + e1x)) * lx
                        + (a1y - (3.0 * b1y - 3.0 * q1y + e1y)) * ly) / norm
                if math.isfinite(m) and not m <= miss:
                    miss = m
            if math.isfinite(px) and math.isfinite(py) and math.isfinite(miss):
                sx += px
                sy += py
                worst = max(worst, miss)
                k += 1
        if k:
            out[i, 0] = sx / k
            out[i, 1] = sy / k
            check[i] = worst
    return out, check


def _dense_grid(xy: np.ndarray, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The grid's corners (rows, cols, 2) by (row, col) from its smallest ids ``lo`` (2,) on, NaN where
    missing; and ``lo``."""
    lo, hi = ids.min(axis=0), ids.max(axis=0)
    cols, rows = (hi - lo + 1).tolist()
    grid = np.full((rows, cols, 2), np.nan)
    grid[ids[:, 1] - lo[1], ids[:, 0] - lo[0]] = xy
    return grid, lo


@njit(cache=True, nogil=True)
def _rim_misfit(grid: np.ndarray, at: np.ndarray, candidates: np.ndarray) -> np.ndarray:
    """How far each candidate position (``candidates`` (N, 2)) of the corners ``at`` (N, 2: col, row) on the
    outer lines of ``grid`` (rows, cols, 2; NaN where missing) is from continuing the grid lines that cross
    there: the line through the next three corners inwards, extrapolated by 3 a - 3 b + c (exact for a
    quadratic: a lens bends lines smoothly), measured along that line only (cut outer squares push a corner
    outwards, along it; the neighbours on the same outer line are pushed alike and say nothing). A side
    whose three corners are not all there adds nothing.
    """
    rows, cols = grid.shape[0], grid.shape[1]
    n = at.shape[0]
    out = np.zeros(n)
    for i in range(n):
        c = at[i, 0]
        r = at[i, 1]
        total = 0.0
        for side in range(4):
            on, dc, dr = _rim_side(side, c, r, cols, rows)
            if not on:
                continue
            ax, ay = _grid_point(grid, r + dr, c + dc)
            bx, by = _grid_point(grid, r + 2 * dr, c + 2 * dc)
            qx, qy = _grid_point(grid, r + 3 * dr, c + 3 * dc)
            lx, ly = ax - bx, ay - by
            norm = max(math.hypot(lx, ly), 1e-9)
            off = ((candidates[i, 0] - (3.0 * ax - 3.0 * bx + qx)) * lx
                   + (candidates[i, 1] - (3.0 * ay - 3.0 * by + qy)) * ly) / norm
            if math.isfinite(off):
                total += off * off
        out[i] = math.sqrt(total)
    return out


def refine_corners(smooth: np.ndarray, pts: np.ndarray, spacing: np.ndarray,
                   max_move_px: float | None = None, criteria: tuple = FINAL_CRITERIA) -> np.ndarray:
    """Refined copies of ``pts`` (M, 2); points that move further than ``max_move_px`` (default: half the
    window) keep their start position: the refinement ran away to another structure. ``criteria``:
    cv2.cornerSubPix's termination (SEARCH_CRITERIA for completion's predictions, else the default).

    One cv2.cornerSubPix call per window size, on the points sorted by it (a call takes one window size);
    the bookkeeping is done once for all points, not per size (it cost a third as much as the refinement).
    """
    start = np.array(pts, dtype=np.float32).reshape(-1, 2)
    if len(start) == 0:
        return start.astype(np.float64)
    spacing = np.asarray(spacing, np.float64)
    # (np.broadcast_to only where needed: it costs more than the small calls' bookkeeping it serves)
    spacing = np.ascontiguousarray(spacing.reshape(-1) if spacing.size == len(start) and spacing.ndim <= 1
                                   else np.broadcast_to(spacing, (len(start),)))
    h, w = smooth.shape
    order, sizes, bounds = _refinement_plan(start, spacing, h, w)
    if len(order) == 0:
        return start.astype(np.float64)
    block = start[order].reshape(-1, 1, 2)
    # one call per run of equal sizes
    edges = bounds.tolist()
    for a, b in zip(edges[:-1], edges[1:]):
        part = block[a:b]  # a contiguous view: cornerSubPix refines it in place
        size = int(sizes[a])
        cv2.cornerSubPix(smooth, part, (size, size), (-1, -1), criteria)
    return _kept_refinements(start, block, order, sizes, -1.0 if max_move_px is None else float(max_move_px))


@njit(cache=True, nogil=True)
def _refinement_plan(start: np.ndarray, spacing: np.ndarray, h: int, w: int
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The points of ``start`` (M, 2) float32 whose cornerSubPix window (subpixel_window of ``spacing``
    (M,), of 6 px where a point or its spacing is not finite) lies inside an h x w image, sorted by window
    half-width (stable): (their indices (K,), half-widths (K,), the bounds of the runs of one half-width
    (R + 1,): run r is [bounds[r], bounds[r + 1]))."""
    m = start.shape[0]
    half = np.empty(m, np.int64)
    ok = np.zeros(m, np.bool_)
    count = np.zeros(13, np.int64)
    for i in range(m):
        x = start[i, 0]
        y = start[i, 1]
        finite = math.isfinite(x) and math.isfinite(y) and math.isfinite(spacing[i])
        hw = int(min(max(math.floor(0.5 * (spacing[i] if finite else 6.0)), 3.0), 12.0))
        half[i] = hw
        # cornerSubPix needs the window inside the image
        if finite and x > hw + 1 and x < w - hw - 2 and y > hw + 1 and y < h - hw - 2:
            ok[i] = True
            count[hw] += 1
    first = np.zeros(13, np.int64)
    for hw in range(1, 13):
        first[hw] = first[hw - 1] + count[hw - 1]
    n = first[12] + count[12]
    order = np.empty(n, np.int64)
    sizes = np.empty(n, np.int64)
    runs = 0
    for hw in range(13):
        runs += count[hw] > 0
    bounds = np.empty(runs + 1, np.int64)
    bounds[0] = 0
    r = 1
    for hw in range(13):
        if count[hw] > 0:
            bounds[r] = first[hw] + count[hw]
            r += 1
    for i in range(m):
        if ok[i]:
            k = first[half[i]]
            order[k] = i
            sizes[k] = half[i]
            first[half[i]] += 1
    return order, sizes, bounds


@njit(cache=True, nogil=True)
def _kept_refinements(start: np.ndarray, block: np.ndarray, order: np.ndarray, sizes: np.ndarray,
                      max_move: float) -> np.ndarray:
    """``start`` (M, 2) float32 as float64 with the refined points ``block`` (K, 1, 2) of ``order`` (K,) put in
    where they moved less than ``max_move`` px (negative: half the window, at least 1.5 px). The move is
    measured in float32, as cornerSubPix's points are."""
    out = start.astype(np.float64)
    for k in range(order.shape[0]):
        i = order[k]
        dx = block[k, 0, 0] - start[i, 0]
        dy = block[k, 0, 1] - start[i, 1]
        moved = np.sqrt(dx * dx + dy * dy)
        limit = max_move if max_move >= 0.0 else max(1.5, 0.5 * sizes[k])
        if moved < limit:
            out[i, 0] = block[k, 0, 0]
            out[i, 1] = block[k, 0, 1]
    return out


@njit(cache=True, nogil=True)
def _nearest_distances(pts: np.ndarray, order: np.ndarray) -> np.ndarray:
    """Distance from each point (M, 2) to its nearest other one, clipped to 4..300 px (nearest_spacing's
    clip, here: two numpy calls cost more than the sweep); ``order`` sorts the points by x.

    A sweep along x from each point outwards that stops once the x gap alone exceeds the best distance:
    exact, and linear in practice for points spread over an image (a k-d tree costs ~40 us per call in
    building and querying, which a frame pays ten times over for a few dozen corners).
    """
    m = pts.shape[0]
    best = np.full(m, np.inf)
    for a in range(m):
        i = order[a]
        xi = pts[i, 0]
        yi = pts[i, 1]
        b2 = np.inf
        for step in (-1, 1):
            b = a + step
            while 0 <= b < m:
                j = order[b]
                dx = pts[j, 0] - xi
                if dx * dx > b2:
                    break
                dy = pts[j, 1] - yi
                d2 = dx * dx + dy * dy
                if d2 < b2:
                    b2 = d2
                b += step
        # (never NaN: a NaN point's comparisons all fail and leave it at inf, as np.maximum/np.minimum saw it)
        best[i] = min(max(math.sqrt(b2), 4.0), 300.0)
    return best


@njit(cache=True, nogil=True)
def _nearest_of_sorted(queries: np.ndarray, ref: np.ndarray, order: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """nearest_of with ``order`` sorting ``ref`` by x: a binary search, then a sweep outwards in x."""
    m = queries.shape[0]
    n = ref.shape[0]
    xs = np.empty(n)
    for a in range(n):
        xs[a] = ref[order[a], 0]
    dist = np.full(m, np.inf)
    index = np.full(m, -1, np.int64)
    for i in range(m):
        qx = queries[i, 0]
        qy = queries[i, 1]
        start = np.searchsorted(xs, qx)
        b2 = np.inf
        best = -1
        for step in (-1, 1):
            b = start - 1 if step < 0 else start
            while 0 <= b < n:
                dx = xs[b] - qx
                if dx * dx > b2:
                    break
                j = order[b]
                dy = ref[j, 1] - qy
                d2 = dx * dx + dy * dy
                if d2 < b2 or (d2 == b2 and j < best):
                    b2 = d2
                    best = j
                b += step
        if best >= 0:
            dist[i] = math.sqrt(b2)
            index[i] = best
    return dist, index


def nearest_of(queries: np.ndarray, ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For each query point (M, 2): the distance to the nearest of the points ``ref`` (N, 2) and its index
    (inf and -1 when ``ref`` is empty)."""
    queries = np.ascontiguousarray(queries, dtype=np.float64).reshape(-1, 2)
    ref = np.ascontiguousarray(ref, dtype=np.float64).reshape(-1, 2)
    return _nearest_of_sorted(queries, ref, np.argsort(ref[:, 0], kind="stable"))


def nearest_spacing(pts: np.ndarray) -> np.ndarray:
    """Distance from each point to its nearest other point: the local square size on a board.

    On a steeply slanted board the nearest corner can be a diagonal neighbour, which is why this is taken
    from the points themselves and not from grid labels: windows sized by it never hold two corners.
    Clipped to 4..300 px; 20 px for a lone point.
    """
    pts = np.ascontiguousarray(pts, dtype=np.float64).reshape(-1, 2)
    if len(pts) < 2:
        return np.full(len(pts), 20.0)
    return _nearest_distances(pts, np.argsort(pts[:, 0], kind="stable"))


# The final refiners a detector can use (DetectorParams.subpixel_refiner): cornerSubPix alone, followed by the
# saddle fit (more accurate on every rendered set, see saddle_refine), or followed by the saddle fit and the
# X-junction model fit from its result (the default: more accurate again on every rendered set, see
# xjunction_fit).
REFINERS = ("cornersubpix", "saddle", "xjunction")

# Saddle fit: a quadratic surface fitted to the image around each corner, the corner at its saddle point.
# The fit window (half-width 5 px, Gaussian weights sigma 3 px) reaches past the corner's own blur: an
# X-junction smoothed once more (sigma 0.12 x the square size, 0.5..1.5 px) is close to a saddle-shaped
# quadratic that far, and the wider fit averages far more noise. Measured side by side (refiners from the
# detector's own cornerSubPix corners, bench/detect.py's rendered and ../shared synthetic sets) against the
# earlier 2 px window with weights of sigma 2 px and 0.08 x square smoothing up to 1 px: clean renders
# 0.0093 -> 0.0043 px RMS, planar 0.027 -> 0.024, multi 0.038 -> 0.030, 8 px squares 0.038 -> 0.035, every
# scale of the sweep better or equal; larger windows or weights lose on 8 px and 100 px squares.
_SADDLE_HALF = 5
_SADDLE_WEIGHT_SIGMA = 3.0
_SADDLE_BLUR_PER_SPACING = 0.12
_SADDLE_BLUR_SIGMA = (0.5, 1.5)  # px, bounds of the extra smoothing
_SADDLE_BLUR_MAX = 4  # half-width of the extra smoothing kernel (sigma 1.5 px: truncated at 2.7 sigma)
_SADDLE_ITERATIONS = 4
_SADDLE_CONVERGED_PX = 1e-3  # a step this small ends the iterations


def _saddle_fit_matrix() -> np.ndarray:
    """Weighted least-squares pseudo-inverse (6, 25): window values -> a x^2 + b xy + c y^2 + d x + e y + f."""
    r = np.arange(-_SADDLE_HALF, _SADDLE_HALF + 1, dtype=np.float64)
    dx, dy = (a.ravel() for a in np.meshgrid(r, r))
    design = np.stack([dx * dx, dx * dy, dy * dy, dx, dy, np.ones_like(dx)], axis=1)
    w = np.exp(-(dx * dx + dy * dy) / (2.0 * _SADDLE_WEIGHT_SIGMA ** 2))
    return np.linalg.pinv(design * w[:, None]) * w[None, :]


_SADDLE_FIT = _saddle_fit_matrix()


@njit(cache=True, nogil=True, inline="always")
def fit_coefficients(fit: np.ndarray, win: np.ndarray, n: int) -> np.ndarray:
    """The first ``n`` coefficients of the saddle fit's quadratic: rows of its weighted pseudo-inverse ``fit``
    applied to the window's values ``win`` (the fit and its covariance, corner_covariance, share it)."""
    c = np.zeros(n)
    # the coefficients side by side (each still summed over the window in order: the same sums), not one
    # long chain of dependent additions at a time
    for q in range(win.shape[0]):
        wq = win[q]
        for j in range(n):
            c[j] += fit[j, q] * wq
    return c


@njit(cache=True, nogil=True)
def _saddle_kernel(smooth: np.ndarray, pts: np.ndarray, sigma: np.ndarray, fit: np.ndarray, half: int,
                   blur: int, iterations: int, max_move: float, converged: float) -> np.ndarray:
    """saddle_refine for all corners in one pass (see there); fit: (6, (2 half + 1)^2) weighted pseudo-inverse;
    a corner's iterations stop once a step is below ``converged`` px in x and y.

    The extra smoothing and the resampling at the estimate are both convolutions on the pixel grid, so
    their order does not matter: the patch is smoothed on the grid once per pixel the estimate lies in
    and only the bilinear resampling is done per iteration (the same fit to ~1e-13 px, half the time).
    """
    h, w = smooth.shape
    m = pts.shape[0]
    out = pts.copy()
    n_fit = 2 * half + 1
    n_grid = n_fit + 1  # the smoothed patch: the fit window and the pixel beyond it that resampling reads
    rows = np.empty((n_grid + 2 * blur, n_grid))
    patch = np.empty((n_grid, n_grid))
    win = np.empty(n_fit * n_fit)
    kern = np.empty(2 * blur + 1)
    for i in range(m):
        total = 0.0
        for k in range(2 * blur + 1):
            kern[k] = math.exp(-((k - blur) ** 2) / (2.0 * sigma[i] * sigma[i]))
            total += kern[k]
        for k in range(2 * blur + 1):
            kern[k] /= total
        x = pts[i, 0]
        y = pts[i, 1]
        ok = True
        px = -1  # the pixel the smoothed patch was made for (none yet)
        py = -1
        for _ in range(iterations):
            if x < half + blur + 1 or y < half + blur + 1 or x > w - half - blur - 2 or y > h - half - blur - 2:
                ok = False
                break
            x0 = int(math.floor(x))
            y0 = int(math.floor(y))
            if x0 != px or y0 != py:
                px = x0
                py = y0
                # each output's taps summed in order as before (the same values), a row of outputs at a time
                for a in range(n_grid + 2 * blur):
                    src = smooth[y0 - half - blur + a]
                    xs = x0 - half - blur
                    for b in range(n_grid):
                        rows[a, b] = 0.0
                    for k in range(2 * blur + 1):
                        kk = kern[k]
                        for b in range(n_grid):
                            rows[a, b] += src[xs + b + k] * kk
                for a in range(n_grid):
                    for b in range(n_grid):
                        patch[a, b] = 0.0
                    for k in range(2 * blur + 1):
                        kk = kern[k]
                        for b in range(n_grid):
                            patch[a, b] += rows[a + k, b] * kk
            # the smoothed patch resampled at the estimate: one bilinear fraction for every pixel
            fx = x - x0
            fy = y - y0
            for a in range(n_fit):
                for b in range(n_fit):
                    win[a * n_fit + b] = ((patch[a, b] * (1.0 - fx) + patch[a, b + 1] * fx) * (1.0 - fy)
                                          + (patch[a + 1, b] * (1.0 - fx) + patch[a + 1, b + 1] * fx) * fy)
            c = fit_coefficients(fit, win, 5)
            det = 4.0 * c[0] * c[2] - c[1] * c[1]
            if not det < 0.0:  # an extremum or flat: no saddle here
                ok = False
                break
            sx = (c[1] * c[4] - 2.0 * c[2] * c[3]) / det
            sy = (c[1] * c[3] - 2.0 * c[0] * c[4]) / det
            if abs(sx) >= 1.0 or abs(sy) >= 1.0:
                continue
            x += sx
            y += sy
            if abs(sx) < converged and abs(sy) < converged:
                break
        if ok and math.hypot(x - pts[i, 0], y - pts[i, 1]) <= max_move:
            out[i, 0] = x
            out[i, 1] = y
    return out


def saddle_refine(smooth: np.ndarray, pts: np.ndarray, spacing: np.ndarray, max_move_px: float = 1.0) -> np.ndarray:
    """Corners (M, 2) moved to the saddle point of a quadratic fitted to the image around them.

    Starts from ``pts`` (cornerSubPix's corners) and iterates on a patch resampled at the current estimate.
    A corner whose fit is no saddle, or that would move more than ``max_move_px`` from its start, keeps its
    start position, as does one within _SADDLE_HALF + _SADDLE_BLUR_MAX + 1 px of the border. Measured on
    renders with exact truth against cornerSubPix from the same start (bench/detect.py's rendered and
    synthetic sets): clean 0.004 instead of 0.016 px, 8 px squares 0.035 instead of 0.085 px, several boards
    with clutter (synthetic/multi) 0.030 instead of 0.074 px, noisy and blurred ones (synthetic/hard)
    0.26 instead of 0.29 px.
    """
    pts = np.ascontiguousarray(pts, dtype=np.float64).reshape(-1, 2)
    if len(pts) == 0:
        return pts.copy()
    fit, half, blur_half, sigma = saddle_fit_setup(spacing)
    return _saddle_kernel(np.ascontiguousarray(smooth, np.float32), pts, sigma, np.ascontiguousarray(fit[:5]),
                          half, blur_half, _SADDLE_ITERATIONS, float(max_move_px), _SADDLE_CONVERGED_PX)


def saddle_fit_setup(spacing: np.ndarray) -> tuple[np.ndarray, int, int, np.ndarray]:
    """What saddle_refine fits with, for the covariance of its corners (corner_covariance repeats the fit):
    the weighted pseudo-inverse (6, (2 half + 1)^2), the fit's half-width, the extra smoothing kernel's
    half-width and its sigma per corner (N,) for the local square sizes ``spacing`` (N,) px."""
    sigma = np.minimum(np.maximum(_SADDLE_BLUR_PER_SPACING * np.asarray(spacing, dtype=np.float64).reshape(-1),
                                  _SADDLE_BLUR_SIGMA[0]), _SADDLE_BLUR_SIGMA[1])
    return _SADDLE_FIT, _SADDLE_HALF, _SADDLE_BLUR_MAX, np.ascontiguousarray(sigma)


# X-junction model fit: the image around a corner is fitted by what a blurred X-junction looks like: two
# straight lines through the corner with a step across each, blurred by a Gaussian of s px and integrated over
# a pixel (_edge_profile, F), the image m + c F(d1) F(d2) (d1, d2 signed distances to the lines; 7 parameters:
# the corner, the lines' angles, s, the level m and the contrast c), by Gauss-Newton least squares on the raw
# image in a disc of _XJ_RADIUS_PER_SPACING x the nearest-corner distance (_XJ_RADIUS_PX). The saddle fit's
# quadratic only holds within about the blur of a corner, so its fit is 5 px and smoothed; this model holds
# out to the next edges, so its disc takes every pixel that says where the two edges run (~4x the saddle
# fit's pixels: the noise averages out) and nothing is resampled or smoothed (no pixel locking from the
# resampling, no noise correlated by smoothing). The model is point-symmetric about the corner like the true
# blurred junction (also its gamma-mapped and non-orthogonal versions, which it does not describe exactly),
# so what it misses does not move the corner in a disc centred there. No light-gradient terms: they are odd
# like a shift and, fitted, doubled the corner's noise (8 px squares, blur 1.9: 0.044 -> 0.069 px RMS).
# Measured from the saddle fit's corners against them (the ../shared synthetic sets and bench/detect.py's
# renders; disc radius 0.5/0.6/0.7 x the square size, up to 8/10/12/15/20/30 px, swept): planar 0.0236 ->
# 0.0120 px RMS, multi 0.0296 -> 0.0225, hard 0.168 -> 0.149, box_stereo 0.0265 -> 0.0145, clean renders
# 0.0043 -> 0.0033, every scale from 8 to 150 px lower (0.035 -> 0.029 at 8 px, 0.028 -> 0.016 at 150 px);
# discs beyond 12 px lose on 60-150 px squares (the lens bends the lines, the light changes). A plain erf
# step (no pixel width) gave planar 0.0157 and left sharp edges along a pixel axis locked to it (0.07 px).
_XJ_RADIUS_PER_SPACING = 0.6
_XJ_RADIUS_PX = (3.0, 12.0)
_XJ_ITERATIONS = 10
# A step this small in x and y ends the iterations (and is taken): from the saddle fit's corners a second step
# of under 0.02 px leaves a third below ~1e-3 px (the same RMS on every set as 1e-3 px, ~1/3 less time).
_XJ_CONVERGED_PX = 0.02
_XJ_MIN_BLUR_PX = 0.05  # the blur is kept above this (the edge profile's pixel integral stays smooth)
_XJ_FLAT_BLURS = 5.5  # beyond this many blurs (and half a pixel) from its line a step is flat
_SQRT2 = math.sqrt(2.0)
_SQRT_2_OVER_PI = math.sqrt(2.0 / math.pi)


@njit(cache=True, nogil=True, inline="always")
def _erf(u: float, gauss: float) -> float:
    """erf(u) given exp(-u^2), which the fit needs anyway (Abramowitz and Stegun 7.1.26, error < 1.5e-7 of the
    contrast: well below a grey level; math.erf would cost a third of the fit)."""
    t = 1.0 / (1.0 + 0.3275911 * abs(u))
    v = 1.0 - t * (0.254829592 + t * (-0.284496736 + t * (1.421413741 + t * (-1.453152027 + t * 1.061405429)))) * gauss
    return v if u >= 0.0 else -v


@intrinsic
def _f64_from_bits(typingctx, bits):
    """The float64 whose IEEE bits are the int64 ``bits`` (a bit cast: numba has no scalar one)."""
    sig = types.float64(types.int64)

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.DoubleType())
    return sig, codegen


_LOG2E = 1.4426950408889634
_LN2_HI = 6.93147180369123816490e-01  # ln 2 in two parts (fdlibm's): k * _LN2_HI is exact for |k| < 2^20
_LN2_LO = 1.90821492927058770002e-10
# 1 / j! for j = 13 .. 0: exp on [-ln2 / 2, ln2 / 2] by its Taylor series to ~4e-18
_EXP_TAYLOR = tuple(1.0 / math.factorial(j) for j in range(13, -1, -1))


@njit(cache=True, nogil=True, inline="always")
def _exp_neg_square(u: float) -> float:
    """exp(-u^2), to about an ulp of math.exp, in arithmetic only (no libm call, no branch): the X-junction
    fit's loop over its pixels then runs in SIMD lanes, where math.exp's call took half of the fit's time.
    Below exp(-700) it is that (the fit only uses it next to a line, where it is above 1e-150)."""
    x = max(-u * u, -700.0)
    k = math.floor(x * _LOG2E + 0.5)
    r = x - k * _LN2_HI - k * _LN2_LO
    p = _EXP_TAYLOR[0]
    p = p * r + _EXP_TAYLOR[1]
    p = p * r + _EXP_TAYLOR[2]
    p = p * r + _EXP_TAYLOR[3]
    p = p * r + _EXP_TAYLOR[4]
    p = p * r + _EXP_TAYLOR[5]
    p = p * r + _EXP_TAYLOR[6]
    p = p * r + _EXP_TAYLOR[7]
    p = p * r + _EXP_TAYLOR[8]
    p = p * r + _EXP_TAYLOR[9]
    p = p * r + _EXP_TAYLOR[10]
    p = p * r + _EXP_TAYLOR[11]
    p = p * r + _EXP_TAYLOR[12]
    p = p * r + _EXP_TAYLOR[13]
    return p * _f64_from_bits((np.int64(k) + 1023) << 52)  # type: ignore[call-arg]


@njit(cache=True, nogil=True, inline="always")
def _edge_profile(d: float, s: float, inv: float) -> tuple[float, float, float]:
    """A unit step (-1 .. 1) across a line, blurred by a Gaussian of ``s`` px and integrated over a pixel across
    the line, at signed distance ``d`` px from it (``inv`` = 1 / (sqrt2 s)); and its derivatives by d and s.

    The mean of erf(t / (sqrt2 s)) over t in d -+ 1/2: with G(t) = t erf(t / (sqrt2 s)) + s sqrt(2/pi)
    exp(-t^2 / (2 s^2)) (its antiderivative), G(d + 1/2) - G(d - 1/2). Without the pixel's width a sharp
    edge (blur ~0.3 px) along a pixel axis is no erf: such corners were locked to the pixel grid (0.07 px).
    Computed everywhere and then selected (no branch: the fit's loop over its pixels runs in SIMD lanes).
    """
    a = (d + 0.5) * inv
    b = (d - 0.5) * inv
    ga = _exp_neg_square(a)
    gb = _exp_neg_square(b)
    ea = _erf(a, ga)
    eb = _erf(b, gb)
    # the step's plateau (to ~1e-7 of the contrast) beyond _XJ_FLAT_BLURS blurs and half a pixel from its line
    flat = abs(d) > 0.5 + _XJ_FLAT_BLURS * s
    value = (d + 0.5) * ea - (d - 0.5) * eb + s * _SQRT_2_OVER_PI * (ga - gb)
    plateau = 1.0 if d > 0.0 else -1.0
    return (plateau if flat else value), (0.0 if flat else ea - eb), (0.0 if flat else _SQRT_2_OVER_PI * (ga - gb))


@njit(cache=True, nogil=True, inline="always")
def _xj_sign(x0: float, y0: float, t1: float, t2: float, x: float, y: float) -> float:
    """The sign of the X-junction pattern at (x, y): +1 where both line distances have the same sign."""
    d1 = -(x - x0) * math.sin(t1) + (y - y0) * math.cos(t1)
    d2 = -(x - x0) * math.sin(t2) + (y - y0) * math.cos(t2)
    return 1.0 if d1 * d2 >= 0.0 else -1.0


# fast maths without assuming finite values: the NaN checks of a failed solve must stay
@njit(cache=True, nogil=True, fastmath={"contract", "afn", "reassoc", "arcp", "nsz"})
def _xjunction_kernel(img: np.ndarray, pts: np.ndarray, angles: np.ndarray, radius: np.ndarray, iterations: int,
                      max_move: float, converged: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """xjunction_fit for all corners in one pass (see there): ``img`` (H, W) the raw image, ``pts`` (M, 2)
    the starts, ``angles`` (M, 2) the two lines' directions there (radians), ``radius`` (M,) px the disc.
    A corner keeps its start (fitted False) when its disc is below _XJ_RADIUS_PX or leaves the image, the
    fit does not converge in ``iterations`` or moves it further than ``max_move`` px."""
    h, w = img.shape
    m = pts.shape[0]
    out = pts.copy()
    fitted = np.zeros(m, dtype=np.bool_)
    noise_cov = np.full((m, 2, 2), np.nan)
    r_max = int(math.ceil(radius.max() + 0.5)) if m else 0
    px = np.empty((2 * r_max + 1) ** 2)
    py = np.empty_like(px)
    pv = np.empty_like(px)
    pw = np.empty_like(px)
    jtj = np.empty((7, 7))
    jtr = np.empty(7)
    # the residuals and the Jacobian's columns per disc pixel (weighted copies too), summed into the normal
    # equations column by column: SIMD sums over the pixels, where adding every pixel's 28 products to the
    # matrix in turn cost ~40 % of the fit
    res = np.empty(px.shape[0])
    jac = np.empty((7, px.shape[0]))
    wjac = np.empty((7, px.shape[0]))
    blur = 1.0  # the blur found at the last corner (one board's corners share their blur): the next one's start
    for i in range(m):
        x = pts[i, 0]
        y = pts[i, 1]
        rad = radius[i]
        if not rad >= _XJ_RADIUS_PX[0]:
            continue
        r = int(math.ceil(rad + 0.5))
        xi = int(math.floor(x + 0.5))
        yi = int(math.floor(y + 0.5))
        if xi - r < 0 or yi - r < 0 or xi + r >= w or yi + r >= h:
            continue
        # the disc, its rim pixels weighted by how much of them it covers (a disc that moves smoothly with
        # its centre, not one that jumps by whole pixels)
        n = 0
        outer = (rad + 0.5) * (rad + 0.5)
        inner = max(rad - 0.5, 0.0) ** 2
        for yy in range(yi - r, yi + r + 1):
            for xx in range(xi - r, xi + r + 1):
                d2 = (xx - x) * (xx - x) + (yy - y) * (yy - y)
                if d2 >= outer:
                    continue
                px[n] = xx
                py[n] = yy
                pv[n] = img[yy, xx]
                pw[n] = 1.0 if d2 <= inner else rad + 0.5 - math.sqrt(d2)
                n += 1
        t1 = angles[i, 0]
        t2 = angles[i, 1]
        # level and contrast from the pixels half way out in the four squares (along the lines' bisectors)
        level = 0.0
        contrast = 0.0
        for q in range(4):
            t = 0.5 * (t1 + t2) + 0.5 * math.pi * q
            qx = int(math.floor(x + 0.5 * rad * math.cos(t) + 0.5))
            qy = int(math.floor(y + 0.5 * rad * math.sin(t) + 0.5))
            level += 0.25 * img[qy, qx]
            contrast += 0.25 * img[qy, qx] * _xj_sign(x, y, t1, t2, qx, qy)
        if contrast == 0.0:
            continue
        p = np.array([x, y, t1, t2, blur, level, contrast])
        prev = p.copy()
        prev_cost = np.inf
        damping = 1e-4
        done = False
        for _ in range(iterations):
            s1, c1 = math.sin(p[2]), math.cos(p[2])
            s2, c2 = math.sin(p[3]), math.cos(p[3])
            s = p[4]
            c = p[6]
            inv = 1.0 / (_SQRT2 * s)
            _xj_model_rows(px, py, pv, n, p[0], p[1], s1, c1, s2, c2, s, p[5], c, inv, jac, res)
            cost = _weighted_sums(jac, wjac, res, pw, n, jtj, jtr)
            if cost > prev_cost:  # the last step overshot: go half way back and damp
                p = prev + 0.5 * (p - prev)
                damping *= 10.0
                continue
            prev[:] = p
            prev_cost = cost
            for a in range(7):
                for b in range(a):
                    jtj[a, b] = jtj[b, a]
                jtj[a, a] *= 1.0 + damping
                jtj[a, a] += 1e-12
            step = solve_spd(jtj, jtr)
            p -= step
            p[4] = max(p[4], _XJ_MIN_BLUR_PX)
            damping = max(0.3 * damping, 1e-6)
            if not (abs(step[0]) >= converged or abs(step[1]) >= converged):  # (NaN ends it too)
                done = True
                break
        if done and math.isfinite(p[0]) and math.isfinite(p[1]) and math.hypot(p[0] - x, p[1] - y) <= max_move:
            out[i, 0] = p[0]
            out[i, 1] = p[1]
            fitted[i] = True
            blur = p[4]
            # the position block of (J^T W J)^-1 from the last step's Cholesky factor L (jtj, lower triangle;
            # damped by 1e-6 at most): A^-1_ij = (L^-1 e_i) . (L^-1 e_j)
            z0 = _forward_unit(jtj, 0)
            z1 = _forward_unit(jtj, 1)
            noise_cov[i, 0, 0] = np.dot(z0, z0)
            noise_cov[i, 0, 1] = noise_cov[i, 1, 0] = np.dot(z0, z1)
            noise_cov[i, 1, 1] = np.dot(z1, z1)
    return out, fitted, noise_cov


@njit(cache=True, nogil=True, inline="always")
def _forward_unit(lower: np.ndarray, j: int) -> np.ndarray:
    """L^-1 e_j for the lower-triangular ``lower`` (n, n) that solve_spd leaves (its upper triangle ignored)."""
    n = lower.shape[0]
    z = np.zeros(n)
    for i in range(j, n):
        v = 1.0 if i == j else 0.0
        for k in range(j, i):
            v -= lower[i, k] * z[k]
        z[i] = v / lower[i, i]
    return z


# fast maths as the fit's (no NaN or inf assumed away), and numpy's division (no ZeroDivisionError branch, which
# kept the loop out of SIMD lanes; _erf divides by at least 1): the loop over the pixels runs vectorised
@njit(cache=True, nogil=True, fastmath={"contract", "afn", "reassoc", "arcp", "nsz"}, error_model="numpy")
def _xj_model_rows(px: np.ndarray, py: np.ndarray, pv: np.ndarray, n: int, x0: float, y0: float, s1: float,
                   c1: float, s2: float, c2: float, s: float, level: float, c: float, inv: float, jac: np.ndarray,
                   res: np.ndarray) -> None:
    """The X-junction model's residuals ``res`` (>= n,) and Jacobian columns ``jac`` (7, >= n) at the first
    ``n`` disc pixels (px, py, values pv) for the corner (x0, y0), the lines' sines and cosines, the blur
    ``s`` (``inv`` = 1 / (sqrt2 s)), the level and the contrast ``c``: one branch-free pass (a function of
    its own, its parameters in registers, so that the compiler runs it in SIMD lanes)."""
    for k in range(n):
        dx = px[k] - x0
        dy = py[k] - y0
        d1 = -dx * s1 + dy * c1
        d2 = -dx * s2 + dy * c2
        f1, f1d, f1s = _edge_profile(d1, s, inv)
        f2, f2d, f2s = _edge_profile(d2, s, inv)
        g1 = c * f1d
        g2 = c * f2d
        res[k] = level + c * f1 * f2 - pv[k]
        jac[0, k] = g1 * s1 * f2 + f1 * g2 * s2
        jac[1, k] = -(g1 * c1 * f2 + f1 * g2 * c2)
        jac[2, k] = -g1 * (dx * c1 + dy * s1) * f2
        jac[3, k] = -f1 * g2 * (dx * c2 + dy * s2)
        jac[4, k] = c * (f1s * f2 + f1 * f2s)
        jac[5, k] = 1.0
        jac[6, k] = f1 * f2


# fast maths as the fit's: the sums over the pixels in SIMD lanes
@njit(cache=True, nogil=True, fastmath={"contract", "afn", "reassoc", "arcp", "nsz"})
def _weighted_sums(jac: np.ndarray, wjac: np.ndarray, res: np.ndarray, w: np.ndarray, n: int, jtj: np.ndarray,
                   jtr: np.ndarray) -> float:
    """The weighted least-squares sums of the first ``n`` pixels: jtj (upper triangle) = J^T W J, jtr = J^T W r
    for the Jacobian's columns ``jac`` (7, >= n) and residuals ``res``, weights ``w``; returns r^T W r.
    ``wjac`` (7, >= n) is scratch (the weighted columns)."""
    cost = 0.0
    for k in range(n):
        cost += w[k] * res[k] * res[k]
    for a in range(7):
        ja = jac[a]
        wa = wjac[a]
        acc = 0.0
        for k in range(n):
            wa[k] = w[k] * ja[k]
            acc += wa[k] * res[k]
        jtr[a] = acc
    for a in range(7):
        wa = wjac[a]
        for b in range(a, 7):
            jb = jac[b]
            acc = 0.0
            for k in range(n):
                acc += wa[k] * jb[k]
            jtj[a, b] = acc
    return cost


@njit(cache=True, nogil=True, inline="always")
def solve_spd(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """x with a x = b for a symmetric positive-definite (n, n) ``a`` (Cholesky, in place on ``a``): the fit's
    damped normal equations, 7x7, where LAPACK's call costs more than the solve (and line_bend's 3x3 / 4x4)."""
    n = a.shape[0]
    for j in range(n):
        d = a[j, j]
        for k in range(j):
            d -= a[j, k] * a[j, k]
        if not d > 0.0:
            return np.full(n, np.nan)
        d = math.sqrt(d)
        a[j, j] = d
        for i in range(j + 1, n):
            v = a[i, j]
            for k in range(j):
                v -= a[i, k] * a[j, k]
            a[i, j] = v / d
    x = b.copy()
    for i in range(n):
        v = x[i]
        for k in range(i):
            v -= a[i, k] * x[k]
        x[i] = v / a[i, i]
    for i in range(n - 1, -1, -1):
        v = x[i]
        for k in range(i + 1, n):
            v -= a[k, i] * x[k]
        x[i] = v / a[i, i]
    return x


def grid_line_angles(xy: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """(N, 2) the directions (radians, image axes) of a grid's row and column lines at each of its corners
    ``xy`` (N, 2) with ``ids`` (N, 2: col, row): from the neighbours on either side along the line (one side
    at a line's end; 0 and pi/2 where a corner has no neighbour along a line)."""
    xy = np.ascontiguousarray(np.asarray(xy, dtype=np.float64).reshape(-1, 2))
    ids = np.ascontiguousarray(np.asarray(ids, dtype=np.int64).reshape(-1, 2))
    if not len(xy):
        return np.empty((0, 2))
    return _grid_line_angles(xy, ids)


@njit(cache=True, nogil=True)
def _grid_line_angles(xy: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """grid_line_angles in one pass (N >= 1 corners): per coordinate, the step between the neighbours ahead
    and behind, else to the one there is, else the line's axis (as the numpy expressions it replaced)."""
    n = xy.shape[0]
    padded, lo_c, lo_r = id_grid(xy, ids, 0, n, 1)
    out = np.empty((n, 2))
    step = np.empty(2)
    for i in range(n):
        r = ids[i, 1] - lo_r + 1
        c = ids[i, 0] - lo_c + 1
        for k in range(2):
            dr = k
            dc = 1 - k
            for j in range(2):
                ahead = padded[r + dr, c + dc, j]
                behind = padded[r - dr, c - dc, j]
                if math.isfinite(ahead) and math.isfinite(behind):
                    v = ahead - behind
                elif math.isfinite(ahead):
                    v = ahead - xy[i, j]
                else:
                    v = xy[i, j] - behind
                step[j] = v if math.isfinite(v) else (1.0 if j == k else 0.0)
            out[i, k] = math.atan2(step[1], step[0])
    return out


def xjunction_disc_radius(spacing: np.ndarray) -> np.ndarray:
    """(N,) px: the X-junction fit's disc away from a board's rim, _XJ_RADIUS_PER_SPACING x the local square
    size ``spacing`` (N,) px, within _XJ_RADIUS_PX."""
    # np.minimum/np.maximum: np.clip's values (NaN too) at a third of its call overhead
    return np.minimum(np.maximum(_XJ_RADIUS_PER_SPACING * np.asarray(spacing, dtype=np.float64).reshape(-1),
                                 _XJ_RADIUS_PX[0]), _XJ_RADIUS_PX[1])


def xjunction_radius(image_smooth: np.ndarray, xy: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """(N,) px: the X-junction fit's disc for each corner of a grid (``xy`` (N, 2), ``ids`` (N, 2): col, row),
    _XJ_RADIUS_PER_SPACING x its nearest-corner distance (_XJ_RADIUS_PX); on the grid's rim no further than
    RIM_EDGE_MARGIN_PX inside where its outer squares were seen to end on the smoothed image
    ``image_smooth`` (_window_reaches_edge; the board's edge beyond would pull the corner outwards), and 0
    (no fit) where that cannot be told."""
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    radius = xjunction_disc_radius(nearest_spacing(xy))
    ids = np.asarray(ids, dtype=np.int64).reshape(-1, 2)
    grid, rim, at = _rim_layout(xy, ids)  # the rim corners and the grid in one pass
    if not len(rim):
        return radius
    # a square window's reach: larger than the disc's along a diagonal (conservative for the disc)
    reaches, room = _window_reaches_edge(np.ascontiguousarray(image_smooth, np.float32), grid, at,
                                         np.floor(radius[rim]))
    radius[rim] = np.where(reaches, np.minimum(radius[rim], room), radius[rim])
    return radius


def xjunction_fit(image: np.ndarray, pts: np.ndarray, angles: np.ndarray, radius: np.ndarray,
                  max_move_px: float = 1.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(corners (M, 2), fitted (M,) bool, noise (M, 2, 2)): where a blurred X-junction fitted to the raw
    ``image`` (H, W) in a disc of ``radius`` (M,) px (xjunction_radius) around each corner puts it, which
    corners it moved, and the covariance of each fitted corner (px^2) per unit variance of white noise in the
    image: the position block of the fit's (J^T W J)^-1, its blur, contrast and disc counted (NaN where not
    fitted).

    Starts from ``pts`` (the saddle fit's corners) and the directions of the two lines through each,
    ``angles`` (M, 2) radians (grid_line_angles); a corner whose fit does not converge, moves more than
    ``max_move_px`` or whose disc is below _XJ_RADIUS_PX or leaves the image keeps its start (not fitted).
    """
    pts = np.ascontiguousarray(pts, dtype=np.float64).reshape(-1, 2)
    if len(pts) == 0:
        return pts.copy(), np.zeros(0, dtype=bool), np.zeros((0, 2, 2))
    radius = np.ascontiguousarray(np.asarray(radius, dtype=np.float64).reshape(-1))
    angles = np.ascontiguousarray(np.asarray(angles, dtype=np.float64).reshape(-1, 2))
    return _xjunction_kernel(image, pts, angles, radius, _XJ_ITERATIONS, float(max_move_px), _XJ_CONVERGED_PX)
