"""Triangulation of corners seen by both cameras of a calibrated pair."""

from __future__ import annotations

import cv2
import numpy as np

from edgecal.pose.types import StereoCameras


def undistort_to_normalised(points_px: np.ndarray, camera_matrix: np.ndarray,
                            dist_coeffs: np.ndarray) -> np.ndarray:
    """Pixel points (N, 2) -> ideal normalised image coordinates (x/z, y/z), distortion removed."""
    pts = np.asarray(points_px, dtype=np.float64).reshape(-1, 1, 2)
    if len(pts) == 0:
        return np.zeros((0, 2))
    # The default 5 iterations leave ~0.01 px of error on strongly distorted lenses; 20 is still cheap.
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 1e-12)
    out = cv2.undistortPoints(pts, camera_matrix, dist_coeffs, criteria=criteria)
    return out.reshape(-1, 2)


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def triangulate_normalised(x_left: np.ndarray, x_right: np.ndarray, R: np.ndarray, T: np.ndarray,
                           optimal: bool = True) -> np.ndarray:
    """3-D points in the left camera frame from matched normalised coordinates (N, 2) each.

    ``optimal`` first moves each match onto its epipolar lines by the smallest change (Hartley-Sturm,
    cv2.correctMatches with the essential matrix), then solves the linear (DLT) system.
    """
    x_left = np.asarray(x_left, dtype=np.float64).reshape(-1, 2)
    x_right = np.asarray(x_right, dtype=np.float64).reshape(-1, 2)
    if len(x_left) == 0:
        return np.zeros((0, 3))
    T = np.asarray(T, dtype=np.float64).reshape(3)
    if optimal:
        E = _skew(T) @ np.asarray(R, dtype=np.float64)
        a, b = cv2.correctMatches(E, x_left.reshape(1, -1, 2), x_right.reshape(1, -1, 2))
        if a is not None and np.all(np.isfinite(a)) and np.all(np.isfinite(b)):
            x_left, x_right = a.reshape(-1, 2), b.reshape(-1, 2)
    P1 = np.hstack([np.eye(3), np.zeros((3, 1))])
    P2 = np.hstack([np.asarray(R, dtype=np.float64), T.reshape(3, 1)])
    X = cv2.triangulatePoints(P1, P2, x_left.T.copy(), x_right.T.copy())
    return (X[:3] / X[3]).T


def triangulate_pixels(cams: StereoCameras, left_px: np.ndarray, right_px: np.ndarray,
                       optimal: bool = True) -> np.ndarray:
    """3-D points (N, 3) in the rig (left camera) frame, metres, from matched pixel corners."""
    xl = undistort_to_normalised(left_px, cams.camera_matrix_left, cams.dist_coeffs_left)
    xr = undistort_to_normalised(right_px, cams.camera_matrix_right, cams.dist_coeffs_right)
    return triangulate_normalised(xl, xr, cams.R, cams.T, optimal)
