"""Where the target's corners will be in the next frame: the pose extrapolated in time, then projected.

The live loop tracks the robot: instead of searching a whole image for boards, it projects every board
of the target through the pose it expects and lets the detector verify the corners there
(edgecal.detection.tracking). These are the geometric halves of that: a constant-velocity extrapolation
of T_rig_robot and the projection of the target into one camera of the rig.
"""

from __future__ import annotations

import cv2
import numpy as np

from edgecal.camera import CameraModel, StereoRig, project, unproject
from edgecal.detection.types import CornerPrediction
from edgecal.targets import Board, Target

# A board seen closer to edge-on than this (cosine between its normal and the line of sight; 0.3 is 72.5
# degrees off face-on) is neither predicted nor used for a pose: its squares are slivers whose corners the
# detector places with a bias along the foreshortened direction (on rendered sequences, 0.2-0.3 mm of
# pose error at 1 m against a reported 0.08 mm), not just more noise.
MIN_FACING_COS = 0.3
# Farthest the extrapolation reaches ahead, in units of the last inter-frame interval: after a long gap
# (dropped frames, a stalled camera) constant velocity is a guess, not a prediction.
MAX_EXTRAPOLATION = 3.0


def _rotation_vector(R: np.ndarray) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(R, dtype=np.float64))[0].ravel()


def extrapolate_pose(R_prev: np.ndarray, t_prev: np.ndarray, stamp_prev_ns: int, R_last: np.ndarray,
                     t_last: np.ndarray, stamp_last_ns: int, stamp_ns: int) -> tuple[np.ndarray, np.ndarray]:
    """T_rig_robot at ``stamp_ns`` from the two latest poses, moving at constant (angular) velocity.

    The rotation step is taken about the rig's axes (R_last = dR R_prev) and scaled by the time ratio,
    at most MAX_EXTRAPOLATION intervals ahead; stamps that do not advance give the last pose.
    """
    R_last = np.asarray(R_last, dtype=np.float64)
    t_last = np.asarray(t_last, dtype=np.float64).ravel()
    interval = stamp_last_ns - stamp_prev_ns
    if interval <= 0 or stamp_ns <= stamp_last_ns:
        return R_last.copy(), t_last.copy()
    ratio = min((stamp_ns - stamp_last_ns) / interval, MAX_EXTRAPOLATION)
    step = _rotation_vector(R_last @ np.asarray(R_prev, dtype=np.float64).T)
    dR = cv2.Rodrigues(ratio * step)[0]
    return dR @ R_last, t_last + ratio * (t_last - np.asarray(t_prev, dtype=np.float64).ravel())


def camera_from_rig(cams: StereoRig, side: str, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """T_cam_robot for the ``side`` ("left" or "right") camera, given T_rig_robot (the rig frame is the left
    camera's)."""
    if side == "left":
        return np.asarray(R, dtype=np.float64), np.asarray(t, dtype=np.float64).ravel()
    Rrl = cams.R_right_left
    return Rrl @ R, Rrl @ np.asarray(t, dtype=np.float64).ravel() + cams.t_right_left_m


def facing_cos(board: Board, R_c: np.ndarray, t_c: np.ndarray) -> float:
    """Cosine between ``board``'s normal and the line of sight to its centre in a camera at T_cam_robot =
    (R_c, t_c in metres): 1 seen face-on, 0 edge-on, negative from behind (the normal points into the
    body, away from a camera that sees the printed side; see configs/targets/)."""
    centre = R_c @ (board.centre_mm / 1000.0) + t_c
    return float((R_c @ board.normal) @ centre / max(np.linalg.norm(centre), 1e-12))


def _in_view(p_cam: np.ndarray, camera: CameraModel) -> np.ndarray:
    """Which camera-frame points (N, 3) the lens can image without folding.

    A distortion polynomial folds points far outside the field of view back into the image: a pinhole lens
    projects only points well in front and inside 1.5 image sizes of its ideal view; a fisheye lens points
    whose angle from the axis stays on the rising part of its theta polynomial (what unproject can invert).
    """
    w, h = camera.image_size
    if camera.lens == "fisheye":
        theta = np.arctan2(np.hypot(p_cam[:, 0], p_cam[:, 1]), p_cam[:, 2])
        edge = np.array([[-0.5, -0.5], [w - 0.5, -0.5], [-0.5, h - 0.5], [w - 0.5, h - 0.5]]) if w and h else None
        if edge is None:
            return theta < np.pi / 2
        v = unproject(edge, camera)
        limit = np.nanmax(np.arccos(np.clip(v[:, 2], -1, 1))) if np.any(np.isfinite(v)) else np.pi / 2
        return theta < limit + np.radians(5.0)
    front = p_cam[:, 2] > 1e-3
    if w and h:
        z = np.where(front, p_cam[:, 2], 1.0)
        pinhole = (p_cam[:, :2] / z[:, None]) * [camera.fx, camera.fy] + [camera.cx, camera.cy]
        front &= ((pinhole[:, 0] > -0.5 * w) & (pinhole[:, 0] < 1.5 * w)
                  & (pinhole[:, 1] > -0.5 * h) & (pinhole[:, 1] < 1.5 * h))
    return front


def predict_corners(R: np.ndarray, t_m: np.ndarray, cams: StereoRig, side: str, target: Target,
                    margin_px: float = 8.0) -> list[CornerPrediction]:
    """The corners of every board of ``target`` that the ``side`` camera should see under T_rig_robot = (R, t).

    A board must face the camera (its printed side: the board normal x_axis × y_axis points away from
    the camera, see configs/targets/) at more than MIN_FACING_COS; of its corners, those in front of the
    camera and at least ``margin_px`` inside the image are kept. Occlusion is not modelled: the detector's
    verification drops corners that are not there.
    """
    camera = cams.left if side == "left" else cams.right
    R_c, t_c = camera_from_rig(cams, side, R, t_m)
    w, h = camera.image_size
    out = []
    for board in target.boards:
        ids = board.ids()
        X = board.target_points_mm(ids) / 1000.0
        if facing_cos(board, R_c, t_c) < MIN_FACING_COS:
            continue
        X_cam = X @ R_c.T + t_c
        front = _in_view(X_cam, camera)
        if not front.any():
            continue
        px = project(X_cam[front], camera)
        inside = ((px[:, 0] >= margin_px) & (px[:, 0] <= w - 1 - margin_px)
                  & (px[:, 1] >= margin_px) & (px[:, 1] <= h - 1 - margin_px)) if w and h else np.ones(len(px), bool)
        if inside.any():
            out.append(CornerPrediction(board, ids[front][inside], px[inside]))
    return out
