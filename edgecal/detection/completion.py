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


def _local_homography(grid: dict[tuple[int, int], np.ndarray], u_lo: int, u_hi: int, v_lo: int,
                      v_hi: int) -> np.ndarray | None:
    """Homography label -> image fitted to the corners with labels in [u_lo, u_hi] x [v_lo, v_hi]."""
    src, dst = [], []
    for (a, b), xy in grid.items():
        if u_lo <= a <= u_hi and v_lo <= b <= v_hi:
            src.append((a, b))
            dst.append(xy)
    if len(src) < 4:
        return None
    src_a = np.asarray(src, np.float64)
    if len(np.unique(src_a[:, 0])) < 2 or len(np.unique(src_a[:, 1])) < 2:
        return None
    h, _ = cv2.findHomography(src_a, np.asarray(dst, np.float64), 0)
    return h


def _apply(h: np.ndarray, labels: np.ndarray) -> np.ndarray:
    p = np.c_[labels, np.ones(len(labels))] @ h.T
    return p[:, :2] / p[:, 2:3]


def _predict(h: np.ndarray, labels: list[tuple[int, int]]) -> tuple[np.ndarray, np.ndarray]:
    """Image positions of ``labels`` and the local square size there (the shorter label step), pixels."""
    lab = np.asarray(labels, np.float64)
    p = _apply(h, lab)
    du = np.linalg.norm(_apply(h, lab + (1.0, 0.0)) - p, axis=1)
    dv = np.linalg.norm(_apply(h, lab + (0.0, 1.0)) - p, axis=1)
    return p, np.minimum(du, dv)


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
        added = False
        # Holes: each from a homography of its own neighbourhood (lens distortion is local).
        holes = [(u, v) for u in range(u0, u1 + 1) for v in range(v0, v1 + 1) if (u, v) not in grid]
        preds, keys, spac = [], [], []
        for (u, v) in holes:
            h = _local_homography(grid, u - 2, u + 2, v - 2, v + 2)
            if h is not None:
                p, sp = _predict(h, [(u, v)])
                preds.append(p[0])
                keys.append((u, v))
                spac.append(sp[0])
        # Sides: a whole new row or column from the three nearest ones.
        sides = []
        if u1 - u0 + 1 < max_dim:
            sides += [([(u0 - 1, v) for v in range(v0, v1 + 1)], (u0, u0 + 2, v0, v1)),
                      ([(u1 + 1, v) for v in range(v0, v1 + 1)], (u1 - 2, u1, v0, v1))]
        if v1 - v0 + 1 < max_dim:
            sides += [([(u, v0 - 1) for u in range(u0, u1 + 1)], (u0, u1, v0, v0 + 2)),
                      ([(u, v1 + 1) for u in range(u0, u1 + 1)], (u0, u1, v1 - 2, v1))]
        groups = [(len(keys), None)]
        for labels, box in sides:
            h = _local_homography(grid, *box)
            if h is None:
                continue
            p, sp = _predict(h, labels)
            preds.extend(p)
            keys.extend(labels)
            spac.extend(sp)
            groups.append((len(keys), labels))
        if not keys:
            break
        refined, good = _verify(smooth, gx, gy, np.asarray(preds), np.asarray(spac), params)
        start = 0
        for end, labels in groups:
            sel = range(start, end)
            # A side line is taken only when most of it is confirmed (a board's margin confirms nothing).
            if labels is None or sum(good[i] for i in sel) >= max(2, 0.6 * len(labels)):
                for i in sel:
                    if good[i]:
                        grid[keys[i]] = refined[i]
                        added = True
            start = end
        if not added:
            break
    return grid
