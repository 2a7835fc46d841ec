"""Pose math against exact projections of a known pose (plus noise)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from edgecal.detection.types import Detection
from edgecal.geometry import triangulate_pixels
from edgecal.pose import PoseSettings, QualityBounds, estimate_pose, fit_rigid
from edgecal.targets import Board, Target

from .pose_fixtures import render_detections, robot_target, rotation_error_rad, stereo_cams, true_pose


def test_fit_rigid_recovers_transform_and_never_reflects() -> None:
    rng = np.random.default_rng(1)
    X = rng.normal(size=(20, 3))
    R = Rotation.from_rotvec([0.3, -1.2, 0.7]).as_matrix()
    t = np.array([0.1, -2.0, 3.0])
    R_est, t_est = fit_rigid(X, X @ R.T + t)
    assert np.allclose(R_est, R, atol=1e-12) and np.allclose(t_est, t, atol=1e-12)
    # A mirrored cloud has no proper rotation mapping it exactly: the answer must still be a rotation.
    R_m, _ = fit_rigid(X, X * np.array([1, 1, -1]))
    assert np.linalg.det(R_m) == pytest.approx(1.0)


def test_triangulation_is_exact_on_exact_projections() -> None:
    cams = stereo_cams()
    rng = np.random.default_rng(2)
    X = rng.uniform([-0.3, -0.2, 0.8], [0.3, 0.2, 1.5], size=(50, 3))
    pl, _ = cv2.projectPoints(X, np.zeros(3), np.zeros(3), cams.left.camera_matrix, cams.left.dist_coeffs)
    pr, _ = cv2.projectPoints(X, cv2.Rodrigues(cams.R_right_left)[0], cams.t_right_left_m, cams.right.camera_matrix,
                              cams.right.dist_coeffs)
    for optimal in (True, False):
        Xt = triangulate_pixels(cams, pl.reshape(-1, 2), pr.reshape(-1, 2), optimal=optimal)
        assert np.abs(Xt - X).max() < 1e-7


@pytest.mark.parametrize("distorted", [False, True, "fisheye"])
def test_stereo_pose_is_exact_on_exact_projections(distorted: bool | str) -> None:
    target, cams = robot_target(), stereo_cams(distorted)
    R, t = true_pose()
    left, right = render_detections(target, cams, R, t)
    pose = estimate_pose(left, right, target, cams)
    assert pose.valid, pose.reason
    assert pose.mode == "stereo" and pose.n_both >= 30
    assert np.abs(pose.t_m - t).max() < 1e-9
    assert np.linalg.norm(rotation_error_rad(pose.R, R)) < 1e-9
    assert pose.rms_px < 1e-6
    q = pose.quaternion_xyzw
    assert q[3] >= 0 and np.allclose(Rotation.from_quat(q).as_matrix(), R, atol=1e-9)
    # Default scale "max": exact data still reports the configured corner noise, not zero.
    assert 0 < pose.position_std_mm < 1.0


def test_mono_fallback_when_one_camera_sees_nothing() -> None:
    target, cams = robot_target(), stereo_cams()
    R, t = true_pose()
    left, right = render_detections(target, cams, R, t)
    for seen_left, seen_right, mode in ((left, [], "mono-left"), ([], right, "mono-right")):
        pose = estimate_pose(seen_left, seen_right, target, cams)
        assert pose.valid, pose.reason
        assert pose.mode == mode
        assert np.abs(pose.t_m - t).max() < 1e-8
        assert np.linalg.norm(rotation_error_rad(pose.R, R)) < 1e-8


def test_noisy_pose_is_close() -> None:
    target, cams = robot_target(), stereo_cams()
    R, t = true_pose()
    left, right = render_detections(target, cams, R, t, 0.2, np.random.default_rng(3))
    pose = estimate_pose(left, right, target, cams)
    assert pose.valid
    assert np.linalg.norm(pose.t_m - t) < 2e-3
    assert np.degrees(np.linalg.norm(rotation_error_rad(pose.R, R))) < 0.2
    assert 0.1 < pose.rms_px < 0.3


def test_quality_bounds_mark_pose_invalid_with_reason() -> None:
    target, cams = robot_target(), stereo_cams()
    R, t = true_pose()
    left, right = render_detections(target, cams, R, t, 2.0, np.random.default_rng(4))
    pose = estimate_pose(left, right, target, cams, PoseSettings(bounds=QualityBounds(max_rms_px=0.5)))
    assert not pose.valid and "max_rms_px" in pose.reason
    few = [Detection(d.board, d.corners[:2], d.ids[:2], d.quality[:2], d.grid) for d in left[:1]]
    pose = estimate_pose(few, [], target, cams)
    assert not pose.valid and "too few corners" in pose.reason
    pose = estimate_pose([], [], target, cams)
    assert not pose.valid and pose.reason == "no board detected"
    tight = PoseSettings(bounds=QualityBounds(max_position_std_mm=1e-6))
    pose = estimate_pose(left, right, target, cams, tight)
    assert not pose.valid and "max_position_std_mm" in pose.reason


def test_unknown_boards_are_ignored() -> None:
    target, cams = robot_target(), stereo_cams()
    R, t = true_pose()
    left, right = render_detections(target, cams, R, t)
    stray = Detection("other", np.array([[1.0, 2.0]] * 4), np.array([[0, 0], [1, 0], [0, 1], [1, 1]]),
                      np.ones(4), (2, 2))
    pose = estimate_pose(left + [stray], right, target, cams)
    assert pose.valid and "other" not in pose.boards


def test_a_board_seen_twice_in_one_image_is_taken_in_the_copy_the_other_boards_explain() -> None:
    """A second board of the same size under the same name (the detector's copy 1; e.g. a part of an edge-on
    board of another size) is not mixed in: the pose from the other boards picks the copy it explains, and
    when it explains neither, that board's corners are left out of that image."""
    target, cams = robot_target(), stereo_cams()
    R, t = true_pose()
    left, right = render_detections(target, cams, R, t)
    first = left[0]
    elsewhere = Detection(first.board, first.corners + 40.0, first.ids, first.quality, first.grid, copy=1)
    full = estimate_pose(left, right, target, cams)
    for order in ([elsewhere] + left, left + [elsewhere]):
        pose = estimate_pose(order, right, target, cams)
        assert pose.valid and pose.n_left == full.n_left and not pose.rejected
        assert abs(pose.rms_px - full.rms_px) < 1e-6
    # neither copy where the pose puts that board: left out as ambiguous, not fitted as a misfit
    further = Detection(first.board, first.corners - 40.0, first.ids, first.quality, first.grid, copy=2)
    pose = estimate_pose([elsewhere, further] + left[1:], right, target, cams)
    clean = estimate_pose(left[1:], right, target, cams)
    assert pose.valid and clean.valid
    assert pose.n_left == clean.n_left and not pose.rejected
    assert abs(pose.rms_px - clean.rms_px) < 1e-9


@pytest.mark.parametrize("scale", ["noise", "residual"])
def test_covariance_matches_monte_carlo_spread(scale: str) -> None:
    """With Gaussian corner noise of the configured sigma, the predicted covariance matches the spread.

    The normalised estimation error squared (NEES = e^T C^-1 e) of a consistent 6-D estimator averages 6;
    each axis' observed std must be within 25 % of the predicted one.
    """
    target, cams = robot_target(), stereo_cams()
    R, t = true_pose()
    sigma = 0.3
    settings = PoseSettings(covariance_scale=scale, corner_noise_px=sigma)
    rng = np.random.default_rng(5)
    errors, nees, covs = [], [], []
    for _ in range(300):
        left, right = render_detections(target, cams, R, t, sigma, rng)
        pose = estimate_pose(left, right, target, cams, settings)
        e = np.concatenate([pose.t_m - t, rotation_error_rad(pose.R, R)])
        errors.append(e)
        covs.append(pose.covariance)
        nees.append(e @ np.linalg.solve(pose.covariance, e))
    errors = np.array(errors)
    mean_cov = np.mean(covs, axis=0)
    assert np.mean(nees) == pytest.approx(6.0, rel=0.15)
    ratio = errors.std(axis=0) / np.sqrt(np.diag(mean_cov))
    assert np.all((ratio > 0.75) & (ratio < 1.25)), ratio
    assert np.all(np.abs(errors.mean(axis=0)) < 4 * errors.std(axis=0) / np.sqrt(len(errors)) + 1e-9)


def test_a_misread_board_is_rejected_and_named() -> None:
    """One board's ids shifted by one column in the right image (a misread grid): the pose survives."""
    target, cams = robot_target(), stereo_cams()
    R, t = true_pose()
    left, right = render_detections(target, cams, R, t, 0.1, np.random.default_rng(6))
    bad = right[0]
    shifted = bad.ids.copy()
    shifted[:, 0] = (shifted[:, 0] + 1) % target.board(bad.board).cols
    right = [Detection(bad.board, bad.corners, shifted, bad.quality, bad.grid)] + right[1:]
    assert not estimate_pose(left, right, target, cams, max_rejected=0).valid
    pose = estimate_pose(left, right, target, cams)
    assert pose.valid, pose.reason
    assert pose.rejected == (f"{bad.board} (right)",)
    assert np.linalg.norm(pose.t_m - t) < 1e-3


def test_a_misnamed_board_is_found_by_leaving_each_board_out() -> None:
    """The right image's view of one board carries another board's name (the detector names boards by
    their size, and a partly seen board can pass for a smaller one). The wrong board drags the fit so far
    that a correct board may fit worst under it; leaving each board out in turn finds the culprit."""
    tilt = np.radians(40.0)
    spare_axes = Rotation.from_rotvec([-1.323, 0.362, 1.149]).as_matrix()
    target = Target("three", (
        Board("face", 6, 5, 20.0, np.array([-60.0, 40.0, 0.0]), np.array([1.0, 0, 0]), np.array([0, -1.0, 0])),
        Board("slant", 6, 5, 20.0, np.array([80.0, 40.0, 0.0]), np.array([np.cos(tilt), 0, -np.sin(tilt)]),
              np.array([0, -1.0, 0])),
        # Placed where, under the fit the misnamed view contaminates, the correct "face" (left) fits worst.
        Board("spare", 6, 5, 20.0, np.array([-97.4, 52.4, -41.2]), spare_axes[:, 0], spare_axes[:, 1]),
    ))
    cams = stereo_cams()
    R, t = np.eye(3), np.array([0.0, 0.0, 0.8])
    left, right = render_detections(target, cams, R, t, 0.1, np.random.default_rng(7))
    assert {d.board for d in left} == {d.board for d in right} == {"face", "slant"}   # "spare" faces away
    right = [Detection("spare", d.corners, d.ids, d.quality, d.grid) if d.board == "face" else d for d in right]
    pose = estimate_pose(left, right, target, cams)
    assert pose.valid, pose.reason
    assert pose.rejected == ("spare (right)",)
    assert np.linalg.norm(pose.t_m - t) < 1e-3


def test_single_corner_outliers_are_left_out_and_counted() -> None:
    target, cams = robot_target(), stereo_cams()
    R, t = true_pose()
    left, right = render_detections(target, cams, R, t, 0.05, np.random.default_rng(5))
    clean = estimate_pose(left, right, target, cams)
    assert clean.valid and clean.outliers == 0
    # Two corners locked onto the wrong structure, 3 and 5 px off: a board-level RMS check would pass them.
    left[0].corners[3] += [3.0, 0.0]
    right[0].corners[7] += [0.0, -5.0]
    pose = estimate_pose(left, right, target, cams)
    assert pose.valid, pose.reason
    assert pose.outliers == 2 and pose.n_corners == clean.n_corners - 2
    assert np.linalg.norm(pose.t_m - t) < 0.5e-3
    assert pose.rms_px < 0.1
    # Without the rejection (a floor above the outliers) the same corners move the pose measurably.
    kept = estimate_pose(left, right, target, cams, PoseSettings(outlier_min_px=10.0))
    assert kept.outliers == 0 and kept.rms_px > 2 * pose.rms_px


def test_boards_seen_edge_on_are_left_out() -> None:
    """A board seen closer to edge-on than MIN_FACING_COS has biased corners: the pose leaves it out of
    the cameras that see it so (exactly those) and the rest gives the exact pose."""
    from edgecal.pose.predict import MIN_FACING_COS, camera_from_rig, facing_cos

    theta = np.radians(78.0)      # the second board's normal 78 deg off the line of sight (cos 0.21)
    target = Target("two", (
        Board("face", 6, 5, 20.0, np.array([-60.0, 40.0, 0.0]), np.array([1.0, 0, 0]), np.array([0, -1.0, 0])),
        Board("slant", 6, 5, 20.0, np.array([80.0, 40.0, 0.0]), np.array([np.cos(theta), 0, -np.sin(theta)]),
              np.array([0, -1.0, 0])),
    ))
    cams = stereo_cams()
    R, t = np.eye(3), np.array([0.0, 0.0, 0.8])
    left, right = render_detections(target, cams, R, t)
    expected = set()
    for side, dets in (("left", left), ("right", right)):
        R_c, t_c = camera_from_rig(cams, side, R, t)
        for d in dets:
            if abs(facing_cos(target.board(d.board), R_c, t_c)) < MIN_FACING_COS:
                expected.add(f"{d.board} ({side})")
                d.corners[:] += [0.3, -0.2]          # the detector's bias on slivers of squares
    assert "slant (right)" in expected and not any(e.startswith("face") for e in expected)
    pose = estimate_pose(left, right, target, cams)
    assert pose.valid, pose.reason
    assert set(pose.edge_on) == expected
    assert np.abs(pose.t_m - t).max() < 1e-6       # the 0.3 px bias would be ~0.2 mm
