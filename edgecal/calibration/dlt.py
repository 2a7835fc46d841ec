"""Direct linear transform: a 3x4 camera matrix from non-coplanar 3-D/2-D points, and its RQ split.

The DLT needs no initial guess, which is what lets a single image of a calibration box start a
calibration (OpenCV's calibrateCamera cannot start from a non-planar target without one).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import scipy.linalg

from edgecal.calibration.checks import DegenerateInput, require_non_coplanar


@dataclass(frozen=True)
class LinearCamera:
    """A camera from a linear method: intrinsics K (zero skew), pose target->camera, and diagnostics."""

    camera_matrix: np.ndarray   # (3, 3)
    rotation: np.ndarray        # (3, 3) R_cam_target
    translation: np.ndarray     # (3,) t_cam_target, same unit as the 3-D points
    dist_coeffs: np.ndarray     # (5,) k1 k2 p1 p2 k3 (the DLT leaves them 0)
    rms_px: float               # reprojection RMS of this linear camera (distortion included)
    method: str
    skew: float = 0.0           # the skew the DLT found before it was dropped, in pixels


def _normalising_transform(points: np.ndarray) -> np.ndarray:
    """Hartley's similarity: centroid to 0, mean distance sqrt(dim); conditions the DLT system."""
    dim = points.shape[1]
    centre = points.mean(axis=0)
    scale = np.sqrt(dim) / max(float(np.mean(np.linalg.norm(points - centre, axis=1))), 1e-12)
    t = np.eye(dim + 1)
    t[:dim, :dim] *= scale
    t[:dim, dim] = -scale * centre
    return t


def dlt_projection_matrix(object_pts: np.ndarray, image_px: np.ndarray) -> np.ndarray:
    """The 3x4 projection matrix P (up to scale, det(P[:, :3]) > 0) mapping target points to pixels.

    Raises DegenerateInput for fewer than 6 points or coplanar points.
    """
    obj, img = require_non_coplanar(object_pts, image_px)
    t3 = _normalising_transform(obj)
    t2 = _normalising_transform(img)
    xh = (t3 @ np.c_[obj, np.ones(len(obj))].T).T
    uh = (t2 @ np.c_[img, np.ones(len(img))].T).T
    n = len(obj)
    a = np.zeros((2 * n, 12))
    a[0::2, 0:4] = xh
    a[0::2, 8:12] = -uh[:, :1] * xh
    a[1::2, 4:8] = xh
    a[1::2, 8:12] = -uh[:, 1:2] * xh
    _, s, vt = np.linalg.svd(a, full_matrices=False)
    if s[-2] < 1e-9 * s[0]:
        raise DegenerateInput("the corners do not determine a camera (their 3-D layout is degenerate)")
    p = np.linalg.inv(t2) @ vt[-1].reshape(3, 4) @ t3
    if np.linalg.det(p[:, :3]) < 0:
        p = -p
    return p / np.linalg.norm(p[2, :3])


def decompose_projection(p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Split P = K [R | t] by RQ decomposition: K upper triangular with positive diagonal, K[2,2] = 1,
    R a proper rotation."""
    p = np.asarray(p, dtype=np.float64)
    if np.linalg.det(p[:, :3]) < 0:
        p = -p
    k, r = scipy.linalg.rq(p[:, :3])
    d = np.diag(np.sign(np.diag(k)))
    k, r = k @ d, d @ r  # d @ d = I: flip signs so that K has a positive diagonal
    t = np.linalg.solve(k, p[:, 3])
    scale = k[2, 2]
    return k / scale, r, t


def _rms(obj: np.ndarray, img: np.ndarray, k: np.ndarray, r: np.ndarray, t: np.ndarray,
         dist: np.ndarray) -> float:
    proj, _ = cv2.projectPoints(obj, cv2.Rodrigues(r)[0], t, k, dist)
    return float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - img) ** 2, axis=1))))


def calibrate_dlt(object_pts: np.ndarray, image_px: np.ndarray) -> LinearCamera:
    """Intrinsics and pose from one view of non-coplanar points by the DLT; skew is dropped."""
    obj, img = require_non_coplanar(object_pts, image_px)
    k, r, t = decompose_projection(dlt_projection_matrix(obj, img))
    skew = float(k[0, 1])
    k = k.copy()
    k[0, 1] = 0.0
    if (obj @ r.T + t)[:, 2].min() <= 0:
        raise DegenerateInput("the DLT placed some corners behind the camera: the matches are inconsistent")
    dist = np.zeros(5)
    return LinearCamera(k, r, t, dist, _rms(obj, img, k, r, t, dist), "dlt", skew)
