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

import numpy as np

from edgecal.targets import Board

# The eight symmetries of the lattice as 2x2 integer matrices acting on (u, v).
_SYMMETRIES = [np.array(m, dtype=np.int64) for m in (
    ((1, 0), (0, 1)), ((0, -1), (1, 0)), ((-1, 0), (0, -1)), ((0, 1), (-1, 0)),
    ((-1, 0), (0, 1)), ((1, 0), (0, -1)), ((0, 1), (1, 0)), ((0, -1), (-1, 0)))]


def _mean_step(uv: np.ndarray, xy: np.ndarray, axis: int) -> np.ndarray:
    """Mean image displacement for +1 along label ``axis`` (0 = u, 1 = v)."""
    index = {(int(u), int(v)): i for i, (u, v) in enumerate(uv)}
    steps = []
    for i, (u, v) in enumerate(uv):
        key = (int(u) + (axis == 0), int(v) + (axis == 1))
        j = index.get(key)
        if j is not None:
            steps.append(xy[j] - xy[i])
    return np.mean(steps, axis=0) if steps else np.zeros(2)


def square_darkness(uv: np.ndarray, xy: np.ndarray, smooth: np.ndarray) -> float:
    """Mean intensity of squares whose low corner has odd u+v minus that of squares with even u+v.

    Positive means squares with even u+v (at their low corner) are the dark ones.
    """
    index = {(int(u), int(v)): i for i, (u, v) in enumerate(uv)}
    h, w = smooth.shape
    sums = {0: [], 1: []}
    for (u, v), i in index.items():
        quad = [index.get((u + 1, v)), index.get((u, v + 1)), index.get((u + 1, v + 1))]
        if any(q is None for q in quad):
            continue
        c = (xy[i] + xy[quad[0]] + xy[quad[1]] + xy[quad[2]]) / 4.0
        x, y = int(round(c[0])), int(round(c[1]))
        if 0 <= x < w and 0 <= y < h:
            sums[(u + v) % 2].append(float(smooth[y, x]))
    if not sums[0] or not sums[1]:
        return 0.0
    return float(np.mean(sums[1]) - np.mean(sums[0]))


def assign_ids(uv: np.ndarray, xy: np.ndarray, smooth: np.ndarray, board: Board) -> np.ndarray | None:
    """(col, row) ids for a complete grid of labels ``uv`` at image points ``xy``, or None if it does not fit."""
    uv = np.asarray(uv, dtype=np.int64)
    best = None
    for m in _SYMMETRIES:
        ids = uv @ m.T
        ids = ids - ids.min(axis=0)
        span = ids.max(axis=0) + 1
        if span[0] != board.cols or span[1] != board.rows:
            continue
        d_col = _mean_step(ids, xy, 0)
        d_row = _mean_step(ids, xy, 1)
        if d_col[0] * d_row[1] - d_col[1] * d_row[0] <= 0:
            continue
        # Squares with even col+row at their low corner must be dark (the black square at +,+ of (0, 0)).
        colour_ok = square_darkness(ids, xy, smooth) > 0 if (board.cols + board.rows) % 2 == 1 else True
        origin = xy[np.nonzero((ids[:, 0] == 0) & (ids[:, 1] == 0))[0][0]]
        key = (not colour_ok, float(origin[0] + origin[1]))
        if best is None or key < best[0]:
            best = (key, ids)
    return None if best is None else best[1]


def grid_is_regular(corners: np.ndarray, ids: np.ndarray, cols: int, rows: int, cross_ratio_tolerance: float,
                    max_turn_deg: float = 40.0, max_step_ratio: float = 2.0) -> bool:
    """Final check of a complete, numbered board: every row and column is a smooth run of corners.

    Consecutive steps may turn by at most ``max_turn_deg`` (room for fisheye lenses) and change length by at
    most ``max_step_ratio``; every four consecutive corners keep the cross-ratio of equal steps (Eq. 8)
    within ``cross_ratio_tolerance``. A grid whose labels went wrong zig-zags and fails.
    """
    grid = np.full((rows, cols, 2), np.nan)
    grid[ids[:, 1], ids[:, 0]] = corners
    if np.isnan(grid).any():
        return False
    cos_turn = np.cos(np.radians(max_turn_deg))
    for lines in (grid, grid.transpose(1, 0, 2)):  # rows, then columns
        steps = np.diff(lines, axis=1)
        length = np.linalg.norm(steps, axis=2)
        if (length < 1e-6).any():
            return False
        if steps.shape[1] >= 2:
            a, b = steps[:, :-1], steps[:, 1:]
            la, lb = length[:, :-1], length[:, 1:]
            if ((a * b).sum(axis=2) / (la * lb) < cos_turn).any():
                return False
            if (np.maximum(la / lb, lb / la) > max_step_ratio).any():
                return False
        if steps.shape[1] >= 3:
            # positions along each run of four, measured along the run's chord
            x1 = np.zeros(length[:, :-2].shape)
            x2 = length[:, :-2]
            x3 = x2 + length[:, 1:-1]
            x4 = x3 + length[:, 2:]
            cr = (x3 - x1) * (x4 - x2) / ((x3 - x2) * (x4 - x1))
            if (np.abs(cr - 4.0 / 3.0) / (4.0 / 3.0) > cross_ratio_tolerance).any():
                return False
    return True
