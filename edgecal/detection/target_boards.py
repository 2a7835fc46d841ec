"""Which of the target's boards a grid is: board sizes, full rectangles, copies of one board, near misses."""

from __future__ import annotations

import numpy as np

from edgecal.detection.types import Detection
from edgecal.targets import Board, Target


def grid_span(grid: dict[tuple[int, int], np.ndarray]) -> tuple[int, int]:
    """(cols, rows) the grid's labels span."""
    # in Python: the labels are tuples of ints, and an array made of them cost several times the min/max
    us, vs = zip(*grid)
    return int(max(us) - min(us) + 1), int(max(vs) - min(vs) + 1)


def is_full_board(grid: dict[tuple[int, int], np.ndarray], by_size: dict[frozenset, list[Board]]) -> bool:
    """Whether the grid is a full rectangle of one of the target's board sizes (no completion needed)."""
    span = grid_span(grid)
    return len(grid) == span[0] * span[1] and frozenset(span) in by_size


def boards_by_size(target: Target) -> dict[frozenset, list[Board]]:
    """The target's boards by their size {cols, rows} (either way round)."""
    out: dict[frozenset, list[Board]] = {}
    for b in target.boards:
        out.setdefault(frozenset((b.cols, b.rows)), []).append(b)
    return out


def all_boards_found(detections: list[Detection], target: Target) -> bool:
    """Whether every board of the target has been found at least once."""
    return {b.name for b in target.boards} <= {d.board for d in detections}


def number_copies(detections: list[Detection]) -> None:
    """Number the detections of each board name 0, 1, ... by position (centroid top to bottom, then left
    to right), so that the numbering does not depend on the order the grids were found in."""
    by_name: dict[str, list[Detection]] = {}
    for d in detections:
        by_name.setdefault(d.board, []).append(d)
    for same in by_name.values():
        if len(same) == 1:
            same[0].copy = 0
            continue
        keys = [(float(d.corners[:, 1].mean()), float(d.corners[:, 0].mean())) for d in same]
        for k, i in enumerate(sorted(range(len(same)), key=lambda j: keys[j])):
            same[i].copy = k
    detections.sort(key=lambda d: (d.board, d.copy))


def note_near_miss(notes: list[str], span: np.ndarray, full: bool, n: int, target: Target) -> None:
    """Record a grid that matched no board: the most common cause is a board-size convention mistake
    (or a board that is part of a larger grid). Small fragments, mostly clutter, are not worth a note."""
    sizes = ", ".join(f"{b.cols}x{b.rows}" for b in target.boards)
    if n < min(12, min(b.n_corners for b in target.boards)):
        return
    # The grid's labels have no preferred axis: say its size the way round the target says its own.
    first = target.boards[0]
    if (span[0] >= span[1]) != (first.cols >= first.rows):
        span = span[::-1]
    if full:
        notes.append(f"found a {span[0]}x{span[1]} grid; the target says {sizes} inner corners")
    else:
        notes.append(f"found a partial grid of {n} corners spanning {span[0]}x{span[1]}; "
                     f"the target says {sizes} inner corners")
