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
    covariance: (N, 2, 2) float64 px^2 per corner (edgecal.detection.corner_covariance), NaN where the
             corner is unusable; None when not computed (a Detection built by hand).
    unusable: (N,) reasons, "" for a usable corner (a covariance that is not positive definite: a flat,
             saturated or degenerate window, a window leaving the image).
    shared_px2: (N,) float64, the part of each corner's covariance (px^2 per axis) that the corners of its
             board share (CornerCovariances); NaN where unusable, None when not computed.
    light_gradient: (N, 2) float64, the gradient of log light (1/px) over each corner's board, read off its
             squares (CornerCovariances); zeros where it was not read, None when not computed.
    alternating_px2: (N,) float64, the part of each corner's covariance (px^2 per axis) that is its board's
             light shift in the checkerboard pattern of its corners (CornerCovariances); None when not computed.
    xjunction_fitted: (N,) bool, the corners the X-junction fit placed (refiner "xjunction"; the others hold
             the saddle fit's or cornerSubPix's position, and get that refiner's covariance); None: all of
             them, for the refiner's covariance.
    bend_px: (N,) float64, the length (px) of the lens-bend correction taken off each X-junction corner
             (edgecal.detection.line_bend; 0 where none was), which its covariance counts; None: none.
    xjunction_noise: (N, 2, 2) float64, the X-junction fit's covariance of each corner it placed per unit
             variance of the image noise (px^2 per grey level^2; subpixel.xjunction_fit), NaN elsewhere; its
             covariance's noise term; None: not fitted (the saddle fit's noise term stands in).
    """

    board: str
    corners: np.ndarray
    ids: np.ndarray
    quality: np.ndarray
    grid: tuple[int, int]
    complete: bool = True
    copy: int = 0
    covariance: np.ndarray | None = None
    unusable: list[str] = field(default_factory=list)
    shared_px2: np.ndarray | None = None
    light_gradient: np.ndarray | None = None
    alternating_px2: np.ndarray | None = None
    xjunction_fitted: np.ndarray | None = None
    bend_px: np.ndarray | None = None
    xjunction_noise: np.ndarray | None = None

    def usable(self) -> np.ndarray:
        """(N,) bool: corners with a positive-definite covariance (all when none was computed)."""
        if not self.unusable:
            return np.ones(len(self.corners), dtype=bool)
        return np.array([r == "" for r in self.unusable], dtype=bool)

    def as_json(self) -> dict:
        """The JSON form printed by ``edgecal detect``: covariance_px2 is [xx, xy, yy] per corner (px^2),
        null for an unusable corner, which ``unusable`` lists with its reason (never NaN)."""
        out = {
            "name": self.board,
            "copy": self.copy,
            "corners": [[round(float(x), 4), round(float(y), 4)] for x, y in self.corners],
            "ids": [[int(c), int(r)] for c, r in self.ids],
        }
        if self.covariance is not None:
            ok = self.usable()
            out["covariance_px2"] = [[float(f"{c[0, 0]:.4g}"), float(f"{c[0, 1]:.4g}"), float(f"{c[1, 1]:.4g}")]
                                     if good else None for c, good in zip(self.covariance, ok)]
            out["unusable"] = [{"id": [int(i[0]), int(i[1])], "reason": r}
                               for i, r in zip(self.ids, self.unusable) if r]
        return out


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
    quality:     (K,) how cleanly the probe saw each accepted point (probe_quality; empty when not kept).
    """

    candidates: np.ndarray
    accepted: np.ndarray
    directions: np.ndarray
    spacing: np.ndarray
    detections: list[Detection] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    quality: np.ndarray = field(default_factory=lambda: np.zeros(0))


@dataclass(frozen=True)
class CornerPrediction:
    """Where the corners of one board are expected in an image (edgecal.detection.tracking verifies them).

    ids: (N, 2) int64 (col, row) on ``board``; xy: (N, 2) float64 pixels, OpenCV convention.
    """

    board: Board
    ids: np.ndarray
    xy: np.ndarray
