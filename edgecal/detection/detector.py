"""The chessboard detector: the paper's pipeline end to end, arrays in, detections out.

1. candidates: minimum-eigenvalue local maxima of a lightly smoothed image (noise-adaptive smoothing);
2. circular probe at the paper's radius r_e and at a small radius (squares down to ~8 px), after a cheap
   ring pre-filter: four border directions, 180-degree test, black/white alternation;
3. sub-pixel refinement with a window that follows the local square size, then the probe again at a
   radius adapted to that size (accurate directions for 8..150 px squares);
4. grouping along the directions with the point-to-line distance, verified by cross-ratios;
5. completion of each grid (missed corners predicted and verified) and ids from the target board.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from numba import njit

from edgecal.detection.board_corners import (
    final_corners,
    polish_corners,
    provisional_corners,
    resettle_slid_corners,
    unpolished,
)
from edgecal.detection.candidates import (
    chess_filter,
    chess_ring,
    chess_thresholds,
    dedupe_in_order,
    estimate_noise_sigma,
    half_resolution_noise_sigma,
    min_eigen_candidates,
    noise_response_floor,
    snap_to_saddle,
)
from edgecal.detection.completion import complete_grid, grid_arrays, grid_may_continue, trim_false_edges
from edgecal.detection.corner_covariance import add_board_covariances, covariance_noise_sigma
from edgecal.detection.grouping import group_grids
from edgecal.detection.levels import Level, window_level
from edgecal.detection.ordering import assign_ids, grid_is_regular
from edgecal.detection.params import DetectorParams
from edgecal.detection.probe import (
    EDGE_ACROSS_RAY,
    probe_accepts,
    probe_candidates,
    probe_quality,
    probe_radii,
    probe_reach,
    ring_prefilter_radii,
)
from edgecal.detection.subpixel import SEARCH_CRITERIA, id_grid, nearest_of, nearest_spacing, refine_corners
from edgecal.detection.target_boards import (
    all_boards_found,
    boards_by_size,
    is_full_board,
    note_near_miss,
    number_copies,
)
from edgecal.detection.types import Detection, DetectionDebug
from edgecal.images import as_grey
from edgecal.targets import Target

DEFAULT_PARAMS = DetectorParams()
# Closest two corners of a board may be at half resolution before its corners are not trusted there
# (sub-pixel windows need a few pixels of their own; the full-resolution search decides below this).
MIN_HALF_SPACING_PX = 5.0
# Closest two corners of a board at half resolution from which a line of corners beyond it would be seen
# there too (its squares shrink by less than half from one line to the next), so that a board nothing
# continues at half resolution is not grown at full resolution (see _refine_at_full_resolution).
GROWTH_CHECK_HALF_SPACING_PX = 10.0
# Completion grows a grid up to this many labels per axis whatever the board's size, so that a board that is
# part of a larger regular grid is seen as that grid (and its size said in the note), never as a sub-grid.
GRID_GROWTH_MAX_DIM = 40
# ChESS rings (px) of the candidate filter: 3 px for the smallest squares, 5 px past a blurred corner's blur.
CHESS_RADII_PX = (3.0, 5.0)
# Grey level from which a pixel counts as saturated (8-bit; JPEG ringing keeps some just below 255).
SATURATED_LEVEL = 250
# Boards found at half resolution are refined on a window of the full-resolution image around them: what
# the refinement, completion's one line beyond the board (with the squares beyond it) and the covariances
# sample lies within this many grid steps plus pixels (the probe's largest radius and a refinement window)
# of the outermost corners. Smoothing and gradients then cost the window's area, not the image's.
WINDOW_MARGIN_STEPS = 2.5
WINDOW_MARGIN_PX = 48
# ... and without completion (see _refine_at_full_resolution) this many: the rim check (subpixel.
# _window_reaches_edge) samples the outer squares half a square along the rim beyond a board's last corners,
# the covariances' light field a quarter square diagonally from every corner.
WINDOW_RIM_MARGIN_STEPS = 0.75
# ... plus this many pixels (not WINDOW_MARGIN_PX: no probe reads beyond such a board): a cornerSubPix window
# (half-width at most 12 px) and the X-junction fit's disc (radius at most 12 px) round its outer corners.
WINDOW_RIM_MARGIN_PX = 16
# A corner the search's probe rated no further than this (half-resolution px) from where it ends keeps that
# figure (Detection.quality) instead of being probed again.
QUALITY_REUSE_PX = 0.1
# The full-resolution smoothing's noise per half-resolution noise estimate (1 / pyrDown's gain on white
# noise): the value the smoothing was tuned with (see _search).
SMOOTHING_NOISE_PER_HALF_NOISE = 1.0 / 0.273
_CHESS_RINGS = np.array([np.stack(chess_ring(r)) for r in CHESS_RADII_PX], dtype=np.int64)


def _probe(smooth: np.ndarray, gx: np.ndarray, gy: np.ndarray, pts: np.ndarray, radii: np.ndarray,
           p: DetectorParams, n_angles: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """probe_candidates with the thresholds of ``p`` (``n_angles`` rays, default p.probe_angles)."""
    return probe_candidates(gx, gy, smooth, np.ascontiguousarray(pts, np.float64),
                            np.ascontiguousarray(radii, np.float64), n_angles or p.probe_angles, *_probe_tests(p))


def _probe_tests(p: DetectorParams) -> tuple[float, int, float, float, float, float]:
    """The probe kernels' arguments after the rays (probe_candidates, probe_accepts) from ``p``: the rays'
    inner radius, the edge mode and the thresholds of Eq. (3)-(5)."""
    return (p.probe_inner_radius_px, EDGE_ACROSS_RAY, math.radians(p.angle_diff_max_deg), p.sign_fraction,
            p.min_contrast, p.min_peak_ratio)


def _first_pass(level: Level, cands: np.ndarray, p: DetectorParams) -> np.ndarray:
    """Candidates accepted by the probe at r_e or, failing that, at a small or a large radius.

    Min-eigenvalue maxima sit 1-3 px off an X-corner (the gradient vanishes at the saddle itself), and the
    probe needs to sit on the corner, so every candidate is snapped to its saddle first. In noisy images
    most candidates are noise: a ChESS response above what the image's noise reaches (two rings, for small
    and for large or blurred corners) thins them before the ring pre-filter and the probe look at them.
    """
    smooth, gx, gy = level.smooth, level.gx, level.gy
    # r_e first; a small radius for small squares; a large one for big, blurred or blooming corners.
    radii = (float(p.probe_radius_px), max(p.probe_radius_min_px, 0.5 * p.probe_radius_px),
             min(p.probe_radius_max_px, 2.0 * p.probe_radius_px))
    pts = snap_to_saddle(smooth, cands, 3)
    pts = pts[dedupe_in_order(pts, 0.75)]
    thresholds = chess_thresholds(CHESS_RADII_PX, level.noise_sigma, level.smoothing_sigma,
                                  p.candidate_chess_quantile, p.candidate_chess_min)
    pts = pts[chess_filter(smooth, pts, _CHESS_RINGS, thresholds)]
    # each point tried at the radii in turn (one that keeps it needs no other), all points in one call
    radii_seq = np.array(radii)
    pts = pts[ring_prefilter_radii(smooth, np.ascontiguousarray(pts, np.float64), radii_seq, p.min_contrast)]
    if len(pts) == 0:
        return pts
    # Half the rays suffice to accept or reject; the directions used later come from the second pass.
    accepted = probe_accepts(gx, gy, smooth, np.ascontiguousarray(pts, np.float64), radii_seq,
                             max(16, p.probe_angles // 2), *_probe_tests(p))
    return pts[accepted]


Grid = dict[tuple[int, int], np.ndarray]


def detect_debug(image: np.ndarray, target: Target, params: DetectorParams | None = None) -> DetectionDebug:
    """Detect the target's boards in ``image`` and return every intermediate result (see DetectionDebug).

    Every detection carries its corners' covariances (edgecal.detection.corner_covariance), computed on
    the full-resolution image in one call over all boards.
    """
    p = params or DEFAULT_PARAMS
    grey = as_grey(image)
    debug, level = _search(grey, target, p)
    add_covariances(debug.detections, level, p)
    if not all_boards_found(debug.detections, target) and _blooming(grey, p):
        _add_bloomed_boards(grey, target, p, debug)
    return debug


def _blooming(grey: np.ndarray, p: DetectorParams) -> bool:
    """Whether the image is overexposed enough for white squares to bloom over the black ones' corners
    (a share ``bloom_saturated_fraction`` of the pixels at the top of the range)."""
    step = max(1, min(grey.shape) // 200)  # a sparse sample is plenty for a share of pixels
    return bool((grey[::step, ::step] >= SATURATED_LEVEL).mean() >= p.bloom_saturated_fraction)


def _add_bloomed_boards(grey: np.ndarray, target: Target, p: DetectorParams, debug: DetectionDebug) -> None:
    """Search again in the image eroded by 3x3 and add the boards found there that were missing.

    In an overexposed image white bleeds into black, so two black squares no longer meet at a corner but
    face each other across a white gap: there is no X-junction left for the probe. A grey-level erosion
    (3x3 minimum) closes gaps of up to two pixels and, being symmetric, leaves the saddle of an X-junction
    where it was; the corners are refined (and their covariances taken) on the eroded image.
    """
    eroded = cv2.erode(grey, np.ones((3, 3), np.uint8))
    found = {d.board for d in debug.detections}
    extra, level = _search(eroded, target, p)
    new = [d for d in extra.detections if d.board not in found]
    if not new:
        return
    add_covariances(new, level, p)
    debug.detections.extend(new)
    number_copies(debug.detections)
    debug.notes.append("overexposed: boards found in the image eroded by 3x3 (white bloomed over the corners)")


def add_covariances(detections: list[Detection], level: Level, p: DetectorParams) -> None:
    """Fill in the covariances of ``detections``, corners refined on ``level`` by ``p``'s refiner
    (corner_covariance.add_board_covariances)."""
    add_board_covariances(detections, level.grey, level.smooth, level.smoothing_sigma,
                          covariance_noise_sigma(level.image), p.subpixel_refiner, level.origin)


def _search(grey: np.ndarray, target: Target, p: DetectorParams) -> tuple[DetectionDebug, Level]:
    """The search of detect_debug; also returns the full-resolution level the corners were refined on.

    Large images are searched at half resolution first (a quarter of the pixel work). Boards found there are
    refined at full resolution; grids that fell short of a board there are scaled up and completed at full
    resolution. Only when a board is still missing does the full-resolution search run (the smallest
    squares need it).
    """
    if min(grey.shape) < p.pyramid_min_size_px:
        level = Level(grey)
        debug, grids = _find_grids(level, p)
        _boards_from_grids(level, grids, target, p, debug)
        return debug, level

    half_grey = cv2.pyrDown(grey)
    noise_half = estimate_noise_sigma(half_grey)
    half_level = Level(half_grey, noise_half)
    half, half_grids = _find_grids(half_level, p)
    # Provisional: whatever the half-resolution search finds is refined, checked and rated at full
    # resolution below (or searched for there again), so its corners are not polished here. Its boards are
    # only used when they are all of the target's: each grid names one board at most, so with fewer grids
    # than boards the completion and ordering there would be thrown away (the full-resolution search
    # starts again from the raw grids).
    if len(half_grids) >= len({b.name for b in target.boards}):
        _boards_from_grids(half_level, half_grids, target, p, half, provisional=True)
    # The full-resolution smoothing keeps the value it was tuned with (subpixel accuracy): noise_half / 0.273
    # (pyrDown's gain on white noise), about half the image's noise (see half_resolution_noise_sigma);
    # smoothing for the true noise moved corners of a hard render by up to 7 px.
    smooth_noise = noise_half * SMOOTHING_NOISE_PER_HALF_NOISE
    if all_boards_found(half.detections, target):
        refined = _refine_at_full_resolution(half, half_level, grey, smooth_noise, p)
        if refined is not None:
            return refined
    # The full search's thresholds (candidates, ChESS) are quantiles of the image's noise, so they need the
    # noise itself: half of it let up to 6x the candidates through on noisy frames (bench/live.py's hard
    # sequence: ~5800 per frame, now ~1100; all detections the same).
    level = Level(grey, half_resolution_noise_sigma(grey), smoothing_noise=smooth_noise)
    # pyrDown keeps the even pixels: x_full = 2 x_half.
    debug = DetectionDebug(2.0 * half.candidates, 2.0 * half.accepted, half.directions, 2.0 * half.spacing,
                           quality=half.quality)
    seeds = []
    for grid in half_grids:
        if len(grid) < p.min_grid_corners:
            continue
        xy = 2.0 * np.array(list(grid.values()))
        spacing = nearest_spacing(xy)
        if spacing.min() < 2.0 * MIN_HALF_SPACING_PX:
            continue  # too small at half resolution: leave it to the full-resolution search
        xy = refine_corners(level.smooth, xy, spacing)
        seeds.append(dict(zip(grid.keys(), xy)))
    _boards_from_grids(level, seeds, target, p, debug)
    if all_boards_found(debug.detections, target):
        return debug, level
    # The boards found so far are not searched for again: their areas are left out of the full search.
    full, grids = _find_grids(level, p, exclude=[d.corners for d in debug.detections])
    full.detections = list(debug.detections)
    full.notes = list(debug.notes)
    _boards_from_grids(level, grids, target, p, full)
    return full, level


def _refine_at_full_resolution(half: DetectionDebug, half_level: Level, grey: np.ndarray, noise_sigma: float,
                               p: DetectorParams) -> tuple[DetectionDebug, Level] | None:
    """Boards found at half resolution (on ``half_level``), scaled up (x_full = 2 x_half) and refined at full
    resolution, on a window of ``grey`` around them; also returns that window's level.

    None when a board was too small at half resolution to trust (corners closer than MIN_HALF_SPACING_PX
    there), does not stay regular after refinement or extends beyond its size at full resolution: the
    caller then works at full resolution. ``noise_sigma``: what the window's smoothing is set for (it only
    refines and completes boards: no thresholds on noise there).

    Whether a board may be part of a larger grid is asked at full resolution (completion one line beyond
    it), which needs the window to reach WINDOW_MARGIN_STEPS grid steps beyond the board. Where its
    squares are large at half resolution (GROWTH_CHECK_HALF_SPACING_PX) and completion.grid_may_continue
    sees no corners of a line beyond it there, the board is not grown and the window reaches
    WINDOW_RIM_MARGIN_STEPS beyond it: with large squares the wide margin was most of the window.
    """
    boxes = []
    may_grow = []
    half_spacings = []  # (each board's, used again for its refinement windows below)
    for det in half.detections:
        half_spacings.append(nearest_spacing(det.corners))
        spacing = half_spacings[-1].min()
        if spacing < MIN_HALF_SPACING_PX:
            return None
        may_grow.append(spacing < GROWTH_CHECK_HALF_SPACING_PX or grid_may_continue(
            dict(zip(map(tuple, det.ids.tolist()), det.corners)), half_level.smooth, p))
        steps, margin_px = ((WINDOW_MARGIN_STEPS, WINDOW_MARGIN_PX) if may_grow[-1]
                            else (WINDOW_RIM_MARGIN_STEPS, WINDOW_RIM_MARGIN_PX))
        margin = margin_px + steps * 2.0 * _largest_step(det.corners, det.ids)
        boxes.append(np.concatenate([2.0 * det.corners.min(axis=0) - margin, 2.0 * det.corners.max(axis=0) + margin]))
    box = np.array(boxes)
    level = window_level(grey, noise_sigma, (box[:, 0].min(), box[:, 1].min(), box[:, 2].max(), box[:, 3].max()))
    for det, grows, half_spacing in zip(half.detections, may_grow, half_spacings):
        spacing = 2.0 * half_spacing
        # Half-resolution corners are ~0.5 px off at full resolution: allow the move, to 0.01 px (final_corners
        # polishes to 0.001 px right after: with its criteria here too, the same corners to 6e-4 px, slower).
        xy = refine_corners(level.smooth, 2.0 * det.corners - level.origin, spacing, max_move_px=3.0,
                            criteria=SEARCH_CRITERIA)
        xy = resettle_slid_corners(level.smooth, det.ids, final_corners(level.smooth, xy, det.ids, p), p)
        if not grid_is_regular(xy, det.ids, det.grid[0], det.grid[1], 2 * p.cross_ratio_tolerance):
            return None
        # Half resolution can miss a line of small corners beyond the board: a sub-grid must not pass.
        if grows and len(complete_grid(dict(zip(map(tuple, det.ids.tolist()), xy)), level, GRID_GROWTH_MAX_DIM,
                                       p)) > len(xy):
            return None
        xy, det.xjunction_fitted, det.bend_px, det.xjunction_noise = polish_corners(level.grey, level.smooth, xy,
                                                                                   det.ids, p)
        provisional_xy = det.corners
        det.corners = xy + level.origin
        # rated where the board was found (the half-resolution gradients exist, the window's need not): where
        # the search's probe rated a corner as good as where it ends, that figure, else the probe there
        moved = np.hypot(*(0.5 * det.corners - provisional_xy).T)
        kept = np.where(moved <= QUALITY_REUSE_PX, det.quality, np.nan)
        det.quality = _corner_quality(half_level, 0.5 * det.corners, p, kept)
    return (DetectionDebug(2.0 * half.candidates, 2.0 * half.accepted, half.directions, 2.0 * half.spacing,
                           half.detections, half.notes, half.quality), level)


def _largest_step(corners: np.ndarray, ids: np.ndarray) -> float:
    """The longest distance (px) between neighbouring corners along a board's rows and columns."""
    step = _longest_neighbour_step(np.ascontiguousarray(corners, np.float64), np.ascontiguousarray(ids, np.int64))
    return step if step >= 0.0 else float(nearest_spacing(corners).max())


@njit(cache=True, nogil=True)
def _longest_neighbour_step(corners: np.ndarray, ids: np.ndarray) -> float:
    """_largest_step's longest finite distance between corners (N, 2) whose ids (N, 2: col, row) are
    neighbours along a row or a column; -1 when there is none (one numba pass: its dozen numpy steps cost
    more than the distances)."""
    dense = id_grid(corners, ids, 0, ids.shape[0], 0)[0]
    rows, cols = dense.shape[0], dense.shape[1]
    best = -1.0
    for r in range(rows):
        for c in range(cols):
            for dr, dc in ((1, 0), (0, 1)):
                if r + dr < rows and c + dc < cols:
                    dx = dense[r + dr, c + dc, 0] - dense[r, c, 0]
                    dy = dense[r + dr, c + dc, 1] - dense[r, c, 1]
                    d = math.sqrt(dx * dx + dy * dy)  # np.linalg.norm's sum of two squares
                    if math.isfinite(d) and d > best:
                        best = d
    return best


def _outside_boards(pts: np.ndarray, boards: list[np.ndarray], shape: tuple[int, int]) -> np.ndarray:
    """Which points (M, 2) of an image of ``shape`` lie outside every board's area: the convex hull of its
    corners grown by a quarter square (room for the corners' snapping), as one mask. Not more: another
    board can start just beyond the margin (the faces of a box meet there)."""
    mask = np.zeros(shape, np.uint8)
    for corners in boards:
        hull = cv2.convexHull(corners.astype(np.float32)).reshape(-1, 2).astype(np.float64)
        centre = hull.mean(axis=0)
        grow = 0.25 * float(np.median(nearest_spacing(corners)))
        d = np.linalg.norm(hull - centre, axis=1, keepdims=True)
        grown = centre + (hull - centre) * (d + grow) / np.maximum(d, 1e-9)
        cv2.fillConvexPoly(mask, np.rint(grown).astype(np.int32), 1)
    xy = np.clip(np.rint(pts).astype(np.int64), 0, [shape[1] - 1, shape[0] - 1])
    return mask[xy[:, 1], xy[:, 0]] == 0


def _find_grids(level: Level, p: DetectorParams, exclude: list[np.ndarray] | None = None
                ) -> tuple[DetectionDebug, list[Grid]]:
    """Candidates, probe, sub-pixel and grouping on one level: the accepted points and their raw grids.

    ``exclude``: corners (N, 2) of boards already found; candidates within their areas are dropped.
    """
    smooth, gx, gy = level.smooth, level.gx, level.gy
    floor = noise_response_floor(level.noise_sigma, level.smoothing_sigma, p.candidate_block_size,
                                 p.candidate_noise_quantile)
    cands, _resp = min_eigen_candidates(gx, gy, p.candidate_block_size, p.candidate_quality, p.max_candidates,
                                        floor)
    if exclude:
        cands = cands[_outside_boards(cands, exclude, smooth.shape)]
    debug = DetectionDebug(cands, np.zeros((0, 2)), np.zeros((0, 4)), np.zeros(0))
    pts = _first_pass(level, cands, p)
    if len(pts) < 4:
        return debug, []

    # Sub-pixel with a window from the local square size, then the probe again with its radius adapted.
    spacing = nearest_spacing(pts)
    pts = refine_corners(smooth, pts, spacing)
    pts = pts[dedupe_in_order(pts, 1.0)]
    spacing = nearest_spacing(pts)
    ok, dirs, meas = _probe(smooth, gx, gy, pts, probe_radii(spacing, p), p)
    pts, dirs, meas, spacing = pts[ok], dirs[ok], meas[ok], spacing[ok]
    quality = probe_quality(meas, p)
    debug = DetectionDebug(cands, pts, dirs, spacing, quality=quality)
    if len(pts) < 4:
        return debug, []
    labels, _nbr = group_grids(pts, dirs, spacing, quality, p.line_distance_px, p.reference_spacing_px,
                               p.cross_ratio_tolerance)
    grids = []
    for comp in np.unique(labels[:, 0]):
        members = np.nonzero(labels[:, 0] == comp)[0]
        if comp >= 0 and len(members) >= p.min_grid_corners:
            grids.append(dict(zip(map(tuple, labels[members, 1:3].tolist()), pts[members])))
    return debug, grids


def _boards_from_grids(level: Level, grids: list[Grid], target: Target, p: DetectorParams,
                       debug: DetectionDebug, provisional: bool = False) -> None:
    """Trim, complete, match to the target's boards and number each grid; appends to debug.detections.

    Every grid is grown as far as the image shows a chessboard (up to GRID_GROWTH_MAX_DIM labels per axis),
    not only up to the board's size: a board that is part of a larger regular grid is not the asked board
    (taking a sub-grid would put the board's origin at an arbitrary square), so it gives a note, not a
    detection. Several grids of one board's size all become detections, numbered by ``copy``.

    ``provisional``: the boards are refined again at full resolution (_refine_at_full_resolution), which
    also grows every board by one line to see whether it is part of a larger grid and rates the corners
    the search did not (on this level): here a grid that already is a complete board is not grown, its
    corners keep the search's refinement with the rim pass (provisional_corners) and its quality is the
    search's probe's where a corner is one the search accepted (``debug.quality``), NaN elsewhere.
    """
    smooth = level.smooth
    by_size = boards_by_size(target)
    min_corners = min(b.n_corners for b in target.boards)
    finished = []
    for grid in grids:
        # A grid that already is a complete board needs no trimming: a stray outer line would change its size.
        if not is_full_board(grid, by_size):
            grid = trim_false_edges(grid, smooth, p.min_contrast)
        # Completion is for boards the probe half-saw, not for every fragment of clutter; a complete board
        # is still tried one line further on every side (it may be a sub-grid of a larger one).
        full_board = is_full_board(grid, by_size)
        if (len(grid) >= max(p.min_grid_corners, 0.3 * min_corners) or full_board) \
                and not (provisional and full_board):
            grid = complete_grid(grid, level, GRID_GROWTH_MAX_DIM, p, debug.accepted)
        if len(grid) >= p.min_grid_corners:
            finished.append(grid)
    # Larger grids first, so that a full board wins its name over a fragment.
    finished.sort(key=len, reverse=True)
    used_boards = {d.board for d in debug.detections}
    notes: list[str] = []
    for grid in finished:
        uv, xy = grid_arrays(grid)
        span = uv.max(axis=0) - uv.min(axis=0) + 1
        full = len(uv) == span[0] * span[1]
        boards = by_size.get(frozenset(int(s) for s in span), [])
        if not full or not boards:
            note_near_miss(notes, span, full, len(uv), target)
            continue
        # A named board not yet found takes the grid; when all are, the grid is another copy of the first.
        board = next((b for b in boards if b.name not in used_boards), boards[0])
        ids = assign_ids(uv, xy, smooth, board)
        if ids is None:
            notes.append(f"found a {span[0]}x{span[1]} grid that could not be oriented")
            continue
        # Final sub-pixel pass with the window from the grid's own spacing, then a last sanity check (a
        # provisional board's final pass is at full resolution).
        search_xy = xy
        xy = provisional_corners(smooth, xy, ids) if provisional else resettle_slid_corners(
            smooth, ids, final_corners(smooth, xy, ids, p), p)
        polished = unpolished(xy) if provisional else polish_corners(level.grey, smooth, xy, ids, p)
        # Corners cornerSubPix slid along an edge at a fisheye's rim can make the grid look irregular; the
        # polished ones (the X-junction fit, fitted again from the grid lines where it saw no corner) are
        # asked too (synthetic fisheye views: 1 board in 78 rejected only for them).
        if not (grid_is_regular(xy, ids, board.cols, board.rows, 2 * p.cross_ratio_tolerance) or (
                not provisional and grid_is_regular(polished[0], ids, board.cols, board.rows,
                                                    2 * p.cross_ratio_tolerance))):
            notes.append(f"found a {board.cols}x{board.rows} grid that is not regular (rejected)")
            continue
        xy, fitted, bend, noise = polished
        order = np.lexsort((ids[:, 0], ids[:, 1]))
        quality = (_searched_quality(search_xy, xy, debug) if provisional else _corner_quality(level, xy, p))[order]
        debug.detections.append(Detection(board.name, xy[order], ids[order], quality, (board.cols, board.rows),
                                          xjunction_fitted=fitted[order], bend_px=bend[order],
                                          xjunction_noise=noise[order]))
        used_boards.add(board.name)
    number_copies(debug.detections)
    for note in notes:
        if note not in debug.notes:
            debug.notes.append(note)


def _searched_quality(search_xy: np.ndarray, xy: np.ndarray, debug: DetectionDebug) -> np.ndarray:
    """(N,): for each of a board's corners ``search_xy`` (N, 2) that is one of the search's accepted points
    (debug.accepted, the same position) the quality its probe saw there (debug.quality); NaN for the others
    (completion's) and where the corner has moved since (``xy``; the rim pass: it was rated off the corner)."""
    if not len(debug.quality):
        return np.full(len(xy), np.nan)
    d, j = nearest_of(search_xy, debug.accepted)
    return np.where((d == 0.0) & (xy == search_xy).all(axis=1), debug.quality[np.maximum(j, 0)], np.nan)


def _corner_quality(level: Level, xy: np.ndarray, p: DetectorParams, known: np.ndarray | None = None
                    ) -> np.ndarray:
    """Per corner in [0, 1]: how cleanly the probe sees a chessboard corner there (angle error x contrast);
    ``known`` (N,): figures already taken, kept where finite (only the others are probed)."""
    radii = probe_radii(nearest_spacing(xy), p)
    quality = np.full(len(xy), np.nan) if known is None else np.array(known, dtype=np.float64)
    todo = np.flatnonzero(~np.isfinite(quality))
    if not len(todo):
        return quality
    # (a window that only refines a board needs its gradients nowhere else)
    gx, gy = level.gradients_near(xy[todo], probe_reach(radii[todo], p))
    _ok, _dirs, meas = _probe(level.smooth, gx, gy, xy[todo], radii[todo], p, max(16, p.probe_angles // 2))
    quality[todo] = probe_quality(meas, p)
    return quality


def detect(image: np.ndarray, target: Target, params: DetectorParams | None = None) -> list[Detection]:
    """Find the target's boards in a uint8 grey or BGR image; an image without a board gives []."""
    return detect_debug(image, target, params).detections
