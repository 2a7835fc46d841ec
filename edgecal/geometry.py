"""Frames and stereo geometry as pure array functions: camera placement, rotations, triangulation.

Transforms follow docs/conventions.md (``T_a_b`` maps frame-b points to frame a). The camera model and
projection live in edgecal.camera; this module only combines rays and frames.
"""

from __future__ import annotations

import cv2
import numpy as np

from edgecal.camera import StereoRig, unproject

_Z_UP = np.array([0.0, 0.0, 1.0])
_Z_UP.flags.writeable = False   # a shared default argument: read-only so no caller can change it


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = _Z_UP) -> tuple[np.ndarray, np.ndarray]:
    """Pose (R_cam_world, t_cam_world) of a camera at ``eye`` looking at ``target`` (any one unit).

    ``up`` (world frame) appears upwards in the image (camera y points down, so y ~ -up).
    """
    eye = np.asarray(eye, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, dtype=np.float64))
    if np.linalg.norm(x) < 1e-9:
        # Looking along `up`: any perpendicular will do.
        x = np.cross(z, np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0]))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return R, -R @ eye


def rotation_about(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    """Rotation matrix of ``angle_rad`` about ``axis`` (Rodrigues)."""
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    K = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
    return np.eye(3) + np.sin(angle_rad) * K + (1.0 - np.cos(angle_rad)) * (K @ K)


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def triangulate_rays(v_left: np.ndarray, v_right: np.ndarray, R_right_left: np.ndarray, t_right_left: np.ndarray,
                     optimal: bool = False) -> np.ndarray:
    """Left-camera-frame points (N, 3), in the unit of ``t_right_left``, from matched rays (N, 3) of each camera.

    Linear (DLT) on the rays' cross-product constraints, so rays at or behind 90 degrees (fisheye) work.
    ``optimal`` first moves each match onto its epipolar lines by the smallest change (Hartley-Sturm,
    cv2.correctMatches on the essential matrix); it needs rays in front of both cameras and is skipped else.
    """
    vl = np.asarray(v_left, dtype=np.float64).reshape(-1, 3)
    vr = np.asarray(v_right, dtype=np.float64).reshape(-1, 3)
    if len(vl) == 0:
        return np.zeros((0, 3))
    R = np.asarray(R_right_left, dtype=np.float64).reshape(3, 3)
    t = np.asarray(t_right_left, dtype=np.float64).reshape(3)
    if optimal and np.all(vl[:, 2] > 1e-9) and np.all(vr[:, 2] > 1e-9):
        xl, xr = vl[:, :2] / vl[:, 2:], vr[:, :2] / vr[:, 2:]
        a, b = cv2.correctMatches(_skew(t) @ R, xl.reshape(1, -1, 2), xr.reshape(1, -1, 2))
        if a is not None and np.all(np.isfinite(a)) and np.all(np.isfinite(b)):
            vl = np.c_[a.reshape(-1, 2), np.ones(len(vl))]
            vr = np.c_[b.reshape(-1, 2), np.ones(len(vr))]
    vl = vl / np.linalg.norm(vl, axis=1, keepdims=True)
    vr = vr / np.linalg.norm(vr, axis=1, keepdims=True)
    P_l = np.hstack([np.eye(3), np.zeros((3, 1))])
    P_r = np.hstack([R, t.reshape(3, 1)])
    # v x (P X) = 0: three rows per camera (two independent), (N, 6, 4)
    skew_l = np.zeros((len(vl), 3, 3))
    skew_r = np.zeros((len(vr), 3, 3))
    for s, v in ((skew_l, vl), (skew_r, vr)):
        s[:, 0, 1], s[:, 0, 2], s[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
        s[:, 1, 0], s[:, 2, 0], s[:, 2, 1] = v[:, 2], -v[:, 1], v[:, 0]
    A = np.concatenate([skew_l @ P_l, skew_r @ P_r], axis=1)
    # the unit of t makes the 4th column large or small: scale it to 1 for a well-conditioned SVD
    scale = max(float(np.linalg.norm(t)), 1e-12)
    A[:, :, 3] *= scale
    # a ray that is not finite (a pixel the lens model cannot unproject) gives a NaN point, not a failed SVD
    ok = np.all(np.isfinite(A), axis=(1, 2))
    h = np.full((len(A), 4), np.nan)
    if ok.any():
        h[ok] = np.linalg.svd(A[ok], full_matrices=False)[2][:, -1, :]  # (V only is needed)
    with np.errstate(divide="ignore", invalid="ignore"):
        return h[:, :3] / (h[:, 3:] * scale)


def triangulate_pixels(rig: StereoRig, q_left: np.ndarray, q_right: np.ndarray, optimal: bool = False) -> np.ndarray:
    """3-D points (N, 3) in the rig (left camera) frame, metres, from matched pixels (N, 2) of the two cameras."""
    return triangulate_rays(unproject(np.asarray(q_left, dtype=np.float64).reshape(-1, 2), rig.left),
                            unproject(np.asarray(q_right, dtype=np.float64).reshape(-1, 2), rig.right),
                            rig.R_right_left, rig.t_right_left_m, optimal)
