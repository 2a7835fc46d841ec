"""DLT and Tsai recover K, R, t from exact projections; degenerate input is refused with a clear message."""

import cv2
import numpy as np
import pytest

from edgecal.calibration.checks import DegenerateInput
from edgecal.calibration.dlt import calibrate_dlt, decompose_projection
from edgecal.calibration.tsai import calibrate_tsai
from edgecal.camera import CameraModel
from edgecal.synth.corners import cube_box_target, project_target, stereo_truth

SIZE = (640, 480)


def _view(dist=(0, 0, 0, 0, 0), noise=0.0):
    cam, _, pose, _ = stereo_truth(dist=dist)
    cs = project_target(cube_box_target(), cam, pose, SIZE, noise)
    return cam, pose, cs


def test_dlt_recovers_camera_from_exact_points():
    cam, pose, cs = _view()
    lin = calibrate_dlt(cs.object_mm, cs.image_px)
    np.testing.assert_allclose(lin.camera_matrix, cam.camera_matrix, atol=1e-6)
    np.testing.assert_allclose(lin.rotation, pose.rotation, atol=1e-9)
    np.testing.assert_allclose(lin.translation, pose.tvec, atol=1e-6)
    assert lin.rms_px < 1e-8 and abs(lin.skew) < 1e-6


def test_rq_decomposition_of_a_known_matrix():
    k = np.array([[900.0, 2.0, 310.0], [0, 880.0, 250.0], [0, 0, 1]])
    r = cv2.Rodrigues(np.array([0.3, -1.2, 0.4]))[0]
    t = np.array([10.0, -20.0, 400.0])
    p = -3.7 * k @ np.c_[r, t]  # any scale, either sign
    k2, r2, t2 = decompose_projection(p)
    np.testing.assert_allclose(k2, k, atol=1e-9)
    np.testing.assert_allclose(r2, r, atol=1e-12)
    np.testing.assert_allclose(t2, t, atol=1e-9)
    assert np.linalg.det(r2) > 0


def test_tsai_recovers_camera_when_principal_point_is_centred():
    cam0, pose, _ = _view(dist=(-0.1, 0, 0, 0, 0))
    k = cam0.camera_matrix.copy()
    k[0, 2], k[1, 2] = (SIZE[0] - 1) / 2, (SIZE[1] - 1) / 2  # Tsai assumes the centre
    cam = CameraModel.from_opencv(k, np.array([-0.1, 0, 0, 0, 0.0]))
    cs = project_target(cube_box_target(), cam, pose, SIZE)
    lin = calibrate_tsai(cs.object_mm, cs.image_px, SIZE)
    np.testing.assert_allclose(lin.camera_matrix, k, rtol=1e-6)
    np.testing.assert_allclose(lin.rotation, pose.rotation, atol=1e-7)
    np.testing.assert_allclose(lin.translation, pose.tvec, atol=1e-4)
    assert abs(lin.dist_coeffs[0] + 0.1) < 1e-6


def test_tsai_with_offset_principal_point_is_close_enough_to_start():
    cam, pose, cs = _view(dist=(-0.12, 0.08, 0, 0, 0))
    lin = calibrate_tsai(cs.object_mm, cs.image_px, SIZE)
    assert abs(lin.camera_matrix[0, 0] / cam.camera_matrix[0, 0] - 1) < 0.05
    assert lin.rms_px < 2.0


def test_coplanar_points_are_refused_with_a_message():
    cam, pose, cs = _view()
    top = [i for i, k in enumerate(cs.keys) if k[0] == "top"]
    with pytest.raises(DegenerateInput, match="lie on one plane"):
        calibrate_dlt(cs.object_mm[top], cs.image_px[top])
    with pytest.raises(DegenerateInput, match="one plane"):
        calibrate_tsai(cs.object_mm[top], cs.image_px[top], SIZE)


def test_too_few_points_are_refused_with_a_message():
    _, _, cs = _view()
    with pytest.raises(DegenerateInput, match="at least 6"):
        calibrate_dlt(cs.object_mm[:5], cs.image_px[:5])
    with pytest.raises(DegenerateInput, match="pair up"):
        calibrate_dlt(cs.object_mm[:8], cs.image_px[:7])
