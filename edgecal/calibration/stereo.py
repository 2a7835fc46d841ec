"""One-shot stereo calibration from one image pair of a calibration box; 3-D reconstruction error,
rectification and epipolar error.

Each camera is first calibrated alone (mono.initialise_camera); the two box poses give the left->right
pose; then everything is refined jointly: one box pose, both cameras' intrinsics and the rig pose.
"""

from __future__ import annotations

import cv2
import numpy as np

from edgecal.calibration.checks import DegenerateInput
from edgecal.calibration.mono import initialise_camera, relative_pose
from edgecal.calibration.refine import RefineOptions, calibration_from_result, observations_for, refine
from edgecal.calibration.types import Calibration, CornerSet, Reconstruction, Rectification, RigidTransform
from edgecal.camera import CameraModel, unproject
from edgecal.geometry import triangulate_rays


def calibrate_box_stereo(left: CornerSet, right: CornerSet, image_size: tuple[int, int],
                         options: RefineOptions = RefineOptions()) -> Calibration:
    """Both cameras, distortion and the left->right pose from one stereo pair of a non-coplanar target."""
    cam_l, pose_l, _, tried_l = initialise_camera(left, image_size, options, "left")
    cam_r, pose_r, _, tried_r = initialise_camera(right, image_size, options, "right")
    corners = [[left], [right]]
    res = refine(observations_for(corners), [cam_l, cam_r], [pose_l], [relative_pose(pose_l, pose_r)], options)
    cal = calibration_from_result("box-stereo", image_size, corners, res)
    cal.init = {"left": tried_l, "right": tried_r}
    return finish_stereo(cal)


def finish_stereo(cal: Calibration) -> Calibration:
    """Add the reconstruction error, the rectification and the epipolar error to a stereo calibration."""
    cal.reconstruction = reconstruction_error(cal)
    cal.rectification = rectify(cal)
    return cal


def _matched(cal: Calibration, view: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[str]]:
    """Left pixels, right pixels and 3-D target points of the inlier corners seen by both cameras."""
    left, right = cal.corners[0][view], cal.corners[1][view]
    li = {k: i for i, k in enumerate(left.keys) if cal.inliers[0][view][i]}
    pairs = [(li[k], j) for j, k in enumerate(right.keys) if k in li and cal.inliers[1][view][j]]
    if not pairs:
        return np.zeros((0, 2)), np.zeros((0, 2)), np.zeros((0, 3)), []
    a, b = np.array(pairs).T
    return left.image_px[a], right.image_px[b], left.object_mm[a], [left.keys[i][0] for i in a]


def triangulate(cam_l: CameraModel, cam_r: CameraModel, rig: RigidTransform, px_l: np.ndarray,
                px_r: np.ndarray) -> np.ndarray:
    """Left-camera-frame 3-D points (same unit as ``rig.tvec``) of matched pixels in the two cameras."""
    return triangulate_rays(unproject(px_l, cam_l), unproject(px_r, cam_r), rig.rotation, rig.tvec)


def reconstruction_error(cal: Calibration) -> Reconstruction:
    """Triangulate every corner seen by both cameras and compare with its known position (Table 2).

    The known target points are placed in the left camera by the calibrated target pose of their view.
    """
    rig = RigidTransform.from_rt(cal.rotation, cal.translation_mm)
    errors, boards = [], []
    for v, pose in enumerate(cal.view_poses):
        px_l, px_r, obj, names = _matched(cal, v)
        if not len(obj):
            continue
        est = triangulate(cal.cameras[0], cal.cameras[1], rig, px_l, px_r)
        errors.append(np.linalg.norm(est - pose.apply(obj), axis=1))
        boards += names
    if not errors:
        raise DegenerateInput("no corner is seen by both cameras: the reconstruction error cannot be measured")
    e = np.concatenate(errors)
    per_board = {b: float(np.mean(e[[n == b for n in boards]])) for b in sorted(set(boards))}
    return Reconstruction(float(e.mean()), float(e.std()), float(e.max()), len(e), per_board, e)


def rectify(cal: Calibration) -> Rectification:
    """cv2.stereoRectify of the calibrated rig and the vertical disparity of the rectified corners (in
    pixels of the original cameras)."""
    (k1, d1), (k2, d2) = [(c.camera_matrix, c.dist_coeffs) for c in cal.cameras]
    r1, r2, p1, p2, q, _, _ = cv2.stereoRectify(k1, d1, k2, d2, tuple(cal.image_size), cal.rotation,
                                                np.ravel(cal.translation_mm).reshape(3, 1), alpha=0)
    dy = []
    for v in range(len(cal.view_poses)):
        px_l, px_r, _, _ = _matched(cal, v)
        if len(px_l):
            # Rectified normalised rows, scaled back to the cameras' own pixels: the rectified
            # images' focal length depends on alpha and is not what the detector saw.
            yl = cv2.undistortPoints(px_l.reshape(-1, 1, 2), k1, d1, R=r1).reshape(-1, 2)[:, 1]
            yr = cv2.undistortPoints(px_r.reshape(-1, 1, 2), k2, d2, R=r2).reshape(-1, 2)[:, 1]
            dy.append((yl - yr) * 0.5 * (k1[1, 1] + k2[1, 1]))
    d = np.concatenate(dy) if dy else np.zeros(1)
    return Rectification(r1, r2, p1, p2, q, float(np.sqrt(np.mean(d ** 2))), float(np.abs(d).max()))
