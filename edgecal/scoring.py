"""Scoring chessboard detections against ground truth: pure functions, used by tests and bench/.

Ground truth is a :class:`~edgecal.synth.truth.GroundTruth`: read from the renderer's JSON
("edgecal-synth-gt/1", edgecal.synth.truth; shared/data/synthetic/README.md) or from reference corners
shipped with real photographs (bench/references.py). Everything here is arrays in, numbers out; nothing
in the library itself imports this module.

Vocabulary:

- A *found grid* (:class:`FoundGrid`) is what any detector returned for one board: corner positions,
  their (col, row) ids and the grid size. Adapters in bench/ turn each detector's output into one.
- A detection *matches* a truth board under a symmetry of the id grid. Two policies:
  ``"board"`` allows only what the truth format allows (identity, the 180 degree turn
  (col, row) -> (cols-1-col, rows-1-row), and the 90 degree turns for square boards): edgecal is held
  to this. ``"grid"`` allows every symmetry of the grid, transposes and mirrors included: the
  references know nothing of our numbering, and a mirrored order of a flat board is still a valid set
  of 2-D/3-D pairs for calibration.
- A corner is *correct* when the truth corner nearest to it is the one its (mapped) id names and it
  lies within ``max_error_px`` of it. A board is *found* ("all corners found and correctly ordered")
  when every truth corner is named by one detected corner and all of them are correct (for rough
  references: at least ``min_fraction`` of them).
- A *false board* is a detection that lies on no truth board: fewer than half of its corners are
  within ``max_error_px`` of some truth corner.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np

from edgecal.synth.truth import GroundTruth, TruthBoard

#: Default distance (px) within which a detected corner counts as found.
MAX_ERROR_PX = 3.0


# ----------------------------------------------------------------------------------------------------
# Data


@dataclass(frozen=True)
class FoundGrid:
    """A detector's result for one board: corners (N, 2), ids (N, 2) (col, row), grid (cols, rows).

    ``name`` is the target board the detector says it is ("" when it does not say).
    """

    corners: np.ndarray
    ids: np.ndarray
    grid: tuple[int, int]
    complete: bool = True
    name: str = ""


@dataclass(frozen=True)
class BoardMatch:
    """How one found grid lines up with one truth board (under the best allowed symmetry).

    ``errors`` (K,) px and ``correct`` (K,) bool are for the K detected corners whose mapped id is a
    visible truth corner; ``symmetry`` names the id map used; ``found`` is the verdict "all corners
    found and correctly ordered".
    """

    symmetry: str
    errors: np.ndarray
    correct: np.ndarray
    n_truth: int
    n_named: int
    found: bool


@dataclass
class ImageScore:
    """Scores of all detections in one image.

    ``matches[i]`` is the match of truth board i (None when no detection was assigned to it);
    ``false_boards`` counts detections that lie on no truth board; ``partial`` counts detections that
    lie on a truth board without being its complete, correctly ordered match (a sub-grid, a grid of
    another size, a mis-ordering, or a second detection of a board already matched); ``misnamed``
    counts found boards whose detector-given name is not the truth board's (boards of one size on a
    calibration box must still be told apart).
    """

    n_truth: int
    matches: list[BoardMatch | None] = field(default_factory=list)
    false_boards: int = 0
    partial: int = 0
    misnamed: int = 0

    @property
    def n_found(self) -> int:
        """Truth boards found with all corners correctly ordered."""
        return sum(1 for m in self.matches if m is not None and m.found)

    def found_errors(self) -> np.ndarray:
        """Corner errors (px) of the correct corners of found boards, pooled."""
        parts = [m.errors[m.correct] for m in self.matches if m is not None and m.found]
        return np.concatenate(parts) if parts else np.zeros(0)


# ----------------------------------------------------------------------------------------------------
# Grid symmetries


IdMap = Callable[[np.ndarray], np.ndarray]


def _dihedral(cols: int, rows: int) -> list[tuple[str, tuple[int, int], bool, IdMap]]:
    """The 8 symmetries of a cols x rows id grid: (name, result grid size, keeps handedness, map)."""
    c1, r1 = cols - 1, rows - 1
    return [
        ("identity", (cols, rows), True, lambda i: i.copy()),
        ("rot180", (cols, rows), True, lambda i: np.stack([c1 - i[:, 0], r1 - i[:, 1]], axis=1)),
        ("rot90", (rows, cols), True, lambda i: np.stack([r1 - i[:, 1], i[:, 0]], axis=1)),
        ("rot270", (rows, cols), True, lambda i: np.stack([i[:, 1], c1 - i[:, 0]], axis=1)),
        ("flip_cols", (cols, rows), False, lambda i: np.stack([c1 - i[:, 0], i[:, 1]], axis=1)),
        ("flip_rows", (cols, rows), False, lambda i: np.stack([i[:, 0], r1 - i[:, 1]], axis=1)),
        ("transpose", (rows, cols), False, lambda i: i[:, ::-1].copy()),
        ("antitranspose", (rows, cols), False,
         lambda i: np.stack([r1 - i[:, 1], c1 - i[:, 0]], axis=1)),
    ]


def grid_symmetries(found_grid: tuple[int, int], truth_grid: tuple[int, int],
                    policy: str = "board") -> list[tuple[str, IdMap]]:
    """Id maps that carry a found grid of size ``found_grid`` onto a truth grid of ``truth_grid``.

    ``policy="board"``: identity and the 180 degree turn when the sizes are equal, plus the 90 degree
    turns when the board is square (the README's symmetries). ``policy="grid"``: every one of the
    8 grid symmetries whose result has the truth's size (a transposed size included).
    """
    if policy not in ("board", "grid"):
        raise ValueError(f"unknown policy {policy!r}: use 'board' or 'grid'")
    cols, rows = int(found_grid[0]), int(found_grid[1])
    truth_grid = (int(truth_grid[0]), int(truth_grid[1]))
    if policy == "board" and (cols, rows) != truth_grid:
        return []  # a 6x9 grid for a 9x6 target is the size-convention mistake, not a turn
    out = []
    for name, size, proper, fn in _dihedral(cols, rows):
        if size != truth_grid:
            continue
        if policy == "board" and not proper:
            continue
        out.append((name, fn))
    return out


# ----------------------------------------------------------------------------------------------------
# Matching and scoring


def _nearest_truth_index(points: np.ndarray, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Index of and distance to the nearest truth corner for each point (brute force; boards are small)."""
    if len(points) == 0 or len(truth) == 0:
        return np.zeros(len(points), dtype=np.int64), np.full(len(points), np.inf)
    d = np.linalg.norm(points[:, None, :] - truth[None, :, :], axis=2)
    j = np.argmin(d, axis=1)
    return j, d[np.arange(len(points)), j]


def match_board(found: FoundGrid, truth: TruthBoard, policy: str = "board",
                max_error_px: float = MAX_ERROR_PX, min_fraction: float = 1.0) -> BoardMatch | None:
    """Best match of ``found`` to ``truth`` over the allowed id symmetries, or None if none applies.

    The best symmetry is the one with the most correct corners (ties: smaller median error). The match
    is ``found`` when the detection is complete, names every visible truth corner, and at least
    ``min_fraction`` of those corners are correct (1.0: all of them).
    """
    corners = np.asarray(found.corners, dtype=np.float64).reshape(-1, 2)
    ids = np.asarray(found.ids, dtype=np.int64).reshape(-1, 2)
    t_ids = np.asarray(truth.ids, dtype=np.int64).reshape(-1, 2)
    t_xy = np.asarray(truth.corners, dtype=np.float64).reshape(-1, 2)
    if len(corners) != len(ids):
        raise ValueError(f"found grid has {len(corners)} corners but {len(ids)} ids")
    key = {(int(c), int(r)): k for k, (c, r) in enumerate(t_ids)}
    nearest, _ = _nearest_truth_index(corners, t_xy)
    best: BoardMatch | None = None
    best_rank: tuple[int, float] | None = None
    for name, fn in grid_symmetries(found.grid, (truth.cols, truth.rows), policy):
        mapped = fn(ids) if len(ids) else ids
        rows_t = np.array([key.get((int(c), int(r)), -1) for c, r in mapped], dtype=np.int64)
        named = rows_t >= 0
        if not named.any():
            continue
        k = rows_t[named]
        err = np.linalg.norm(corners[named] - t_xy[k], axis=1)
        ok = (nearest[named] == k) & (err <= max_error_px)
        n_named = len(np.unique(k))
        need = math.ceil(min_fraction * len(t_ids) - 1e-9)
        verdict = bool(found.complete and n_named == len(t_ids) and int(ok.sum()) >= need)
        rank = (int(ok.sum()), -float(np.median(err)))
        if best_rank is None or rank > best_rank:
            best_rank = rank
            best = BoardMatch(name, err, ok, len(t_ids), n_named, verdict)
    return best


def lies_on(found: FoundGrid, truth: TruthBoard, max_error_px: float = MAX_ERROR_PX) -> float:
    """Fraction of the found corners within ``max_error_px`` of some corner of ``truth`` (ids ignored)."""
    corners = np.asarray(found.corners, dtype=np.float64).reshape(-1, 2)
    if len(corners) == 0:
        return 0.0
    _, d = _nearest_truth_index(corners, np.asarray(truth.corners, dtype=np.float64).reshape(-1, 2))
    return float(np.mean(d <= max_error_px))


def score_image(found: Sequence[FoundGrid], truth: GroundTruth, policy: str = "board",
                max_error_px: float = MAX_ERROR_PX, min_fraction: float | None = None) -> ImageScore:
    """Assign detections to truth boards one-to-one and score them.

    A detection goes to the truth board it lies on most (at least half of its corners near that
    board's corners); among several detections on one board the best match wins. Detections that lie
    on no board are false boards; the rest that are not a found match are partial. ``min_fraction``
    defaults to 1.0 for exact truth and 0.75 for reference corners (OCamCalib's points hold up to a
    fifth of off-corner points in some views).
    """
    if min_fraction is None:
        min_fraction = 1.0 if truth.exact else 0.75
    score = ImageScore(n_truth=len(truth.boards), matches=[None] * len(truth.boards))
    claims: list[tuple[tuple[int, int, float], int, BoardMatch | None, str]] = []
    for f in found:
        on = [lies_on(f, tb, max_error_px) for tb in truth.boards]
        if not on or max(on) < 0.5:
            score.false_boards += 1
            continue
        b = int(np.argmax(on))
        m = match_board(f, truth.boards[b], policy, max_error_px, min_fraction)
        rank = (int(m.found) if m else 0, int(m.correct.sum()) if m else 0, on[b])
        claims.append((rank, b, m, f.name))
    claims.sort(key=lambda c: c[0], reverse=True)
    for _, b, m, name in claims:
        if score.matches[b] is None and m is not None:
            score.matches[b] = m
            if not m.found:
                score.partial += 1
            elif name and name != truth.boards[b].name:
                score.misnamed += 1
        else:
            score.partial += 1
    return score


def corner_rms(errors: np.ndarray) -> float:
    """Root-mean-square of corner errors (px); NaN when there are none."""
    e = np.asarray(errors, dtype=np.float64).ravel()
    return float(np.sqrt(np.mean(e * e))) if e.size else float("nan")


def percentile(values: Iterable[float], q: float) -> float:
    """The q-th percentile (0..100) of ``values``; NaN when empty."""
    v = np.asarray(list(values), dtype=np.float64)
    return float(np.percentile(v, q)) if v.size else float("nan")


# ----------------------------------------------------------------------------------------------------
# Grid plausibility (real photographs without reference corners)


def grid_is_plausible(found: FoundGrid, max_turn_deg: float = 40.0, max_step_ratio: float = 2.5) -> bool:
    """True when a complete grid is locally regular: a check for images without reference corners.

    Along every row and every column consecutive steps may turn by at most ``max_turn_deg`` and change
    length by at most ``max_step_ratio`` (room for strong lens distortion), and the row and column
    directions at each corner are at least 20 degrees apart. A zig-zag from a mis-ordered grid fails.
    """
    cols, rows = int(found.grid[0]), int(found.grid[1])
    ids = np.asarray(found.ids, dtype=np.int64).reshape(-1, 2)
    if not found.complete or len(ids) != cols * rows:
        return False
    grid = np.full((rows, cols, 2), np.nan)
    inside = (ids[:, 0] >= 0) & (ids[:, 0] < cols) & (ids[:, 1] >= 0) & (ids[:, 1] < rows)
    if not inside.all():
        return False
    grid[ids[:, 1], ids[:, 0]] = np.asarray(found.corners, dtype=np.float64).reshape(-1, 2)
    if np.isnan(grid).any():
        return False  # repeated ids leave holes
    cos_turn = math.cos(math.radians(max_turn_deg))
    # consecutive steps along each row (axis 1: col to col+1), then along each column (axis 0)
    for ax in (1, 0):
        steps = np.diff(grid, axis=ax)
        length = np.linalg.norm(steps, axis=2)
        if (length < 1e-6).any():
            return False
        n = steps.shape[ax]
        if n < 2:
            continue
        a, b = np.take(steps, np.arange(n - 1), axis=ax), np.take(steps, np.arange(1, n), axis=ax)
        la, lb = np.take(length, np.arange(n - 1), axis=ax), np.take(length, np.arange(1, n), axis=ax)
        cos = (a * b).sum(axis=2) / (la * lb)
        if (cos < cos_turn).any() or (np.maximum(la / lb, lb / la) > max_step_ratio).any():
            return False
    d_col = np.gradient(grid, axis=1)
    d_row = np.gradient(grid, axis=0)
    cos = np.abs((d_col * d_row).sum(axis=2)) / (
        np.linalg.norm(d_col, axis=2) * np.linalg.norm(d_row, axis=2) + 1e-12)
    return bool((cos < math.cos(math.radians(20.0))).all())
