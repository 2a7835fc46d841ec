"""Step 5: sub-pixel localisation of accepted corners.

cv2.cornerSubPix (gradient orthogonality: every gradient in the window is perpendicular to the vector from
the corner) is accurate to ~0.01 px on clean corners when its window holds only this corner's two edges,
so the window follows the local square size: half-width 0.5 x the nearest corner distance, 3..12 px
(smaller windows lose more to noise than they gain in isolation).
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy.spatial import cKDTree

FINAL_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 40, 0.001)
# Grid completion's predictions only need to be good to a few hundredths of a pixel (the probe works at
# that level); each board's corners get the full criteria once at the end. In noisy images cornerSubPix
# rarely reaches 0.001 px and runs all 40 iterations, the bulk of its cost. (The first refinement of the
# accepted points keeps the full criteria: grids grown from coarser seeds went astray on fisheye images.)
SEARCH_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 12, 0.01)


def subpixel_window(spacing: np.ndarray) -> np.ndarray:
    """Half-width of the refinement window for each local square size (pixels)."""
    return np.clip(np.floor(0.5 * np.asarray(spacing)), 3, 12).astype(np.int64)


def refine_corners(smooth: np.ndarray, pts: np.ndarray, spacing: np.ndarray,
                   max_move_px: float | None = None, criteria: tuple = FINAL_CRITERIA) -> np.ndarray:
    """Refined copies of ``pts`` (M, 2); points that move further than ``max_move_px`` (default: half the
    window) keep their start position: the refinement ran away to another structure. ``criteria``:
    cv2.cornerSubPix's termination (SEARCH_CRITERIA for completion's predictions, else the default)."""
    out = np.array(pts, dtype=np.float32).reshape(-1, 1, 2)
    if len(out) == 0:
        return out.reshape(-1, 2).astype(np.float64)
    finite = np.isfinite(out[:, 0]).all(axis=1) & np.isfinite(np.asarray(spacing, np.float64))
    half = np.where(finite, subpixel_window(np.where(finite, spacing, 6.0)), -1)
    h, w = smooth.shape
    for hw in np.unique(half[half > 0]):
        sel = np.nonzero(half == hw)[0]
        # cornerSubPix needs the window inside the image.
        inside = ((out[sel, 0, 0] > hw + 1) & (out[sel, 0, 0] < w - hw - 2)
                  & (out[sel, 0, 1] > hw + 1) & (out[sel, 0, 1] < h - hw - 2))
        sel = sel[inside]
        if len(sel) == 0:
            continue
        block = out[sel].copy()
        cv2.cornerSubPix(smooth, block, (int(hw), int(hw)), (-1, -1), criteria)
        moved = np.linalg.norm(block[:, 0] - out[sel, 0], axis=1)
        good = moved < (max_move_px if max_move_px is not None else max(1.5, 0.5 * hw))
        out[sel[good]] = block[good]
    return out.reshape(-1, 2).astype(np.float64)


def nearest_spacing(pts: np.ndarray) -> np.ndarray:
    """Distance from each point to its nearest other point: the local square size on a board.

    On a steeply slanted board the nearest corner can be a diagonal neighbour, which is why this is taken
    from the points themselves and not from grid labels: windows sized by it never hold two corners.
    """
    if len(pts) < 2:
        return np.full(len(pts), 20.0)
    d, _ = cKDTree(pts).query(pts, k=2)
    return np.clip(d[:, 1], 4.0, 300.0)
