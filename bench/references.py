"""Reference corners shipped with real photographs, read as ground truth for bench/detect.py.

Two formats: an OpenCV test ``.dat`` corner file (OpenCV's own output, so not independent truth) and
OCamCalib's points converted to JSON (Fisheye190Pts.json). Both give edgecal.synth.truth's
GroundTruth with ``exact=False``: scoring then lets a few off-corner points pass (edgecal.scoring).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from edgecal.errors import InputError
from edgecal.synth.truth import GroundTruth, TruthBoard, read_truth_json, xy_pairs

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
    data = read_truth_json(p)
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
            xy = xy_pairs(view["points_xy_zero_based"], f"{where}.points_xy_zero_based'")
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
