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
from edgecal.calibration.refine import (
    RefineOptions,
    calibration_from_result,
    observations_for,
    refine,
)
from edgecal.calibration.types import (
    Calibration,
    CornerSet,
    Reconstruction,
    Rectification,
    RigidTransform,
)
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
    assert cal.rotation is not None and cal.translation_mm is not None  # set for every stereo calibration
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


def stereo_rectify(left: CameraModel, right: CameraModel, R_right_left: np.ndarray, t_right_left: np.ndarray,
                   image_size: tuple[int, int]) -> tuple[np.ndarray, ...]:
    """R1, R2, P1, P2, Q of a rig: cv2.fisheye.stereoRectify for fisheye lenses, cv2.stereoRectify else.

    P2's baseline term and Q are in the unit of ``t_right_left``. Both views keep only valid pixels
    (alpha 0 / balance 0).
    """
    t = np.ravel(t_right_left).reshape(3, 1).astype(np.float64)
    size = (int(image_size[0]), int(image_size[1]))
    if left.lens == "fisheye" and right.lens == "fisheye":
        r1, r2, p1, p2, q = cv2.fisheye.stereoRectify(left.camera_matrix, left.dist_coeffs, right.camera_matrix,
                                                      right.dist_coeffs, size, np.asarray(R_right_left, np.float64),
                                                      t, flags=cv2.CALIB_ZERO_DISPARITY, balance=0.0)
        return r1, r2, p1, p2, q
    if left.lens == "fisheye" or right.lens == "fisheye":
        raise DegenerateInput("rectification needs the same lens family in both cameras (fisheye with fisheye)")
    r1, r2, p1, p2, q, _, _ = cv2.stereoRectify(left.camera_matrix, left.dist_coeffs, right.camera_matrix,
                                                right.dist_coeffs, size, np.asarray(R_right_left, np.float64), t,
                                                alpha=0)
    return r1, r2, p1, p2, q


def rectification_maps(camera: CameraModel, R: np.ndarray, P: np.ndarray, image_size: tuple[int, int]
                       ) -> tuple[np.ndarray, np.ndarray]:
    """cv2.remap maps (x, y as float32 images) of one camera into its rectified image (R, P of stereo_rectify)."""
    size = (int(image_size[0]), int(image_size[1]))
    if camera.lens == "fisheye":
        return cv2.fisheye.initUndistortRectifyMap(camera.camera_matrix, camera.dist_coeffs, R, P, size, cv2.CV_32FC1)
    return cv2.initUndistortRectifyMap(camera.camera_matrix, camera.dist_coeffs, R, P, size, cv2.CV_32FC1)


def rectified_rows(q: np.ndarray, camera: CameraModel, R: np.ndarray) -> np.ndarray:
    """Rectified normalised y of pixels (N, 2): the ray through each, rotated by R (any lens model)."""
    v = unproject(q, camera) @ np.asarray(R, dtype=np.float64).T
    return v[:, 1] / v[:, 2]


def rectify(cal: Calibration) -> Rectification:
    """The rectification of the calibrated rig (stereo_rectify) and the vertical disparity of the rectified
    corners (in pixels of the original cameras)."""
    left, right = cal.cameras
    assert cal.rotation is not None and cal.translation_mm is not None  # set for every stereo calibration
    r1, r2, p1, p2, q = stereo_rectify(left, right, cal.rotation, cal.translation_mm, cal.image_size)
    dy = []
    for v in range(len(cal.view_poses)):
        px_l, px_r, _, _ = _matched(cal, v)
        if len(px_l):
            # Rectified normalised rows, scaled back to the cameras' own pixels: the rectified
            # images' focal length depends on alpha and is not what the detector saw.
            dy.append((rectified_rows(px_l, left, r1) - rectified_rows(px_r, right, r2)) * 0.5 * (left.fy + right.fy))
    d = np.concatenate(dy) if dy else np.zeros(1)
    return Rectification(r1, r2, p1, p2, q, float(np.sqrt(np.mean(d ** 2))), float(np.abs(d).max()))
