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


def _dense(ids: np.ndarray, xy: np.ndarray, cols: int, rows: int) -> np.ndarray:
    """The corners as a (rows, cols, 2) array indexed [row, col]."""
    grid = np.empty((rows, cols, 2))
    grid[ids[:, 1], ids[:, 0]] = xy
    return grid


def square_darkness(grid: np.ndarray, smooth: np.ndarray) -> float:
    """Mean intensity of the squares whose low corner has odd col+row minus that of those with even col+row.

    ``grid`` is (rows, cols, 2). Positive means the squares with even col+row at their low corner are dark.
    """
    centres = 0.25 * (grid[:-1, :-1] + grid[1:, :-1] + grid[:-1, 1:] + grid[1:, 1:])
    h, w = smooth.shape
    x = np.clip(np.rint(centres[..., 0]).astype(np.int64), 0, w - 1)
    y = np.clip(np.rint(centres[..., 1]).astype(np.int64), 0, h - 1)
    vals = smooth[y, x]
    r, c = np.mgrid[0:vals.shape[0], 0:vals.shape[1]]
    even = (r + c) % 2 == 0
    if not even.any() or even.all():
        return 0.0
    return float(vals[~even].mean() - vals[even].mean())


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
        grid = _dense(ids, xy, board.cols, board.rows)
        d_col = (grid[:, 1:] - grid[:, :-1]).reshape(-1, 2).mean(axis=0)
        d_row = (grid[1:] - grid[:-1]).reshape(-1, 2).mean(axis=0)
        if d_col[0] * d_row[1] - d_col[1] * d_row[0] <= 0:
            continue
        # Squares with even col+row at their low corner must be dark (the black square at +,+ of (0, 0)).
        colour_ok = square_darkness(grid, smooth) > 0 if (board.cols + board.rows) % 2 == 1 else True
        origin = grid[0, 0]
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
