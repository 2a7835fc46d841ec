"""Detection seeded by a prediction: verify the corners of known boards where they are expected.

In a stream the boards move little between frames, and where each corner should be is known from the
last pose (edgecal.pose.predict). Searching the whole image again is then wasted work: this refines each
predicted corner to sub-pixel, lets the probe confirm a chessboard corner there, and keeps a board only
when enough of its corners are confirmed and its squares have the colours its ids say. The checks are
the detector's own (verify_predictions, as for the holes of a grid); what is skipped is the search.

Why a wrong prediction cannot pass as a board: a corner is kept only if the refinement stays within a
quarter of a square of its prediction, so a whole board would have to be predicted about a square off to
lock onto the neighbouring corners, and a shift by one square along a row or column inverts the colour of
every square, which the colour check rejects.

Why a single corner cannot slide off: between the predicted and the found corners of one board the
motion is smooth - over a board and a frame's worth of prediction error, an affine map to a small
fraction of a pixel. A corner that the refinement slid along an edge (a steeply slanted board's thin
squares leave cornerSubPix ill-conditioned along them) breaks that map and is dropped.
"""

from __future__ import annotations

from typing import Sequence

import cv2
import numpy as np

from edgecal.detection.candidates import estimate_noise_sigma, gradients, smooth_image, smoothing_sigma
from edgecal.detection.completion import verify_predictions
from edgecal.detection.params import DetectorParams
from edgecal.detection.subpixel import nearest_spacing, subpixel_window
from edgecal.detection.types import CornerPrediction, Detection
from edgecal.images import as_grey

DEFAULT_PARAMS = DetectorParams()
# Share of a board's predicted corners that must be confirmed for the board to be kept.
MIN_CONFIRMED_FRACTION = 0.5
# Largest distance (px) of a confirmed corner from the affine map that takes the board's predicted corners
# to the confirmed ones; the detector's corners are good to ~0.1 px, a slid corner is off by pixels.
MAX_MOTION_RESIDUAL_PX = 0.5


def board_motion(predicted: np.ndarray, found: np.ndarray, max_residual_px: float = MAX_MOTION_RESIDUAL_PX
                 ) -> tuple[np.ndarray | None, np.ndarray]:
    """The affine map (2x3) from predicted to found corners (M, 2 each) that most of them follow (RANSAC,
    then least squares on the inliers), and which corners follow it to ``max_residual_px``. (None, all
    False) when fewer than 4 corners are given or no map is found."""
    if len(found) < 4:
        return None, np.zeros(len(found), dtype=bool)
    M, _ = cv2.estimateAffine2D(predicted.astype(np.float32), found.astype(np.float32), method=cv2.RANSAC,
                                ransacReprojThreshold=max_residual_px, maxIters=200, confidence=0.999,
                                refineIters=10)
    if M is None:
        return None, np.zeros(len(found), dtype=bool)
    return M, np.linalg.norm(predicted @ M[:, :2].T + M[:, 2] - found, axis=1) <= max_residual_px


def _confirm(smooth: np.ndarray, gx: np.ndarray, gy: np.ndarray, predicted: np.ndarray, spacing: np.ndarray,
             p: DetectorParams) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One board's corners: refined positions, confirmed mask and probe quality (see track_boards).

    A first pass verifies the predictions as they are. When some corners were missed (a prediction more
    than a quarter square off: the first frames have no velocity yet, thin squares of a slanted board),
    the board's motion fitted to the confirmed ones moves the missed predictions and they are verified once more.
    """
    pinned = np.ones(len(predicted), dtype=bool)
    refined, good, quality = verify_predictions(smooth, gx, gy, predicted, spacing, p, pinned)
    idx = np.nonzero(good)[0]
    M, follows = board_motion(predicted[idx], refined[idx])
    good[idx[~follows]] = False
    missed = np.nonzero(~good)[0]
    if M is None or not len(missed):
        return refined, good, quality
    moved = np.ascontiguousarray(predicted[missed] @ M[:, :2].T + M[:, 2])
    r2, g2, q2 = verify_predictions(smooth, gx, gy, moved, spacing[missed], p, pinned[missed])
    refined[missed], good[missed], quality[missed] = r2, g2, q2
    idx = np.nonzero(good)[0]
    _M, follows = board_motion(predicted[idx], refined[idx])
    good[idx[~follows]] = False
    return refined, good, quality


def square_colours_match(ids: np.ndarray, xy: np.ndarray, smooth: np.ndarray, min_contrast: float) -> bool:
    """Whether the squares framed by confirmed corners have the colours their ids imply.

    The square whose lowest corner is (col, row) is black when col + row is even (docs/conventions.md).
    Needs at least one square of each colour with all four corners confirmed; the dark ones must be
    darker than the light ones by ``min_contrast`` on average and each square on its own side of the
    midpoint between the two means.
    """
    ids = np.asarray(ids, dtype=np.int64)
    if len(ids) < 4:
        return False
    lo = ids.min(axis=0)
    span = ids.max(axis=0) - lo + 1
    grid = np.full((span[1], span[0], 2), np.nan)
    grid[ids[:, 1] - lo[1], ids[:, 0] - lo[0]] = xy
    centres = 0.25 * (grid[:-1, :-1] + grid[:-1, 1:] + grid[1:, :-1] + grid[1:, 1:])
    rows, cols = np.nonzero(np.isfinite(centres).all(axis=2))
    h, w = smooth.shape
    xi = np.rint(centres[rows, cols, 0]).astype(np.int64)
    yi = np.rint(centres[rows, cols, 1]).astype(np.int64)
    inside = (xi >= 1) & (xi < w - 1) & (yi >= 1) & (yi < h - 1)
    rows, cols, xi, yi = rows[inside], cols[inside], xi[inside], yi[inside]
    value = sum(smooth[yi + dy, xi + dx] for dy in (-1, 0, 1) for dx in (-1, 0, 1)) / 9.0
    black = (rows + lo[1] + cols + lo[0]) % 2 == 0
    dark, light = value[black], value[~black]
    if not dark.size or not light.size:
        return False
    mid = 0.5 * (dark.mean() + light.mean())
    return bool(light.mean() - dark.mean() >= min_contrast and dark.max() < mid < light.min())


def track_boards(image: np.ndarray, predictions: Sequence[CornerPrediction],
                 params: DetectorParams | None = None) -> list[Detection]:
    """The predicted boards that are really there, corners refined to sub-pixel (OpenCV pixel convention).

    Only the image region around the predictions is processed. A corner is confirmed when the probe sees a
    chessboard corner near its prediction and it follows the board's motion (board_motion). A board is
    kept when at least MIN_CONFIRMED_FRACTION of its predicted corners (and no fewer than 4) are confirmed
    and its squares' colours match its ids; its Detection holds the confirmed corners (``complete`` when they are all of
    the board). Boards not confirmed are left out: the caller decides whether to search the image.
    """
    p = params or DEFAULT_PARAMS
    predictions = [pr for pr in predictions if len(pr.ids) >= 4]
    if not predictions:
        return []
    grey = as_grey(image)
    h, w = grey.shape
    spacing = [nearest_spacing(pr.xy) for pr in predictions]
    all_xy = np.concatenate([pr.xy for pr in predictions])
    all_spacing = np.concatenate(spacing)
    reach = max(float(subpixel_window(all_spacing).max()),
                float(np.clip(p.probe_radius_per_spacing * all_spacing, p.probe_radius_min_px,
                              p.probe_radius_max_px).max()))
    margin = int(np.ceil(reach)) + 4
    x0, y0 = (max(0, int(np.floor(v)) - margin) for v in all_xy.min(axis=0))
    x1 = min(w, int(np.ceil(all_xy[:, 0].max())) + margin + 1)
    y1 = min(h, int(np.ceil(all_xy[:, 1].max())) + margin + 1)
    if x1 - x0 < 8 or y1 - y0 < 8:
        return []
    crop = grey[y0:y1, x0:x1]
    smooth = smooth_image(crop, smoothing_sigma(estimate_noise_sigma(crop)))
    gx, gy = gradients(smooth)
    offset = np.array([x0, y0], dtype=np.float64)

    found = []
    for pr, sp in zip(predictions, spacing):
        local = np.ascontiguousarray(pr.xy - offset)
        refined, good, quality = _confirm(smooth, gx, gy, local, sp, p)
        if good.sum() < max(4, MIN_CONFIRMED_FRACTION * len(local)):
            continue
        ids, xy = pr.ids[good], refined[good]
        if not square_colours_match(ids, xy, smooth, p.min_contrast):
            continue
        order = np.lexsort((ids[:, 0], ids[:, 1]))
        board = pr.board
        found.append(Detection(board.name, xy[order] + offset, ids[order], quality[good][order],
                               (board.cols, board.rows), complete=len(ids) == board.n_corners))
    return found
