"""Least-squares rigid transform between two matched 3-D point sets (Kabsch / Umeyama without scale)."""

from __future__ import annotations

import numpy as np


def fit_rigid(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """R, t minimising sum ||dst - (R src + t)||^2 over rotations (never a reflection).

    src, dst: (N, 3) matched points, N >= 3 and not all on one line.
    """
    src = np.asarray(src, dtype=np.float64).reshape(-1, 3)
    dst = np.asarray(dst, dtype=np.float64).reshape(-1, 3)
    if len(src) < 3 or len(src) != len(dst):
        raise ValueError("fit_rigid needs at least 3 matched points")
    mu_s, mu_d = src.mean(axis=0), dst.mean(axis=0)
    H = (src - mu_s).T @ (dst - mu_d)
    U, _, Vt = np.linalg.svd(H)
    # Umeyama's sign correction: the nearest proper rotation when the best orthogonal fit is a reflection.
    d = np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0
    D = np.diag([1.0, 1.0, d])
    R = Vt.T @ D @ U.T
    return R, mu_d - R @ mu_s


def is_degenerate(points: np.ndarray, tol_m: float = 1e-4) -> bool:
    """True when the points are (nearly) collinear, so a rigid fit is not determined."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(pts) < 3:
        return True
    s = np.linalg.svd(pts - pts.mean(axis=0), compute_uv=False)
    return bool(s[1] < tol_m)
