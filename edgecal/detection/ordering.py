"""Step 7: giving a grid the (col, row) ids of a target board.

A grid's labels (u, v) are known up to the eight symmetries of a square lattice. Three facts pick one:
- size: the labels must span the board's cols x rows;
- handedness: a board is seen from its printed side, so +col crossed with +row points into the image
  (x right, y down): det[d_col, d_row] > 0 — this rules out the mirror images;
- colour: the square on the +col,+row side of corner (0, 0) is black (docs/conventions.md). When
  cols + rows is odd this tells the two 180-degree turns apart; when it is even they look the same, and
  corner (0, 0) is put nearest the image's top-left.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from edgecal.targets import Board

# The eight symmetries of the lattice as 2x2 integer matrices acting on (u, v).
_SYMMETRIES = [np.array(m, dtype=np.int64) for m in (
    ((1, 0), (0, 1)), ((0, -1), (1, 0)), ((-1, 0), (0, -1)), ((0, 1), (-1, 0)),
    ((-1, 0), (0, 1)), ((1, 0), (0, -1)), ((0, 1), (1, 0)), ((0, -1), (-1, 0)))]


_SYMMETRY_STACK = np.array(_SYMMETRIES, dtype=np.int64)


def assign_ids(uv: np.ndarray, xy: np.ndarray, smooth: np.ndarray, board: Board) -> np.ndarray | None:
    """(col, row) ids for a complete grid of labels ``uv`` at image points ``xy``, or None if it does not fit."""
    uv = np.ascontiguousarray(uv, dtype=np.int64).reshape(-1, 2)
    best = _best_symmetry(uv, np.ascontiguousarray(xy, dtype=np.float64).reshape(-1, 2), smooth, _SYMMETRY_STACK,
                          board.cols, board.rows)
    if best < 0:
        return None
    ids = uv @ _SYMMETRIES[best].T
    return ids - ids.min(axis=0)


@njit(cache=True, nogil=True)
def _best_symmetry(uv: np.ndarray, xy: np.ndarray, smooth: np.ndarray, symmetries: np.ndarray, cols: int,
                   rows: int) -> int:
    """Which of the lattice's ``symmetries`` (8, 2, 2) numbers the complete grid (uv (N, 2) labels at xy (N, 2)
    px) as a cols x rows board seen from its printed side, its colours right or, failing that, any; among
    those the one with corner (0, 0) nearest the image's top-left; -1 when none fits. One pass for all eight
    (it was ~20 small array operations each)."""
    n = uv.shape[0]
    h, w = smooth.shape
    grid = np.empty((rows, cols, 2))
    ids = np.empty((n, 2), np.int64)
    best = -1
    best_bad = True
    best_sum = 0.0
    for s in range(symmetries.shape[0]):
        m = symmetries[s]
        lo0 = lo1 = 1 << 62
        hi0 = hi1 = -(1 << 62)
        for i in range(n):
            a = m[0, 0] * uv[i, 0] + m[0, 1] * uv[i, 1]
            b = m[1, 0] * uv[i, 0] + m[1, 1] * uv[i, 1]
            ids[i, 0] = a
            ids[i, 1] = b
            lo0 = min(lo0, a)
            lo1 = min(lo1, b)
            hi0 = max(hi0, a)
            hi1 = max(hi1, b)
        if hi0 - lo0 + 1 != cols or hi1 - lo1 + 1 != rows:
            continue
        for i in range(n):
            grid[ids[i, 1] - lo1, ids[i, 0] - lo0, 0] = xy[i, 0]
            grid[ids[i, 1] - lo1, ids[i, 0] - lo0, 1] = xy[i, 1]
        # mean steps along the columns and the rows, summed in row-major order
        cx = cy = 0.0
        for r in range(rows):
            for c in range(cols - 1):
                cx += grid[r, c + 1, 0] - grid[r, c, 0]
                cy += grid[r, c + 1, 1] - grid[r, c, 1]
        rx = ry = 0.0
        for r in range(rows - 1):
            for c in range(cols):
                rx += grid[r + 1, c, 0] - grid[r, c, 0]
                ry += grid[r + 1, c, 1] - grid[r, c, 1]
        nc = max(rows * (cols - 1), 1)
        nr = max((rows - 1) * cols, 1)
        cx /= nc
        cy /= nc
        rx /= nr
        ry /= nr
        if cx * ry - cy * rx <= 0:
            continue
        colour_ok = True
        if (cols + rows) % 2 == 1:
            colour_ok = _square_darkness(grid, smooth, h, w) > 0
        total = grid[0, 0, 0] + grid[0, 0, 1]
        bad = not colour_ok
        if best < 0 or (bad < best_bad) or (bad == best_bad and total < best_sum):
            best = s
            best_bad = bad
            best_sum = total
    return best


@njit(cache=True, nogil=True)
def _square_darkness(grid: np.ndarray, smooth: np.ndarray, h: int, w: int) -> float:
    """Mean intensity of the squares whose low corner has odd col+row minus that of those with even col+row
    (grid (rows, cols, 2), each square sampled at its centre's pixel). Positive: the squares with even col+row
    at their low corner are dark."""
    odd_sum = even_sum = 0.0
    n_odd = n_even = 0
    for r in range(grid.shape[0] - 1):
        for c in range(grid.shape[1] - 1):
            x = 0.25 * (grid[r, c, 0] + grid[r + 1, c, 0] + grid[r, c + 1, 0] + grid[r + 1, c + 1, 0])
            y = 0.25 * (grid[r, c, 1] + grid[r + 1, c, 1] + grid[r, c + 1, 1] + grid[r + 1, c + 1, 1])
            xi = min(max(int(np.rint(x)), 0), w - 1)
            yi = min(max(int(np.rint(y)), 0), h - 1)
            v = float(smooth[yi, xi])
            if (r + c) % 2 == 0:
                even_sum += v
                n_even += 1
            else:
                odd_sum += v
                n_odd += 1
    if n_even == 0 or n_odd == 0:
        return 0.0
    return odd_sum / n_odd - even_sum / n_even


def grid_is_regular(corners: np.ndarray, ids: np.ndarray, cols: int, rows: int, cross_ratio_tolerance: float,
                    max_turn_deg: float = 40.0, max_step_ratio: float = 2.0) -> bool:
    """Final check of a complete, numbered board: every row and column is a smooth run of corners.

    Consecutive steps may turn by at most ``max_turn_deg`` (room for fisheye lenses) and change length by at
    most ``max_step_ratio``; every four consecutive corners keep the cross-ratio of equal steps (Eq. 8)
    within ``cross_ratio_tolerance``. A grid whose labels went wrong zig-zags and fails.
    """
    grid, complete = _board_grid(np.ascontiguousarray(corners, np.float64), np.ascontiguousarray(ids, np.int64),
                                 rows, cols)
    if not complete:
        return False
    cos_turn = math.cos(math.radians(max_turn_deg))  # (np.cos(np.radians(.)) to the bit, without its overhead)
    return _lines_are_regular(grid, cos_turn, max_step_ratio, cross_ratio_tolerance) and _lines_are_regular(
        np.ascontiguousarray(grid.transpose(1, 0, 2)), cos_turn, max_step_ratio, cross_ratio_tolerance)


@njit(cache=True, nogil=True)
def _board_grid(corners: np.ndarray, ids: np.ndarray, rows: int, cols: int) -> tuple[np.ndarray, bool]:
    """The corners (N, 2) laid out by their ids (N, 2: col, row; negative ones counted from the end, as numpy
    indexes) as a grid (rows, cols, 2), and whether it is complete: no NaN left (one numba pass instead of
    numpy's fill, scatter and NaN test)."""
    grid = np.full((rows, cols, 2), np.nan)
    for i in range(ids.shape[0]):
        c = ids[i, 0] + cols if ids[i, 0] < 0 else ids[i, 0]
        r = ids[i, 1] + rows if ids[i, 1] < 0 else ids[i, 1]
        if not (0 <= c < cols and 0 <= r < rows):
            raise IndexError("grid_is_regular: an id outside the board")
        grid[r, c, 0] = corners[i, 0]
        grid[r, c, 1] = corners[i, 1]
    for r in range(rows):
        for c in range(cols):
            if math.isnan(grid[r, c, 0]) or math.isnan(grid[r, c, 1]):
                return grid, False
    return grid, True


@njit(cache=True, nogil=True)
def _lines_are_regular(lines: np.ndarray, cos_turn: float, max_step_ratio: float, tolerance: float) -> bool:
    """grid_is_regular's tests on the rows of ``lines`` (n_lines, n, 2): no step shorter than 1e-6 px, turns
    with a cosine of at least ``cos_turn``, step ratios up to ``max_step_ratio``, and every run of four within
    ``tolerance`` of the cross-ratio of equal steps (positions along the run by cumulative step length)."""
    n_lines, n = lines.shape[0], lines.shape[1]
    n_steps = n - 1
    length = np.empty(max(n_steps, 0))
    for li in range(n_lines):
        for j in range(n_steps):
            dx = lines[li, j + 1, 0] - lines[li, j, 0]
            dy = lines[li, j + 1, 1] - lines[li, j, 1]
            length[j] = math.sqrt(dx * dx + dy * dy)
            if length[j] < 1e-6:
                return False
        for j in range(n_steps - 1):
            ax = lines[li, j + 1, 0] - lines[li, j, 0]
            ay = lines[li, j + 1, 1] - lines[li, j, 1]
            bx = lines[li, j + 2, 0] - lines[li, j + 1, 0]
            by = lines[li, j + 2, 1] - lines[li, j + 1, 1]
            la = length[j]
            lb = length[j + 1]
            if (ax * bx + ay * by) / (la * lb) < cos_turn:
                return False
            if max(la / lb, lb / la) > max_step_ratio:
                return False
        for j in range(n_steps - 2):
            x2 = length[j]
            x3 = x2 + length[j + 1]
            x4 = x3 + length[j + 2]
            cr = x3 * (x4 - x2) / ((x3 - x2) * x4)
            if abs(cr - 4.0 / 3.0) / (4.0 / 3.0) > tolerance:
                return False
    return True
