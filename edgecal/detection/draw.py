"""Overlays like the paper's Fig. 5: candidates, accepted points, border directions, ids."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np

from edgecal.detection.types import DetectionDebug
from edgecal.fileio import write_png

_SHIFT = 4  # cv2 drawing with 1/16 px precision, so sub-pixel corners are drawn where they are
_ONE = 1 << _SHIFT


def _pt(xy: np.ndarray) -> tuple[int, int]:
    # OpenCV drawing puts integer coordinates at pixel centres, as our convention does.
    return int(round(xy[0] * _ONE)), int(round(xy[1] * _ONE))


def draw_overlay(grey: np.ndarray, debug: DetectionDebug) -> np.ndarray:
    """A BGR picture of one detection: red = candidates, green = accepted (with the four directions in
    yellow), and each found board's grid with its (col, row) ids, corner (0, 0) in blue."""
    img = cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR)
    scale = max(1.0, max(grey.shape) / 800.0)
    for p in debug.candidates:
        cv2.circle(img, _pt(p), int(2 * scale * _ONE), (0, 0, 255), 1, cv2.LINE_AA, _SHIFT)
    for p, dirs, s in zip(debug.accepted, debug.directions, debug.spacing):
        cv2.circle(img, _pt(p), int(3 * scale * _ONE), (0, 200, 0), 1, cv2.LINE_AA, _SHIFT)
        length = 0.4 * s
        for a in dirs:
            q = p + length * np.array([math.cos(a), math.sin(a)])
            cv2.line(img, _pt(p), _pt(q), (0, 220, 220), 1, cv2.LINE_AA, _SHIFT)
    for det in debug.detections:
        index = {(int(c), int(r)): i for i, (c, r) in enumerate(det.ids)}
        for (c, r), i in index.items():
            for nb in ((c + 1, r), (c, r + 1)):
                j = index.get(nb)
                if j is not None:
                    cv2.line(img, _pt(det.corners[i]), _pt(det.corners[j]), (255, 128, 0), 1, cv2.LINE_AA,
                             _SHIFT)
        for (c, r), xy in zip(det.ids, det.corners):
            colour = (255, 0, 0) if (c, r) == (0, 0) else (0, 255, 0)
            cv2.circle(img, _pt(xy), int(4 * scale * _ONE), colour, 2, cv2.LINE_AA, _SHIFT)
            cv2.putText(img, f"{c},{r}", (int(xy[0] + 4), int(xy[1] - 4)), cv2.FONT_HERSHEY_SIMPLEX,
                        0.3 * scale, (255, 0, 255), 1, cv2.LINE_AA)
        x0, y0 = det.corners[0]
        cv2.putText(img, det.board, (int(x0), int(y0 - 12 * scale)), cv2.FONT_HERSHEY_SIMPLEX, 0.5 * scale,
                    (255, 0, 0), 1, cv2.LINE_AA)
    return img


def write_overlay(path: str | Path, grey: np.ndarray, debug: DetectionDebug, force: bool = False) -> None:
    """Draw the overlay and write it as PNG, atomically; an existing file is kept unless ``force``."""
    write_png(path, draw_overlay(grey, debug), force=force)
