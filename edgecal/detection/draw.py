"""Overlays of a detection (``edgecal detect --draw``): what a user checks, and the detector's debug layers.

By default the picture answers "did it find my board, and which way round?": each board's outline,
its first corner (0, 0) and the direction of increasing column (the row direction), the corner ids,
the board name, and on a miss a "not found" banner with the detector's near-miss note (e.g. a grid of
another size). ``debug=True`` adds the layers of the paper's Fig. 5: every candidate (red), the accepted
points (green) with their four border directions (yellow).
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np

from edgecal.detection.types import Detection, DetectionDebug
from edgecal.fileio import write_png

_SHIFT = 4  # cv2 drawing with 1/16 px precision, so sub-pixel corners are drawn where they are
_ONE = 1 << _SHIFT
OUTLINE = (255, 160, 0)      # BGR: the board's outline
FIRST = (0, 0, 255)          # corner (0, 0) and the row-direction arrow
CORNER = (0, 220, 0)
TEXT = (255, 255, 255)
IDS = (255, 80, 255)
MISS = (0, 0, 230)
MIN_LABEL_SPACING_PX = 14    # ids are written only where squares are this big (smaller ones would be noise)


def _pt(xy: np.ndarray) -> tuple[int, int]:
    # OpenCV drawing puts integer coordinates at pixel centres, as our convention does.
    return int(round(xy[0] * _ONE)), int(round(xy[1] * _ONE))


def _text(img: np.ndarray, text: str, org: tuple[int, int], scale: float, colour: tuple[int, int, int],
          thickness: int = 1, box: bool = False) -> None:
    """Text at ``org`` (bottom-left); with ``box`` on a dark box, readable on black and white squares alike."""
    if box:
        (w, h), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, thickness)
        cv2.rectangle(img, (org[0] - 2, org[1] - h - 3), (org[0] + w + 2, org[1] + base), (30, 30, 30), -1)
    cv2.putText(img, text, org, cv2.FONT_HERSHEY_SIMPLEX, scale, colour, thickness, cv2.LINE_AA)


def board_outline(det: Detection) -> np.ndarray:
    """The outline (K, 2) of a detected grid through its outermost corners, in order around the board.

    For a complete board the four extreme corners; for a partial one the convex hull of its corners.
    """
    ids = np.asarray(det.ids, dtype=np.int64).reshape(-1, 2)
    xy = np.asarray(det.corners, dtype=np.float64).reshape(-1, 2)
    index = {(int(c), int(r)): i for i, (c, r) in enumerate(ids)}
    c0, r0 = ids.min(axis=0)
    c1, r1 = ids.max(axis=0)
    quad = [(c0, r0), (c1, r0), (c1, r1), (c0, r1)]
    if all(q in index for q in quad):
        return xy[[index[q] for q in quad]]
    return cv2.convexHull(xy.astype(np.float32)).reshape(-1, 2).astype(np.float64)


def _spacing(det: Detection) -> float:
    """Median distance between column neighbours (px)."""
    index = {(int(c), int(r)): i for i, (c, r) in enumerate(det.ids)}
    d = [np.linalg.norm(det.corners[i] - det.corners[index[(c + 1, r)]]) for (c, r), i in index.items()
         if (c + 1, r) in index]
    return float(np.median(d)) if d else 0.0


def _draw_board(img: np.ndarray, det: Detection, scale: float) -> None:
    outline = board_outline(det)
    cv2.polylines(img, [np.array([_pt(p) for p in outline], np.int32)], True, OUTLINE, max(1, int(2 * scale)),
                  cv2.LINE_AA, _SHIFT)
    spacing = _spacing(det)
    label = spacing >= MIN_LABEL_SPACING_PX
    font = float(np.clip(spacing / 60.0, 0.3, 0.6))
    for (c, r), xy in zip(det.ids, det.corners):
        cv2.circle(img, _pt(xy), int(max(2.0, 0.12 * spacing) * _ONE), CORNER, 1, cv2.LINE_AA, _SHIFT)
        if label and (c, r) != (0, 0):
            _text(img, f"{c},{r}", (int(xy[0] + 3), int(xy[1] - 3)), font, IDS)
    index = {(int(c), int(r)): i for i, (c, r) in enumerate(det.ids)}
    first = index.get((0, 0))
    if first is not None:
        p0 = det.corners[first]
        cv2.circle(img, _pt(p0), int(max(5.0, 0.3 * spacing) * _ONE), FIRST, max(2, int(2 * scale)), cv2.LINE_AA,
                   _SHIFT)
        _text(img, "0,0", (int(p0[0] + 5), int(p0[1] - 5)), max(font, 0.45), FIRST, 1, box=True)
        # the row direction: from (0, 0) towards increasing column, two squares long
        nxt = index.get((1, 0))
        if nxt is not None:
            d = det.corners[nxt] - p0
            end = p0 + 2.0 * d
            cv2.arrowedLine(img, _pt(p0), _pt(end), FIRST, max(2, int(2 * scale)), cv2.LINE_AA, _SHIFT, 0.25)
            _text(img, "cols", (int(end[0] + 4), int(end[1] + 4)), max(font, 0.45), FIRST, box=True)
    # the name beside the outline's top-left corner, copies numbered
    top = outline[np.argmin(outline[:, 0] + outline[:, 1])]
    name = det.board + (f" #{det.copy + 1}" if det.copy else "")
    grid = "" if det.complete else f" (partial {len(det.corners)} corners)"
    _text(img, name + grid, (int(top[0]), int(max(14 * scale, top[1] - 10 * scale))), 0.55 * scale, OUTLINE,
          max(1, int(scale)), box=True)


def _draw_debug(img: np.ndarray, debug: DetectionDebug, scale: float) -> None:
    for p in debug.candidates:
        cv2.circle(img, _pt(p), int(2 * scale * _ONE), (0, 0, 255), 1, cv2.LINE_AA, _SHIFT)
    for p, dirs, s in zip(debug.accepted, debug.directions, debug.spacing):
        cv2.circle(img, _pt(p), int(3 * scale * _ONE), (0, 200, 0), 1, cv2.LINE_AA, _SHIFT)
        length = 0.4 * s
        for a in dirs:
            q = p + length * np.array([math.cos(a), math.sin(a)])
            cv2.line(img, _pt(p), _pt(q), (0, 220, 220), 1, cv2.LINE_AA, _SHIFT)


def draw_overlay(grey: np.ndarray, debug: DetectionDebug, show_debug: bool = False) -> np.ndarray:
    """A BGR picture of one detection (see the module docstring); ``show_debug`` adds the detector's layers."""
    img = cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR) if grey.ndim == 2 else grey.copy()
    scale = max(1.0, max(grey.shape[:2]) / 800.0)
    if show_debug:
        _draw_debug(img, debug, scale)
    for det in debug.detections:
        _draw_board(img, det, scale)
    if not debug.detections:
        _text(img, "not found", (int(10 * scale), int(34 * scale)), 1.0 * scale, MISS, max(2, int(2 * scale)), True)
        for k, note in enumerate(debug.notes[:3]):
            _text(img, note[:110], (int(10 * scale), int((62 + 24 * k) * scale)), 0.5 * scale, TEXT, 1, True)
    return img


def write_overlay(path: str | Path, grey: np.ndarray, debug: DetectionDebug, force: bool = False,
                  show_debug: bool = False) -> None:
    """Draw the overlay and write it as PNG, atomically; an existing file is kept unless ``force``."""
    write_png(path, draw_overlay(grey, debug, show_debug), force=force)
