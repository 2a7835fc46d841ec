"""Scoring chessboard detections against ground truth: pure functions, used by tests and bench/.

Ground truth comes from the renderer's JSON ("edgecal-synth-gt/1", see edgecal/synth and
shared/data/synthetic/README.md) or from reference corners shipped with real photographs (an OpenCV
``.dat`` corner file, OCamCalib's points converted to JSON). Everything here is arrays in, numbers out.

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

import json
import math
import re
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from edgecal.errors import InputError, quote

GT_FORMAT = "edgecal-synth-gt/1"

#: Default distance (px) within which a detected corner counts as found.
MAX_ERROR_PX = 3.0


# ----------------------------------------------------------------------------------------------------
# Data


@dataclass(frozen=True)
class TruthBoard:
    """One board's true (or reference) corners: ``ids`` (N, 2) int (col, row), ``corners`` (N, 2) px."""

    name: str
    cols: int
    rows: int
    ids: np.ndarray
    corners: np.ndarray

    @property
    def complete(self) -> bool:
        """True when all cols x rows corners are listed (visible)."""
        return len(self.ids) == self.cols * self.rows


@dataclass(frozen=True)
class GroundTruth:
    """Truth for one image: its boards (possibly none), and whether the corners are exact.

    ``exact`` is False for reference corners taken from another tool (real photographs): they may hold
    a few off-corner points, so a board counts as found when ``min_fraction`` of its corners agree.
    """

    image: str
    size: tuple[int, int]
    boards: tuple[TruthBoard, ...]
    exact: bool = True
    source: str = ""


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


# ----------------------------------------------------------------------------------------------------
# Loaders


def _read_json(path: Path) -> object:
    if not path.is_file():
        raise InputError(f"{path}: ground-truth file not found")
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"{path}: not readable JSON ({exc})") from None


def _xy_array(value: object, where: str) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float64)
    if arr.size == 0:
        return np.zeros((0, 2))
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise InputError(f"{where}: expected a list of [a, b] pairs")
    return arr


def ground_truth_from_mapping(data: object, source: str) -> GroundTruth:
    """Build a GroundTruth from a parsed "edgecal-synth-gt/1" mapping; ``source`` names it in messages."""
    if not isinstance(data, dict):
        raise InputError(f"{source}: the top level must be a JSON object")
    fmt = data.get("format")
    if fmt != GT_FORMAT:
        raise InputError(f"{source}: field 'format' is {quote(fmt)}, expected {GT_FORMAT!r}")
    try:
        w, h = (int(v) for v in data["size"])
    except (KeyError, TypeError, ValueError):
        raise InputError(f"{source}: field 'size' must be [width, height]") from None
    raw_boards = data.get("boards")
    if not isinstance(raw_boards, list):
        raise InputError(f"{source}: field 'boards' must be a list")
    boards = []
    for i, b in enumerate(raw_boards):
        where = f"{source}: field 'boards[{i}]"
        if not isinstance(b, dict):
            raise InputError(f"{where}' must be an object")
        for key in ("cols", "rows", "ids", "corners"):
            if key not in b:
                raise InputError(f"{where}.{key}' is missing")
        ids = _xy_array(b["ids"], f"{where}.ids'").astype(np.int64)
        xy = _xy_array(b["corners"], f"{where}.corners'")
        if len(ids) != len(xy):
            raise InputError(f"{where}': {len(ids)} ids but {len(xy)} corners")
        boards.append(TruthBoard(str(b.get("name", f"board{i}")), int(b["cols"]), int(b["rows"]), ids, xy))
    image = str(data.get("image", ""))
    return GroundTruth(image, (w, h), tuple(boards), True, source)


def load_ground_truth(path: str | Path) -> GroundTruth:
    """Load a renderer ground-truth JSON file ("edgecal-synth-gt/1"); InputError naming the file/field."""
    p = Path(path)
    return ground_truth_from_mapping(_read_json(p), str(p))


def truth_targets(path: str | Path) -> list[dict]:
    """The ``target.boards`` list of a ground-truth JSON (all boards in the scene, with 3-D placement)."""
    p = Path(path)
    data = _read_json(p)
    boards = data.get("target", {}).get("boards", []) if isinstance(data, dict) else []
    if not isinstance(boards, list):
        raise InputError(f"{p}: field 'target.boards' must be a list")
    return boards


_DAT_NUMBER = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?")


def load_opencv_corners_dat(path: str | Path, image: str, size: tuple[int, int],
                            cols: int, rows: int) -> GroundTruth:
    """Reference corners from an OpenCV test ``.dat`` (``corners: data: [x0, y0, x1, y1, ...]``).

    OpenCV lists them row-major for patternSize (cols, rows): point i is (col i % cols, row i // cols).
    These are OpenCV's own output, not independent truth: the GroundTruth is marked not exact.
    """
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: reference corner file not found")
    text = p.read_text(encoding="utf-8", errors="replace")
    start = text.find("data:")
    if start < 0:
        raise InputError(f"{p}: no 'data:' list of corner coordinates")
    body = text[start + 5:]
    end = body.find("]")
    numbers = [float(t) for t in _DAT_NUMBER.findall(body[:end] if end >= 0 else body)]
    n = cols * rows
    if len(numbers) != 2 * n:
        raise InputError(f"{p}: {len(numbers)} numbers in 'data', expected {2 * n} for {cols}x{rows} corners")
    xy = np.asarray(numbers).reshape(n, 2)
    k = np.arange(n)
    ids = np.stack([k % cols, k // cols], axis=1).astype(np.int64)
    board = TruthBoard(f"reference_{cols}x{rows}", cols, rows, ids, xy)
    return GroundTruth(image, size, (board,), exact=False, source=str(p))


def load_ocamcalib_json(path: str | Path) -> dict[str, GroundTruth]:
    """Reference corners per image from the OCamCalib points converted to JSON (Fisheye190Pts.json).

    Ids come from each point's board coordinates: with ``inner_corners`` [cols, rows], the board axis
    that has ``cols`` distinct values is the column axis. Images are not read (size left (0, 0)).
    """
    p = Path(path)
    data = _read_json(p)
    if not isinstance(data, dict) or not isinstance(data.get("views"), list):
        raise InputError(f"{p}: field 'views' must be a list")
    try:
        cols, rows = (int(v) for v in data["inner_corners"])
        square = float(data["square_mm"])
    except (KeyError, TypeError, ValueError):
        raise InputError(f"{p}: fields 'inner_corners' [cols, rows] and 'square_mm' are required") from None
    out: dict[str, GroundTruth] = {}
    for i, view in enumerate(data["views"]):
        where = f"{p}: field 'views[{i}]"
        try:
            name = str(view["image"])
            xy = _xy_array(view["points_xy_zero_based"], f"{where}.points_xy_zero_based'")
            board_xy = np.asarray(view["board_XYZ_mm"], dtype=np.float64)[:, :2]
        except (KeyError, TypeError, ValueError, IndexError):
            raise InputError(f"{where}' needs 'image', 'points_xy_zero_based' and 'board_XYZ_mm'") from None
        grid = np.rint(board_xy / square).astype(np.int64)
        # which board axis counts the columns: the one with `cols` distinct values
        if len(np.unique(grid[:, 0])) == cols and len(np.unique(grid[:, 1])) == rows and cols != rows:
            ids = grid
        else:
            ids = grid[:, ::-1].copy()
        if len(xy) != len(ids):
            raise InputError(f"{where}': {len(xy)} points but {len(ids)} board coordinates")
        board = TruthBoard(f"reference_{cols}x{rows}", cols, rows, ids, xy)
        out[name] = GroundTruth(name, (0, 0), (board,), exact=False, source=str(p))
    return out
