"""What the detector returns."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from edgecal.targets import Board


@dataclass
class Detection:
    """One board found in an image.

    corners: (N, 2) float64 pixel positions, OpenCV convention (integer = pixel centre).
    ids:     (N, 2) int64 (col, row) of each corner on the board ``board``, matching the target.
    quality: (N,) float64 per-corner figure in [0, 1] (1 = a clean saddle; see docs/detector.md).
    grid:    (cols, rows) of the grid that was found (equals the board's size when complete).
    copy:    0 for the first (or only) board of this name in the image, 1, 2, ... for further boards of
             the same size, numbered by position (centroid top to bottom, then left to right).
    """

    board: str
    corners: np.ndarray
    ids: np.ndarray
    quality: np.ndarray
    grid: tuple[int, int]
    complete: bool = True
    copy: int = 0

    def as_json(self) -> dict:
        """The JSON form printed by ``edgecal detect``."""
        return {
            "name": self.board,
            "copy": self.copy,
            "corners": [[round(float(x), 4), round(float(y), 4)] for x, y in self.corners],
            "ids": [[int(c), int(r)] for c, r in self.ids],
        }


@dataclass
class DetectionDebug:
    """Intermediate results of one detection, for overlays and debugging.

    candidates:  (M, 2) minimum-eigenvalue candidates.
    accepted:    (K, 2) points that passed the probe's angle and sign tests (sub-pixel).
    directions:  (K, 4) border directions in radians at each accepted point.
    spacing:     (K,) estimated local square size in pixels at each accepted point.
    detections:  the final boards.
    notes:       human-readable remarks, each once, e.g. a grid of another size than the target's
                 ("found a 9x6 grid; the target says 8x6 inner corners").
    """

    candidates: np.ndarray
    accepted: np.ndarray
    directions: np.ndarray
    spacing: np.ndarray
    detections: list[Detection] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)


@dataclass(frozen=True)
class CornerPrediction:
    """Where the corners of one board are expected in an image (edgecal.detection.tracking verifies them).

    ids: (N, 2) int64 (col, row) on ``board``; xy: (N, 2) float64 pixels, OpenCV convention.
    """

    board: Board
    ids: np.ndarray
    xy: np.ndarray
