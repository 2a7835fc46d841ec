"""The camera model against OpenCV's own functions, for every lens model, and its Jacobians and inverses."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from edgecal.camera import LENS_PARAMS, CameraModel, StereoRig, project, undistort_points, unproject

SIZE = (1280, 960)
LENSES = {
    "radtan": (-0.28, 0.09, 0.0012, -0.0008, -0.012),
    "rational": (0.35, -0.12, 0.0009, -0.0011, 0.02, 0.62, -0.05, 0.04),
    "fisheye": (-0.012, 0.021, -0.009, 0.0014),
}


def _camera(lens: str) -> CameraModel:
    return CameraModel(610.0, 612.5, 641.3, 478.9, lens, np.array(LENSES[lens]), SIZE)


def _points(rng: np.random.Generator, n: int, max_angle_deg: float) -> np.ndarray:
    """Random camera-frame points within ``max_angle_deg`` of the optical axis, 0.2..5 m away."""
    theta = np.radians(max_angle_deg) * np.sqrt(rng.uniform(0, 1, n))
    phi = rng.uniform(-np.pi, np.pi, n)
    d = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], axis=1)
    return d * rng.uniform(0.2, 5.0, (n, 1))


def _opencv_project(cam: CameraModel, p: np.ndarray) -> np.ndarray:
    z = np.zeros(3)
    if cam.lens == "fisheye":
        out, _ = cv2.fisheye.projectPoints(p.reshape(-1, 1, 3), z, z, cam.camera_matrix, cam.dist_coeffs)
    else:
        out, _ = cv2.projectPoints(p, z, z, cam.camera_matrix, cam.dist_coeffs)
    return out.reshape(-1, 2)


@pytest.mark.parametrize("lens", list(LENSES))
def test_projection_matches_opencv(lens: str) -> None:
    cam = _camera(lens)
    p = _points(np.random.default_rng(1), 500, 50.0)
    q = project(p, cam)
    assert np.max(np.abs(q - _opencv_project(cam, p))) < 1e-6


@pytest.mark.parametrize("lens", list(LENSES))
def test_undistortion_matches_opencv(lens: str) -> None:
    cam = _camera(lens)
    q = project(_points(np.random.default_rng(2), 500, 45.0), cam)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)
    if lens == "fisheye":
        ref = cv2.fisheye.undistortPoints(q.reshape(-1, 1, 2), cam.camera_matrix, cam.dist_coeffs, criteria=crit)
    else:
        ref = cv2.undistortPoints(q.reshape(-1, 1, 2), cam.camera_matrix, cam.dist_coeffs, criteria=crit)
    ours = undistort_points(q, cam)
    # compared in pixels of the ideal camera
    assert np.max(np.abs((ours - ref.reshape(-1, 2)) * [cam.fx, cam.fy])) < 1e-6


@pytest.mark.parametrize("lens", list(LENSES))
def test_unproject_inverts_project(lens: str) -> None:
    cam = _camera(lens)
    # 48 degrees: the rational lens above folds over at 52 degrees (beyond, a pixel has two preimages)
    p = _points(np.random.default_rng(3), 400, 48.0)
    v = unproject(project(p, cam), cam)
    assert np.allclose(np.linalg.norm(v, axis=1), 1.0)
    assert np.max(np.abs(v - p / np.linalg.norm(p, axis=1, keepdims=True))) < 1e-11


def test_beyond_a_fold_the_principal_ray_is_returned() -> None:
    """Past the rational lens' fold (52 deg) a pixel is also reached from inside it: that ray is the answer."""
    cam = _camera("rational")
    p = np.array([[np.tan(np.radians(54.0)), 0.0, 1.0]])
    v = unproject(project(p, cam), cam)
    assert np.degrees(np.arccos(v[0, 2])) < 52.4
    assert np.allclose(project(v, cam), project(p, cam), atol=1e-8)


def test_fisheye_beyond_180_degrees() -> None:
    """A 190-degree equidistant lens: rays 95 degrees off the axis (behind the camera plane) round-trip."""
    f = 960 / 2 / np.radians(95.0)   # the image circle's edge at 95 degrees
    cam = CameraModel(f, f, 639.5, 479.5, "fisheye", np.array([0.01, -0.002, 0.0, 0.0]), SIZE)
    p = _points(np.random.default_rng(4), 300, 95.0)
    assert np.any(p[:, 2] < 0)
    q = project(p, cam)
    assert np.all(np.isfinite(q))
    v = unproject(q, cam)
    assert np.max(np.abs(v - p / np.linalg.norm(p, axis=1, keepdims=True))) < 1e-11
    # rays behind the camera plane have no normalised (x/z, y/z) coordinates
    back = undistort_points(q[p[:, 2] < 0], cam)
    assert np.all(np.isnan(back))


@pytest.mark.parametrize("lens", list(LENSES))
def test_gradients_match_finite_differences(lens: str) -> None:
    cam = _camera(lens)
    p = _points(np.random.default_rng(5), 50, 50.0)
    q, dq_dp, dq_di = project(p, cam, get_gradients=True)
    for j in range(3):
        h = np.zeros(3)
        h[j] = 1e-6
        num = (project(p + h, cam) - project(p - h, cam)) / 2e-6
        assert np.max(np.abs(num - dq_dp[:, :, j])) < 1e-4 * np.max(np.abs(dq_dp))
    base = cam.intrinsics
    for j in range(len(base)):
        h = np.zeros(len(base))
        h[j] = 1e-7 * max(1.0, abs(base[j]))
        num = (project(p, cam.with_intrinsics(base + h)) - project(p, cam.with_intrinsics(base - h))) / (2 * h[j])
        assert np.max(np.abs(num - dq_di[:, :, j])) < 1e-5 * max(1.0, np.max(np.abs(num))), cam.intrinsic_names[j]


@pytest.mark.parametrize("lens", list(LENSES))
def test_leading_dimensions_and_point_gradients_only(lens: str) -> None:
    """Points shaped (..., 3) project as the same points flattened, and a solver that holds the intrinsics
    fixed (intrinsics_gradient=False) gets the same pixels and point Jacobian, exactly, and no intrinsics
    Jacobian."""
    cam = _camera(lens)
    p = _points(np.random.default_rng(8), 60, 50.0)
    q, dq_dp, dq_di = project(p, cam, get_gradients=True)
    q2, dq_dp2, dq_di2 = project(p.reshape(3, 4, 5, 3), cam, get_gradients=True)
    assert np.array_equal(q2.reshape(-1, 2), q) and np.array_equal(dq_dp2.reshape(-1, 2, 3), dq_dp)
    assert np.array_equal(dq_di2.reshape(dq_di.shape), dq_di)
    q3, dq_dp3, none = project(p, cam, get_gradients=True, intrinsics_gradient=False)
    assert np.array_equal(q3, q) and np.array_equal(dq_dp3, dq_dp) and none is None
    rays = unproject(q2, cam)
    assert rays.shape == (3, 4, 5, 3) and np.array_equal(rays.reshape(-1, 3), unproject(q, cam), equal_nan=True)


def test_gradients_on_the_axis() -> None:
    """The fisheye Jacobian has the pinhole limit on the optical axis (no division by zero)."""
    cam = _camera("fisheye")
    q, dq_dp, dq_di = project(np.array([[0.0, 0.0, 2.0]]), cam, get_gradients=True)
    assert np.allclose(q, [[cam.cx, cam.cy]])
    assert np.allclose(dq_dp[0], [[cam.fx / 2, 0, 0], [0, cam.fy / 2, 0]])
    assert np.all(np.isfinite(dq_di))


def test_intrinsics_gradient_matches_opencv_jacobian() -> None:
    cam = _camera("rational")
    p = _points(np.random.default_rng(6), 30, 40.0)
    _, _, dq_di = project(p, cam, get_gradients=True)
    z = np.zeros(3)
    _, jac = cv2.projectPoints(p, z, z, cam.camera_matrix, cam.dist_coeffs)
    # OpenCV's columns: rvec(3) tvec(3) fx fy cx cy k1 k2 p1 p2 k3 k4 k5 k6
    assert np.allclose(jac[:, 6:18], dq_di.reshape(-1, 12), rtol=1e-9, atol=1e-9)


def test_behind_a_pinhole_camera_is_nan() -> None:
    q = project(np.array([[0.1, 0.0, -1.0], [0.0, 0.0, 1.0]]), _camera("radtan"))
    assert np.all(np.isnan(q[0])) and np.all(np.isfinite(q[1]))


def test_opencv_round_trip_and_validation() -> None:
    cam = _camera("rational")
    again = CameraModel.from_opencv(cam.camera_matrix, cam.dist_coeffs, SIZE)
    assert again.lens == "rational" and np.array_equal(again.params, cam.params)
    assert CameraModel.from_opencv(np.eye(3), np.r_[LENSES["radtan"], 0, 0, 0]).lens == "radtan"
    assert cam.ros_distortion_model == "rational_polynomial"
    assert _camera("fisheye").ros_distortion_model == "equidistant"
    with pytest.raises(ValueError, match="radtan, rational, fisheye"):
        CameraModel(1, 1, 0, 0, "ocam")
    with pytest.raises(ValueError, match="4 parameters"):
        CameraModel(1, 1, 0, 0, "fisheye", np.ones(5))
    assert set(LENS_PARAMS) == {"radtan", "rational", "fisheye"}


def test_stereo_rig() -> None:
    rig = StereoRig(_camera("fisheye"), _camera("fisheye"), np.eye(3), [-0.075, 0.0, 0.001])
    assert rig.baseline_m == pytest.approx(np.hypot(0.075, 0.001))
    assert rig.image_size == SIZE


def test_triangulating_a_pixel_without_a_ray_gives_nan_not_an_error() -> None:
    from edgecal.geometry import triangulate_rays
    v = np.array([[0.0, 0.0, 1.0], [np.nan, np.nan, np.nan]])
    X = triangulate_rays(v, v + [[0.1, 0, 0], [0, 0, 0]], np.eye(3), [-0.1, 0, 0])
    assert np.all(np.isfinite(X[0])) and np.all(np.isnan(X[1]))
