"""Detection seeded by a prediction: verify the corners of known boards where they are expected.

In a stream the boards move little between frames, and where each corner should be is known from the
last pose (edgecal.pose.predict). Searching the whole image again is then wasted work: this refines each
predicted corner to sub-pixel, lets the probe confirm a chessboard corner there, and keeps a board only
when enough of its corners are confirmed and its squares have the colours its ids say. The checks are
the detector's own (verify_predictions, as for the holes of a grid); what is skipped is the search.

Why a wrong prediction cannot pass as a board: a corner is kept only if the refinement stays within a
quarter of a square of its prediction, so a whole board would have to be predicted about a square off to
lock onto the neighbouring corners. A shift by one square along a row or column inverts the colour of
every square, which the colour check rejects; a diagonal shift keeps the colours but leaves real corners
one square beyond one side of the board, which the border check rejects.

Why a single corner cannot slide off: between the predicted and the found corners of one board the
motion is smooth - over a board and a frame's worth of prediction error, an affine map to a small
fraction of a pixel. A corner that the refinement slid along an edge (a steeply slanted board's thin
squares leave cornerSubPix ill-conditioned along them) breaks that map and is dropped.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from edgecal.detection.board_corners import polish_corners
from edgecal.detection.candidates import estimate_noise_sigma
from edgecal.detection.completion import verify_predictions
from edgecal.detection.corner_covariance import add_board_covariances, covariance_noise_sigma
from edgecal.detection.detector import WINDOW_MARGIN_PX, detect
from edgecal.detection.levels import Level
from edgecal.detection.params import DetectorParams
from edgecal.detection.probe import probe_radii
from edgecal.detection.subpixel import (
    nearest_spacing,
    on_board_rim,
    refine_rim,
    saddle_refine,
    subpixel_window,
    window_spacing,
)
from edgecal.detection.types import CornerPrediction, Detection
from edgecal.images import as_grey
from edgecal.targets import Target

DEFAULT_PARAMS = DetectorParams()
# Share of a board's predicted corners that must be confirmed for the board to be kept.
MIN_CONFIRMED_FRACTION = 0.5
# Largest distance (px) of a confirmed corner from the affine map that takes the board's predicted corners
# to the confirmed ones; the detector's corners are good to ~0.1 px, a slid corner is off by pixels. In
# noisy images the bound grows with the corners' own scatter, up to MAX_NOISY_MOTION_RESIDUAL_PX.
MAX_MOTION_RESIDUAL_PX = 0.5
MAX_NOISY_MOTION_RESIDUAL_PX = 1.2
# search_near's window: the predicted corners' bounding box grown by this many of the boards' largest
# square sizes (one square beyond each board for completion and the border checks, the rest for a
# prediction a lost track has got wrong) plus detector.WINDOW_MARGIN_PX (probe rings, refinement windows).
NEAR_MARGIN_SQUARES = 1.5
# A window larger than this share of the image is not worth it: the image is searched in full instead.
NEAR_MAX_AREA_FRACTION = 0.6


def board_motion(predicted: np.ndarray, found: np.ndarray, max_residual_px: float = MAX_MOTION_RESIDUAL_PX
                 ) -> tuple[np.ndarray | None, np.ndarray]:
    """The affine map (2x3) from predicted to found corners (M, 2 each) that most of them follow (RANSAC,
    then least squares on the inliers), and which corners follow it: to ``max_residual_px``, or in a noisy
    image to 3 median residuals, at most MAX_NOISY_MOTION_RESIDUAL_PX. (None, all False) when fewer than 4
    corners are given or no map is found."""
    if len(found) < 4:
        return None, np.zeros(len(found), dtype=bool)
    M, _ = cv2.estimateAffine2D(predicted.astype(np.float32), found.astype(np.float32), method=cv2.RANSAC,
                                ransacReprojThreshold=max_residual_px, maxIters=200, confidence=0.999,
                                refineIters=10)
    if M is None:
        return None, np.zeros(len(found), dtype=bool)
    d = predicted @ M[:, :2].T + M[:, 2] - found
    residual = np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1])     # np.linalg.norm's sums, at a third of its cost
    # In noisy images the corners themselves scatter by a few tenths of a pixel: the bound follows that
    # scatter (3 median residuals, ~3.5 sigma), capped where a slid corner is still far out.
    bound = min(max(max_residual_px, 3.0 * _median(residual)), MAX_NOISY_MOTION_RESIDUAL_PX)
    return M, residual <= bound


def _median(values: np.ndarray) -> float:
    """np.median of a short 1-D array (the same number: the middle value, or the mean of the middle two),
    without its generic machinery (~15 us a call; board_motion makes a dozen a frame)."""
    v = np.sort(values)
    n = len(v)
    if not n or np.isnan(v[-1]):          # sorted last; np.median is NaN then too
        return float("nan")
    return float(v[n // 2]) if n % 2 else float((v[n // 2 - 1] + v[n // 2]) / 2.0)


# Row and column offsets of a 3x3 neighbourhood, row by row (square_colours_match).
_NINE_DY = np.repeat(np.arange(-1, 2), 3)
_NINE_DX = np.tile(np.arange(-1, 2), 3)


def _dense_grid(ids: np.ndarray, xy: np.ndarray, lo: np.ndarray, cols: int, rows: int) -> np.ndarray:
    """(rows, cols, 2) pixel array holding ``xy`` at (col, row) = ids - lo, NaN where no corner is."""
    grid = np.full((rows, cols, 2), np.nan)
    grid[ids[:, 1] - lo[1], ids[:, 0] - lo[0]] = xy
    return grid


def square_colours_match(ids: np.ndarray, xy: np.ndarray, smooth: np.ndarray, min_contrast: float) -> bool:
    """Whether the squares framed by confirmed corners have the colours their ids imply.

    The square whose lowest corner is (col, row) is black when col + row is even (docs/conventions.md).
    Squares are compared with their neighbours (sharing an edge), not with one global threshold, so uneven
    light across the board does not matter: at least one such pair is needed, the square the ids call
    black must be the darker one in 90 % of the pairs, and darker by ``min_contrast`` on average. A
    labelling one square off along a row or column inverts every pair.
    """
    ids = np.asarray(ids, dtype=np.int64)
    if len(ids) < 4:
        return False
    lo = ids.min(axis=0)
    span = ids.max(axis=0) - lo + 1
    grid = _dense_grid(ids, xy, lo, span[0], span[1])
    centres = 0.25 * (grid[:-1, :-1] + grid[:-1, 1:] + grid[1:, :-1] + grid[1:, 1:])
    rows, cols = np.nonzero(np.isfinite(centres).all(axis=2))
    h, w = smooth.shape
    xi = np.rint(centres[rows, cols, 0]).astype(np.int64)
    yi = np.rint(centres[rows, cols, 1]).astype(np.int64)
    inside = (xi >= 1) & (xi < w - 1) & (yi >= 1) & (yi < h - 1)
    rows, cols, xi, yi = rows[inside], cols[inside], xi[inside], yi[inside]
    value = np.full(centres.shape[:2], np.nan)
    # The 3x3 mean around each centre: one gather of the nine samples, summed in the order (dy, dx) row by row
    # (the same float32 sums as nine separate gathers, at a ninth of the indexing).
    nine = smooth[yi[:, None] + _NINE_DY, xi[:, None] + _NINE_DX]
    total = nine[:, 0].copy()
    for k in range(1, 9):
        total += nine[:, k]
    value[rows, cols] = total / 9.0
    # Light minus dark for every pair of neighbouring squares, dark being the one whose ids say black.
    black = (np.add.outer(np.arange(value.shape[0]) + lo[1], np.arange(value.shape[1]) + lo[0]) % 2) == 0
    sign = np.where(black, -1.0, 1.0)
    diffs = np.concatenate([((value[:, 1:] - value[:, :-1]) * sign[:, 1:]).ravel(),
                            ((value[1:, :] - value[:-1, :]) * sign[1:, :]).ravel()])
    diffs = diffs[np.isfinite(diffs)]
    if not diffs.size:
        return False
    # np.mean's numbers (the same sums over the same count) without its overhead
    return bool(np.count_nonzero(diffs > 0) / diffs.size >= 0.9 and diffs.sum() / diffs.size >= min_contrast)


def beyond_border(ids: np.ndarray, xy: np.ndarray, cols: int, rows: int, per_side: int = 3
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Where corners one square beyond each side of the board would be, extrapolated from the two
    outermost confirmed corners of up to ``per_side`` rows or columns spread along the side (a labelling
    one square off shifts whole sides, so a few points tell): (K, 2) points and (K,) side numbers 0..3
    (col -1, col ``cols``, row -1, row ``rows``). On the real board these points are its margin."""
    if cols < 2 or rows < 2:
        return np.zeros((0, 2)), np.zeros(0, dtype=np.int64)
    grid = _dense_grid(ids, xy, np.zeros(2, dtype=np.int64), cols, rows)
    sides = [(grid[:, 0], grid[:, 1]), (grid[:, -1], grid[:, -2]), (grid[0, :], grid[1, :]), (grid[-1, :], grid[-2, :])]
    points, labels = [], []
    for k, (edge, inner) in enumerate(sides):
        ext = 2.0 * edge - inner
        ext = ext[np.isfinite(ext).all(axis=1)]
        if len(ext) > per_side:
            ext = ext[np.linspace(0, len(ext) - 1, per_side).round().astype(np.int64)]
        points.append(ext)
        labels.append(np.full(len(ext), k))
    return np.concatenate(points), np.concatenate(labels)


def slipped_sides(corner: np.ndarray, sides: np.ndarray) -> bool:
    """Whether corners were found one square beyond a side of the board (``corner`` per point of
    beyond_border, ``sides`` its side): at least two on one side and half of those looked at there. The
    board's corners were then labelled one square off, e.g. a prediction more than a square wrong that
    landed on the diagonal neighbours (the square colours cannot tell that shift)."""
    for k in range(4):
        on_side = sides == k
        if corner[on_side].sum() >= max(2, 0.5 * on_side.sum()):
            return True
    return False


def _keep_following(predicted: np.ndarray, refined: np.ndarray, good: np.ndarray) -> np.ndarray | None:
    """Un-confirm (in ``good``, in place) the confirmed corners that do not follow the board's motion;
    returns that motion (board_motion's affine map, None when there is none)."""
    idx = np.nonzero(good)[0]
    M, follows = board_motion(predicted[idx], refined[idx])
    good[idx[~follows]] = False
    return M


def _verify_boards(level: Level, points: list[np.ndarray], spacing: list[np.ndarray], p: DetectorParams,
                   pinned: bool, rim_window: bool = False) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """verify_predictions over the points of several boards in one call; (refined, good, quality) per board.
    ``rim_window``: the points lie on their boards' rims and are refined with the rim's window."""
    if not sum(len(x) for x in points):
        return [(np.zeros((0, 2)), np.zeros(0, dtype=bool), np.zeros(0)) for _ in points]
    cat = np.ascontiguousarray(np.concatenate(points))
    sizes = np.concatenate(spacing)
    window = window_spacing(sizes, np.ones(len(sizes), dtype=bool)) if rim_window else None
    refined, good, quality = verify_predictions(level, cat, sizes, p, np.full(len(cat), pinned),
                                                window=window)
    bounds = np.cumsum([0] + [len(x) for x in points])
    return [(refined[i:j], good[i:j], quality[i:j]) for i, j in zip(bounds[:-1], bounds[1:])]


@dataclass(frozen=True)
class TrackedBoards:
    """What verifying one image's predicted corners gave (verify_boards).

    detections: the boards confirmed (track_boards' result).
    in_place:   names of boards not confirmed whose prediction still held: enough of their corners were
                confirmed where predicted, moving with the board, but too few whole squares were framed by
                confirmed corners for the colour check (in a noisy image the confirmed corners are scattered
                over the board); with the others placed by the board's motion the squares' colours match
                the ids. Such a board is where it was predicted, labelled right: a search around the
                prediction looks at the same corners, so it is not worth one (FramePipeline._tracked_pose).
    """

    detections: list[Detection]
    in_place: frozenset[str] = frozenset()


def track_boards(image: np.ndarray, predictions: Sequence[CornerPrediction],
                 params: DetectorParams | None = None) -> list[Detection]:
    """The predicted boards that are really there, corners refined to sub-pixel (OpenCV pixel convention).

    Only the image region around the predictions is processed. A corner is confirmed when the probe sees a
    chessboard corner near its prediction and it follows the board's motion (board_motion). A board is
    kept when at least MIN_CONFIRMED_FRACTION of its predicted corners (and no fewer than 4) are confirmed,
    its squares' colours match its ids and there are no corners one square beyond its sides; its Detection
    holds the confirmed corners (``complete`` when they are all of the board). Boards not confirmed are
    left out: the caller decides whether to search the image (verify_boards also says which of them held
    their prediction).
    """
    return verify_boards(image, predictions, params).detections


def verify_boards(image: np.ndarray, predictions: Sequence[CornerPrediction],
                  params: DetectorParams | None = None) -> TrackedBoards:
    """track_boards' detections, and the boards not confirmed that are where they were predicted
    (TrackedBoards.in_place)."""
    p = params or DEFAULT_PARAMS
    predictions = [pr for pr in predictions if len(pr.ids) >= 4]
    if not predictions:
        return TrackedBoards([])
    grey = as_grey(image)
    h, w = grey.shape
    spacing = [nearest_spacing(pr.xy) for pr in predictions]
    all_xy = np.concatenate([pr.xy for pr in predictions])
    all_spacing = np.concatenate(spacing)
    reach = max(float(subpixel_window(all_spacing).max()), float(probe_radii(all_spacing, p).max()))
    # The crop also holds one square beyond every board (the border check looks there).
    margin = int(np.ceil(reach + all_spacing.max())) + 4
    x0, y0 = (max(0, int(np.floor(v)) - margin) for v in all_xy.min(axis=0))
    x1 = min(w, int(np.ceil(all_xy[:, 0].max())) + margin + 1)
    y1 = min(h, int(np.ceil(all_xy[:, 1].max())) + margin + 1)
    if x1 - x0 < 8 or y1 - y0 < 8:
        return TrackedBoards([])
    crop = grey[y0:y1, x0:x1]
    # Noise from every 6th pixel: the crop around a robot's boards still gives thousands of samples.
    level = Level(crop, estimate_noise_sigma(crop, stride=6))
    smooth, sigma = level.smooth, level.smoothing_sigma
    offset = np.array([x0, y0], dtype=np.float64)

    local = [np.ascontiguousarray(pr.xy - offset) for pr in predictions]
    # Pass 1: every prediction as it is, all boards in one call.
    results = [list(r) for r in _verify_boards(level, local, spacing, p, True)]
    motions = [_keep_following(pred, res[0], res[1]) for pred, res in zip(local, results)]
    # each board's motion fitted to its corners as last confirmed (passes 2 and 3 refit it)
    last_motions = list(motions)
    # Pass 2: predictions pass 1 missed (more than a quarter square off: the first frames have no velocity
    # yet, a slanted board's squares are thin), moved by their board's motion fitted to the confirmed ones.
    retry = [k for k, (M, res) in enumerate(zip(motions, results)) if M is not None and not res[1].all()]
    missed = [np.nonzero(~results[k][1])[0] for k in retry]
    # retry holds only boards with a motion
    moved = [local[k][m] @ motions[k][:, :2].T + motions[k][:, 2] for k, m in zip(retry, missed)]  # type: ignore[index]
    again_all = _verify_boards(level, moved, [spacing[k][m] for k, m in zip(retry, missed)], p, True)
    for k, m, again in zip(retry, missed, again_all):
        for part in range(3):
            results[k][part][m] = again[part]
        last_motions[k] = _keep_following(local[k], results[k][0], results[k][1])
    # Pass 3: rim corners still missed, with the rim's smaller window: where a board's outer squares are cut
    # short the full window reaches its edge and pulls the corner outwards (subpixel.window_spacing).
    rim_missed = [np.flatnonzero(~res[1] & on_board_rim(pr.ids, (pr.board.cols, pr.board.rows)))
                  for pr, res in zip(predictions, results)]
    starts = [(local[k] if motions[k] is None else local[k] @ motions[k][:, :2].T + motions[k][:, 2])[m]  # type: ignore[index]
              for k, m in enumerate(rim_missed)]
    rim_again = _verify_boards(level, starts, [spacing[k][m] for k, m in enumerate(rim_missed)], p, True,
                               rim_window=True)
    for k, (m, again) in enumerate(zip(rim_missed, rim_again)):
        if len(m):
            for part in range(3):
                results[k][part][m] = again[part]
            last_motions[k] = _keep_following(local[k], results[k][0], results[k][1])
    # Boards with enough confirmed corners whose squares have the right colours...
    kept, in_place = [], set()
    for pr, sp, (refined, good, quality), pred, M in zip(predictions, spacing, results, local, last_motions):
        if good.sum() < max(4, MIN_CONFIRMED_FRACTION * len(good)):
            continue
        if square_colours_match(pr.ids[good], refined[good], smooth, p.min_contrast):
            kept.append((pr, pr.ids[good], refined[good], quality[good], float(np.median(sp)), sp[good]))
        elif M is not None and square_colours_match(
                pr.ids, np.where(good[:, None], refined, pred @ M[:, :2].T + M[:, 2]), smooth, p.min_contrast):
            in_place.add(pr.board.name)
    # ... and no corners one square beyond their sides (all boards in one call; probed at half the square
    # size, a ring of 0.3 squares: beyond the outer corners lie the margin and, a third of a square
    # further, whatever the board is glued on - a full-size ring could see four sectors alternate there).
    beyond = [beyond_border(ids, xy, pr.board.cols, pr.board.rows) for pr, ids, xy, _q, _s, _sp in kept]
    checks = _verify_boards(level, [b[0] for b in beyond],
                            [np.full(len(b[0]), 0.5 * k[4]) for b, k in zip(beyond, kept)], p, False)
    found, windows = [], []
    for (pr, ids, xy, quality, _s, sp), (_pts, sides), (_r, corner, _q) in zip(kept, beyond, checks):
        if slipped_sides(corner, sides):
            continue
        # the rim corners once more with a window that leaves out the board's edge (cut outer squares)
        xy, window = refine_rim(smooth, xy, ids, sp, every=True)
        # then the refiner of the full search (the saddle fit, the X-junction fit on the raw crop): tracked
        # corners as accurate as searched ones (cornerSubPix alone left the hard sequence's tracked pose ~3x
        # less accurate than the searched one)
        if p.subpixel_refiner != "cornersubpix":
            xy = saddle_refine(smooth, xy, window)
        xy, fitted, bend, noise = polish_corners(crop, smooth, xy, ids, p)
        order = np.lexsort((ids[:, 0], ids[:, 1]))
        board = pr.board
        found.append(Detection(board.name, xy[order] + offset, ids[order], quality[order],
                               (board.cols, board.rows), complete=len(ids) == board.n_corners,
                               xjunction_fitted=fitted[order], bend_px=bend[order],
                               xjunction_noise=noise[order]))
        windows.append(sp[order])
    # The corners' covariances, all boards in one call, on the crop they were refined on; the noise from the
    # whole image: in a crop the board fills, its edges inflate the half-resolution estimate up to 2x.
    add_board_covariances(found, crop, smooth, sigma, covariance_noise_sigma(grey), p.subpixel_refiner, offset,
                          windows)
    return TrackedBoards(found, frozenset(in_place))


def near_window(predictions: Sequence[CornerPrediction], shape: tuple[int, int]) -> tuple[int, int, int, int] | None:
    """(x0, y0, x1, y1) of the image region search_near searches for ``predictions`` in an image of ``shape``
    (rows, cols): the predicted corners' bounding box grown by NEAR_MARGIN_SQUARES of the largest square
    plus WINDOW_MARGIN_PX, clipped to the image. None when nothing is predicted or the region would cover
    more than NEAR_MAX_AREA_FRACTION of the image (a full search then costs about the same)."""
    predictions = [pr for pr in predictions if len(pr.ids)]
    if not predictions:
        return None
    h, w = shape
    xy = np.concatenate([pr.xy for pr in predictions])
    step = max(float(nearest_spacing(pr.xy).max()) if len(pr.xy) > 1 else 0.0 for pr in predictions)
    margin = NEAR_MARGIN_SQUARES * step + WINDOW_MARGIN_PX
    x0, y0 = (max(0, int(np.floor(v - margin))) for v in xy.min(axis=0))
    x1 = min(w, int(np.ceil(xy[:, 0].max() + margin)) + 1)
    y1 = min(h, int(np.ceil(xy[:, 1].max() + margin)) + 1)
    if x1 <= x0 or y1 <= y0 or (x1 - x0) * (y1 - y0) > NEAR_MAX_AREA_FRACTION * w * h:
        return None
    return x0, y0, x1, y1


def search_near(image: np.ndarray, predictions: Sequence[CornerPrediction], target: Target,
                params: DetectorParams | None = None) -> list[Detection] | None:
    """The target's boards found by the full search (detector.detect, all its checks) in the region
    around the predicted corners (near_window), corners in the whole image's pixels; None when there is
    no such region (nothing predicted, or it would be most of the image: search the image instead).

    For a track that verification lost (a board the prediction missed by more than its checks allow, too
    few corners confirmed in a noisy frame): the boards are still near where they were a frame ago, and
    searching there costs the region's area, not the image's. Boards outside the region are not seen: the
    caller searches the whole image when the result does not do."""
    grey = as_grey(image)
    window = near_window(predictions, grey.shape[:2])
    if window is None:
        return None
    x0, y0, x1, y1 = window
    found = detect(np.ascontiguousarray(grey[y0:y1, x0:x1]), target, params)
    offset = np.array([x0, y0], dtype=np.float64)
    for det in found:
        det.corners = det.corners + offset
    return found
