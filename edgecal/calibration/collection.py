"""Choosing calibration views from a stream: is a view sharp, still, and does it add coverage?

Pure functions and one small accumulator (:class:`Coverage`); the ``edgecal collect`` command feeds
them frames. The coverage measures are those of ROS's camera_calibration (cameracalibrator.py), so
that a user who knows its four bars reads ours the same way: for each view of a board,

- X, Y: where the board is across the image (0 = at the left/top border, 1 = at the right/bottom);
- size: sqrt(board area / image area), i.e. how close it is;
- skew: how far the board's corner angle is from a right angle (tilt), 2 |pi/2 - angle|, capped at 1.

A measure's progress is the spread of the kept views over it divided by the spread wanted
(ROS: 0.7, 0.7, 0.4, 0.5), in the left camera of a stereo pair (as ROS); a view is a near-duplicate
when its four measures are within MIN_DISTANCE (L1, as ROS's 0.2) of a kept view's, in every camera.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from edgecal.calibration.types import CornerSet
from edgecal.targets import Board, Target

MEASURES = ("X", "Y", "size", "skew")
WANTED_SPREAD = np.array([0.7, 0.7, 0.4, 0.5])  # ROS camera_calibration's param_ranges
MIN_DISTANCE = 0.2        # L1 distance of the measures below which a view adds nothing (ROS)
STILL_PX = 1.0            # corners moved less than this since the previous frame: the board is still
# Blur: OpenCV advises edge widths "below ~3 px" (10-90 % rise). On renders (edgecal.synth.handheld) a sharp
# board measures ~2 px (after the shear correction), a Gaussian blur of sigma 1 px 3.4 px, of 1.5 px 4.3 px,
# 15 px of motion 10+ px. Big squares may exceed it while still sharp: 8 % of a square.
MAX_EDGE_WIDTH_PX = 3.5
EDGE_WIDTH_PER_SQUARE = 0.08
NO_MEASUREMENT = 9999.0   # what estimateChessboardSharpness returns when it has no profile to measure
MIN_FACE_FRACTION = 0.5   # a box view needs at least this share of every face's corners
MIN_SHARED_CORNERS = 6    # corners seen in two frames to compare their positions


def _outer_corners(cs: CornerSet, board: Board) -> np.ndarray | None:
    """Pixels of the board's four extreme inner corners (0,0), (C-1,0), (C-1,R-1), (0,R-1), or None."""
    index = {(c, r): i for i, (b, c, r) in enumerate(cs.keys) if b == board.name}
    want = [(0, 0), (board.cols - 1, 0), (board.cols - 1, board.rows - 1), (0, board.rows - 1)]
    if not all(k in index for k in want):
        return None
    return cs.image_px[[index[k] for k in want]]


def _cross(u: np.ndarray, v: np.ndarray) -> float:
    """z of the cross product of two 2-D vectors."""
    return float(u[0] * v[1] - u[1] * v[0])


def _angle(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> float:
    """The angle at ``b`` of the triangle a-b-c (radians)."""
    u, v = a - b, c - b
    return math.acos(float(np.clip(u @ v / (np.linalg.norm(u) * np.linalg.norm(v) + 1e-12), -1.0, 1.0)))


def view_measures(cs: CornerSet, target: Target, image_size: tuple[int, int]) -> np.ndarray | None:
    """The four ROS measures (X, Y, size, skew) of one camera's view; None if no board outline is seen.

    With several boards (a box) the measures are taken over all corners: position and size of their
    hull, skew of the largest board seen whole.
    """
    w, h = image_size
    quads = [(b, q) for b in target.boards if (q := _outer_corners(cs, b)) is not None]
    if not len(cs) or (not quads and len(target.boards) == 1):
        return None
    if len(target.boards) == 1:
        pts = quads[0][1]
        area = 0.5 * abs(_cross(pts[1] - pts[0], pts[2] - pts[0]) + _cross(pts[2] - pts[0], pts[3] - pts[0]))
    else:
        pts = cs.image_px
        area = float(cv2.contourArea(cv2.convexHull(pts.astype(np.float32))))
    border = math.sqrt(max(area, 0.0))
    x = min(1.0, max(0.0, (float(np.mean(pts[:, 0])) - border / 2) / max(w - border, 1.0)))
    y = min(1.0, max(0.0, (float(np.mean(pts[:, 1])) - border / 2) / max(h - border, 1.0)))
    size = math.sqrt(area / (w * h))
    skew = 0.0
    if quads:
        q = max(quads, key=lambda bq: cv2.contourArea(bq[1].astype(np.float32)))[1]
        skew = min(1.0, 2.0 * abs(math.pi / 2 - _angle(q[0], q[1], q[2])))
    return np.array([x, y, size, skew])


def board_found(cs: CornerSet, target: Target) -> bool:
    """Whether a view shows enough: a flat board whole, or every face of a box at least MIN_FACE_FRACTION."""
    counts = {b.name: 0 for b in target.boards}
    for b, _, _ in cs.keys:
        counts[b] += 1
    if len(target.boards) == 1:
        return counts[target.boards[0].name] == target.boards[0].n_corners
    return all(counts[b.name] >= MIN_FACE_FRACTION * b.n_corners for b in target.boards)


def edge_width_px(grey: np.ndarray, cs: CornerSet, target: Target) -> float:
    """Black-to-white transition width (px) of the boards seen whole, in the blurrier edge direction
    (cv2.estimateChessboardSharpness), corrected for the board's shear in the image (_shear_sine).

    A blurred or moving board has wide edges. NaN when no board is seen whole (nothing to measure).
    """
    widths = []
    for board in target.boards:
        index = {(c, r): i for i, (b, c, r) in enumerate(cs.keys) if b == board.name}
        if len(index) != board.n_corners:
            continue
        order = [index[(c, r)] for r in range(board.rows) for c in range(board.cols)]
        grid = cs.image_px[order].reshape(board.rows, board.cols, 2)
        pts = grid.astype(np.float32).reshape(-1, 1, 2)
        shear = _shear_sine(grid)
        # both edge directions: motion blur widens only the edges across the motion
        for vertical in (False, True):
            sharpness = cv2.estimateChessboardSharpness(grey, (board.cols, board.rows), pts, vertical=vertical)[0]
            value = np.ravel(sharpness)[0]   # a Scalar: (average edge width, min, max, ...)
            # OpenCV answers 9999 when it cannot measure (small squares): no measurement, not a blur
            if np.isfinite(value) and 0 < value < NO_MEASUREMENT:
                widths.append(float(value) * shear)
    return float(np.max(widths)) if widths else math.nan


def _shear_sine(grid: np.ndarray) -> float:
    """sin of the angle between a board's column and row directions in the image ((rows, cols, 2) corners).

    OpenCV measures each edge on the line from a cell's centre to its neighbour's, which crosses the edges
    of a sheared (strongly tilted) board obliquely: the measured width grows by 1 / sin(angle). On rendered
    sharp box faces 3.76 px at 37 deg, 2.97 px at 47 deg, 2.30 px at 62 deg; times the sine, 2.0-2.3 px.
    """
    u = np.mean(grid[:, 1:] - grid[:, :-1], axis=(0, 1))
    v = np.mean(grid[1:, :] - grid[:-1, :], axis=(0, 1))
    return float(min(1.0, abs(_cross(u, v)) / max(float(np.linalg.norm(u) * np.linalg.norm(v)), 1e-12)))


def square_px(cs: CornerSet) -> float:
    """Median distance (px) between neighbouring corners: the size of a square in the image."""
    index = {k: i for i, k in enumerate(cs.keys)}
    d = [np.linalg.norm(cs.image_px[i] - cs.image_px[index[(b, c + 1, r)]])
         for (b, c, r), i in index.items() if (b, c + 1, r) in index]
    return float(np.median(d)) if d else math.nan


def is_sharp(edge_width: float, square: float) -> bool:
    """Whether edges of ``edge_width`` px are sharp enough on squares of ``square`` px (NaN: cannot say, yes)."""
    if not np.isfinite(edge_width):
        return True
    return edge_width <= max(MAX_EDGE_WIDTH_PX, EDGE_WIDTH_PER_SQUARE * square)


def motion_px(previous: CornerSet | None, current: CornerSet) -> float:
    """Largest movement (px) of a corner seen in both frames; inf when they share too few corners."""
    if previous is None:
        return math.inf
    index = {k: i for i, k in enumerate(previous.keys)}
    pairs = [(index[k], j) for j, k in enumerate(current.keys) if k in index]
    if len(pairs) < MIN_SHARED_CORNERS:
        return math.inf
    a, b = np.array(pairs).T
    return float(np.linalg.norm(previous.image_px[a] - current.image_px[b], axis=1).max())


@dataclass
class Coverage:
    """The measures of the kept views, per camera, and what they still lack."""

    n_cameras: int
    kept: list[np.ndarray] = field(default_factory=list)   # per view: (n_cameras, 4)

    def distance(self, measures: np.ndarray) -> float:
        """L1 distance of a view's measures (n_cameras, 4) to the nearest kept view, in the camera where
        it is largest (a view new to either camera adds something)."""
        if not self.kept:
            return math.inf
        return float(min(np.abs(measures - k).sum(axis=1).max() for k in self.kept))

    def adds(self, measures: np.ndarray) -> bool:
        """Whether a view is more than MIN_DISTANCE from every kept view."""
        return self.distance(measures) > MIN_DISTANCE

    def add(self, measures: np.ndarray) -> None:
        """Keep a view's measures."""
        self.kept.append(np.asarray(measures, dtype=np.float64).reshape(self.n_cameras, 4))

    def progress(self) -> np.ndarray:
        """Per measure (X, Y, size, skew), 0..1: the kept views' spread over the spread wanted.

        Measured in the left (first) camera, as ROS's stereo calibrator does: a board both cameras see
        cannot reach the far side of the right image, so the right camera's spread is always smaller.
        """
        if not self.kept:
            return np.zeros(4)
        k = np.stack(self.kept)[:, 0]   # (views, 4) of the first camera
        return np.minimum((k.max(axis=0) - k.min(axis=0)) / WANTED_SPREAD, 1.0)

    @property
    def complete(self) -> bool:
        """Every measure has the spread wanted."""
        return bool(np.all(self.progress() >= 1.0))

    def missing(self) -> list[str]:
        """What to do next, in words: where the kept views do not reach yet (empty when complete)."""
        if not self.kept:
            return ["show the board"]
        k = np.stack(self.kept)[:, 0]
        lo, hi = k.min(axis=0), k.max(axis=0)
        p = self.progress()
        out = []
        # The spread is wanted around the middle: say which end is short.
        if p[0] < 1:
            out.append("move it further left" if lo[0] > 0.5 - WANTED_SPREAD[0] / 2 else "move it further right")
        if p[1] < 1:
            out.append("move it higher" if lo[1] > 0.5 - WANTED_SPREAD[1] / 2 else "move it lower")
        if p[2] < 1:
            out.append("bring it closer" if hi[2] < 0.2 + WANTED_SPREAD[2] else "move it farther away")
        if p[3] < 1:
            out.append("tilt it more")
        return out
