"""Completing a grid: corners the probe missed are predicted from their neighbours and verified.

Noise, glare or a shadow can make the probe reject a few true corners, which leaves holes (or a missing
outer row) in a grid. Each missing label is predicted by a homography fitted to the nearby labelled
corners (local, so lens distortion does not matter), refined to sub-pixel, and accepted only if the probe
confirms a chessboard corner there and the refinement stayed near the prediction. Rows and columns are
added at the grid's sides the same way, so a grid grows up to the board's edge and stops at its margin.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from edgecal.detection.params import DetectorParams
from edgecal.detection.probe import EDGE_ACROSS_RAY, probe_candidates
from edgecal.detection.subpixel import refine_corners


def _predict(grid: dict[tuple[int, int], np.ndarray], u: int, v: int, reach: int = 2) -> np.ndarray | None:
    """Predict the image position of label (u, v) from labelled corners within ``reach`` labels."""
    src, dst = [], []
    for (a, b), xy in grid.items():
        if abs(a - u) <= reach and abs(b - v) <= reach:
            src.append((a, b))
            dst.append(xy)
    if len(src) < 4:
        return None
    src_a = np.asarray(src, np.float64)
    if len(np.unique(src_a[:, 0])) < 2 or len(np.unique(src_a[:, 1])) < 2:
        return None
    h, _ = cv2.findHomography(src_a, np.asarray(dst, np.float64), 0)
    if h is None:
        return None
    p = h @ np.array([u, v, 1.0])
    if abs(p[2]) < 1e-12:
        return None
    return p[:2] / p[2]


def _local_spacing(grid: dict[tuple[int, int], np.ndarray], u: int, v: int, xy: np.ndarray) -> float:
    """Mean distance between label-adjacent corners near (u, v), in pixels."""
    dists = []
    for (a, b), p in grid.items():
        if abs(a - u) <= 2 and abs(b - v) <= 2:
            for da, db in ((1, 0), (0, 1)):
                q = grid.get((a + da, b + db))
                if q is not None:
                    dists.append(float(np.hypot(*(q - p))))
    return float(np.median(dists)) if dists else 10.0


def _verify(smooth: np.ndarray, gx: np.ndarray, gy: np.ndarray, preds: np.ndarray, spacing: np.ndarray,
            params: DetectorParams) -> tuple[np.ndarray, np.ndarray]:
    """Refine predicted corners and keep those the probe confirms near their prediction."""
    h, w = smooth.shape
    inside = ((preds[:, 0] > 2) & (preds[:, 1] > 2) & (preds[:, 0] < w - 3) & (preds[:, 1] < h - 3))
    refined = preds.copy()
    if inside.any():
        refined[inside] = refine_corners(smooth, preds[inside], spacing[inside])
    radii = np.clip(params.probe_radius_per_spacing * spacing, params.probe_radius_min_px,
                    params.probe_radius_max_px)
    ok, _dirs, _meas = probe_candidates(
        gx, gy, smooth, np.ascontiguousarray(refined), np.ascontiguousarray(radii), params.probe_angles,
        params.probe_inner_radius_px, EDGE_ACROSS_RAY, math.radians(params.angle_diff_max_deg),
        params.sign_fraction, params.min_contrast * 0.5, params.min_peak_ratio * 0.8)
    near = np.linalg.norm(refined - preds, axis=1) < 0.25 * spacing
    return refined, ok & near & inside


def complete_grid(grid: dict[tuple[int, int], np.ndarray], smooth: np.ndarray, gx: np.ndarray,
                  gy: np.ndarray, max_dim: int, params: DetectorParams) -> dict[tuple[int, int], np.ndarray]:
    """Fill holes and grow the grid at its sides (up to ``max_dim`` labels per axis); returns a new dict."""
    grid = dict(grid)
    for _ in range(2 * max_dim + 2):
        us = [u for u, _ in grid]
        vs = [v for _, v in grid]
        u0, u1, v0, v1 = min(us), max(us), min(vs), max(vs)
        todo = [(u, v) for u in range(u0, u1 + 1) for v in range(v0, v1 + 1) if (u, v) not in grid]
        side_lines = []
        if u1 - u0 + 1 < max_dim:
            side_lines += [[(u0 - 1, v) for v in range(v0, v1 + 1)], [(u1 + 1, v) for v in range(v0, v1 + 1)]]
        if v1 - v0 + 1 < max_dim:
            side_lines += [[(u, v0 - 1) for u in range(u0, u1 + 1)], [(u, v1 + 1) for u in range(u0, u1 + 1)]]
        added = False
        for labels in [todo] + side_lines:
            if not labels:
                continue
            preds, keys, spac = [], [], []
            for (u, v) in labels:
                p = _predict(grid, u, v)
                if p is not None:
                    preds.append(p)
                    keys.append((u, v))
                    spac.append(_local_spacing(grid, u, v, p))
            if not preds:
                continue
            refined, good = _verify(smooth, gx, gy, np.asarray(preds), np.asarray(spac), params)
            # A side line is taken only when most of it is confirmed (a board's margin confirms nothing).
            if labels is not todo and good.sum() < max(2, 0.6 * len(labels)):
                continue
            for key, p, g in zip(keys, refined, good):
                if g:
                    grid[key] = p
                    added = True
        if not added:
            break
    return grid
