"""Refinement recovers the cameras under noise, drops outliers, and reports honest standard deviations."""

import numpy as np
import pytest

from edgecal.calibration.checks import DegenerateInput
from edgecal.calibration.dlt import calibrate_dlt
from edgecal.calibration.mono import calibrate_box_mono
from edgecal.calibration.refine import Observation, RefineOptions, refine
from edgecal.calibration.stereo import calibrate_box_stereo
from edgecal.calibration.types import CornerSet, RigidTransform
from edgecal.camera import CameraModel
from edgecal.synth.corners import cube_box_target, project_target, stereo_truth

SIZE = (640, 480)


def _stereo(noise, seed=0):
    cl, cr, pl, rig = stereo_truth()
    pr = RigidTransform.from_rt(rig.rotation @ pl.rotation, rig.rotation @ pl.tvec + rig.tvec)
    rng = np.random.default_rng(seed)
    t = cube_box_target()
    return (cl, cr, pl, rig), project_target(t, cl, pl, SIZE, noise, rng), project_target(t, cr, pr, SIZE, noise, rng)


def test_stereo_exact_points_give_exact_rig():
    (cl, cr, pl, rig), left, right = _stereo(0.0)
    cal = calibrate_box_stereo(left, right, SIZE)
    np.testing.assert_allclose(cal.cameras[0].camera_matrix, cl.camera_matrix, atol=1e-6)
    np.testing.assert_allclose(cal.cameras[1].dist_coeffs, cr.dist_coeffs, atol=1e-8)
    np.testing.assert_allclose(cal.translation_mm, rig.tvec, atol=1e-6)
    assert cal.reconstruction.mean_mm < 1e-6 and cal.rectification.epipolar_rms_px < 1e-6


def test_stereo_under_noise_is_within_a_few_sigma():
    (cl, cr, pl, rig), left, right = _stereo(0.1, seed=3)
    cal = calibrate_box_stereo(left, right, SIZE)
    for c, truth in enumerate((cl, cr)):
        for key, (i, j) in (("fx", (0, 0)), ("fy", (1, 1)), ("cx", (0, 2)), ("cy", (1, 2))):
            err = cal.cameras[c].camera_matrix[i, j] - truth.camera_matrix[i, j]
            assert abs(err) < 4 * cal.camera_std[c][key], (c, key, err, cal.camera_std[c][key])
    terr = np.abs(cal.translation_mm - rig.tvec)
    assert np.all(terr < 4 * cal.translation_std_mm + 1e-9)
    assert 0.05 < cal.sigma_px < 0.15
    assert cal.reconstruction.mean_mm < 0.5
    assert not cal.dropped


def test_outliers_are_dropped_and_named():
    (cl, _, pl, _), left, _ = _stereo(0.1, seed=5)
    img = left.image_px.copy()
    img[7] += (4.0, -3.0)
    img[30] += (0.0, 6.0)
    cal = calibrate_box_mono(CornerSet(left.object_mm, img, left.keys), SIZE)
    assert len(cal.dropped) == 2
    for i in (7, 30):
        board, c, r = left.keys[i]
        assert any(f"board {board} ({c},{r})" in d for d in cal.dropped)
    assert abs(cal.cameras[0].camera_matrix[0, 0] / cl.camera_matrix[0, 0] - 1) < 0.02
    assert cal.rms_px < 0.2


def test_too_few_corners_for_the_unknowns():
    _, left, _ = _stereo(0.0)
    lin = calibrate_dlt(left.object_mm, left.image_px)
    with pytest.raises(DegenerateInput, match="more corners"):
        refine([Observation(0, 0, left.object_mm[:6], left.image_px[:6])],
               [CameraModel.from_opencv(lin.camera_matrix, np.zeros(5))],
               [RigidTransform.from_rt(lin.rotation, lin.translation)])


def test_monte_carlo_reported_std_matches_spread():
    """Over many noisy trials the reported 1-sigma must match the actual scatter of the estimates."""
    cam, _, pose, _ = stereo_truth()
    t = cube_box_target(inner_corners=(3, 4), square_mm=20.0)  # small problem: 36 corners, keeps the test fast
    exact = project_target(t, cam, pose, SIZE)
    lin = calibrate_dlt(exact.object_mm, exact.image_px)
    rng = np.random.default_rng(42)
    opts = RefineOptions(distortion="k1", outlier_sigmas=50.0)  # the spread must not be censored by rejection
    values, stds = [], []
    for _ in range(100):
        img = exact.image_px + rng.normal(0.0, 0.2, exact.image_px.shape)
        res = refine([Observation(0, 0, exact.object_mm, img)],
                     [CameraModel.from_opencv(lin.camera_matrix, np.zeros(5))],
                     [RigidTransform.from_rt(lin.rotation, lin.translation)], options=opts)
        values.append(res.values)
        stds.append(res.std)
    spread = np.std(values, axis=0)
    reported = np.mean(stds, axis=0)
    ratio = spread / reported
    # 100 trials: the sample std itself scatters by ~7 %; the linearised covariance is a little optimistic.
    assert np.all((ratio > 0.75) & (ratio < 1.35)), dict(zip(res.names, np.round(ratio, 2)))
    truth = np.r_[cam.camera_matrix[0, 0], cam.camera_matrix[1, 1], cam.camera_matrix[0, 2], cam.camera_matrix[1, 2],
                  cam.dist_coeffs[0], pose.rvec, pose.tvec]
    bias = np.abs(np.mean(values, axis=0) - truth)
    assert np.all(bias < 4 * spread / np.sqrt(100) + 0.05 * spread), dict(zip(res.names, bias / spread))


def test_monte_carlo_stereo_baseline_std_matches_spread():
    """The reported σ of the left->right translation matches its spread over noisy trials."""
    cl, cr, pl, rig = stereo_truth()
    pr = RigidTransform.from_rt(rig.rotation @ pl.rotation, rig.rotation @ pl.tvec + rig.tvec)
    t = cube_box_target(inner_corners=(3, 4), square_mm=20.0)
    el, er = project_target(t, cl, pl, SIZE), project_target(t, cr, pr, SIZE)
    rng = np.random.default_rng(7)
    opts = RefineOptions(distortion="k1", outlier_sigmas=50.0)
    start = [CameraModel.from_opencv(c.camera_matrix, np.zeros(5)) for c in (cl, cr)]
    ts, stds = [], []
    for _ in range(60):
        obs = [Observation(0, 0, el.object_mm, el.image_px + rng.normal(0, 0.2, el.image_px.shape)),
               Observation(1, 0, er.object_mm, er.image_px + rng.normal(0, 0.2, er.image_px.shape))]
        res = refine(obs, start, [pl], [rig], options=opts)
        ts.append(res.rig_poses[0].tvec)
        stds.append([res.std_of(f"rig1.{n}") for n in ("tx", "ty", "tz")])
    ratio = np.std(ts, axis=0) / np.mean(stds, axis=0)
    assert np.all((ratio > 0.7) & (ratio < 1.4)), ratio
