"""Pose from corners with their own covariances: weighted refinement, the model covariance (corner model
plus the error a board's corners share) against Monte-Carlo spread, unusable corners left out."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from edgecal.detection.corner_covariance import LIGHT_SHIFT_PX2, SHARED_FRACTION
from edgecal.detection.types import Detection
from edgecal.pose import PoseSettings, estimate_pose
from edgecal.pose.estimate import shared_error

from .pose_fixtures import render_detections, robot_target, rotation_error_rad, stereo_cams, true_pose


def _random_covariances(rng: np.random.Generator, n: int, sigma_px: float) -> np.ndarray:
    """(n, 2, 2) anisotropic covariances, sigmas 0.3-2 x sigma_px, random orientation."""
    s = sigma_px * rng.uniform(0.3, 2.0, size=(n, 2))
    a = rng.uniform(0, np.pi, n)
    R = np.stack([np.cos(a), -np.sin(a), np.sin(a), np.cos(a)], axis=1).reshape(n, 2, 2)
    return R @ (s[:, :, None] ** 2 * np.eye(2)) @ np.transpose(R, (0, 2, 1))


def _with_model_errors(dets: list[Detection], covs: list[np.ndarray], rng: np.random.Generator) -> list[Detection]:
    """Detections whose corners carry ``covs`` and errors drawn from the pose's error model: independent
    corner errors from those covariances plus the board's shared affine error (shared_error, with the
    shared part of the detector's saddle fit; no common offset: these detections have no light gradient)."""
    out = []
    for det, cov in zip(dets, covs):
        shared = SHARED_FRACTION["saddle"] ** 2 * 0.5 * (cov[:, 0, 0] + cov[:, 1, 1])
        basis, var = shared_error(det.corners, shared, np.zeros(len(cov), dtype=np.int64), np.zeros((len(cov), 2)))
        common = basis @ (rng.standard_normal(len(var)) * np.sqrt(var))
        own = np.einsum("nij,nj->ni", np.linalg.cholesky(cov), rng.standard_normal((len(cov), 2)))
        out.append(Detection(det.board, det.corners + own + common, det.ids, det.quality, det.grid,
                             covariance=cov, unusable=[""] * len(cov), shared_px2=shared))
    return out


def test_model_covariance_matches_monte_carlo_spread() -> None:
    """Corners with different, anisotropic covariances and errors from the model: NEES averages 6."""
    target, cams = robot_target(), stereo_cams()
    R, t = true_pose()
    rng = np.random.default_rng(11)
    left0, right0 = render_detections(target, cams, R, t)
    covs_l = [_random_covariances(rng, len(d.corners), 0.2) for d in left0]
    covs_r = [_random_covariances(rng, len(d.corners), 0.2) for d in right0]
    nees, errors, covs = [], [], []
    for _ in range(300):
        left, right = _with_model_errors(left0, covs_l, rng), _with_model_errors(right0, covs_r, rng)
        pose = estimate_pose(left, right, target, cams)
        assert pose.valid, pose.reason
        e = np.concatenate([pose.t_m - t, rotation_error_rad(pose.R, R)])
        errors.append(e)
        covs.append(pose.covariance)
        nees.append(e @ np.linalg.solve(pose.covariance, e))
    assert np.mean(nees) == pytest.approx(6.0, rel=0.15)
    ratio = np.array(errors).std(axis=0) / np.sqrt(np.diag(np.mean(covs, axis=0)))
    assert np.all((ratio > 0.75) & (ratio < 1.25)), ratio


def test_an_alternating_light_shift_is_modelled_as_such() -> None:
    """Each board's corners shifted by one vector times +1/-1 in their checkerboard pattern (the X-junction
    fit's light shift, Detection.alternating_px2, 3x the independent variance) on top of independent errors:
    the pose's covariance matches the spread (NEES 6). Weighting it as independent per-corner error instead
    (the same total covariance, no alternating part) makes the pose's sigma too large."""
    target, cams = robot_target(), stereo_cams()
    R, t = true_pose()
    rng = np.random.default_rng(5)
    left0, right0 = render_detections(target, cams, R, t)
    own_px2, alternating_px2 = 0.05 ** 2, 3 * 0.05 ** 2

    def shifted(dets: list[Detection], modelled: bool) -> list[Detection]:
        out = []
        for d in dets:
            n = len(d.corners)
            parity = 1.0 - 2.0 * (np.asarray(d.ids).sum(axis=1) % 2)
            error = (rng.normal(0, np.sqrt(own_px2), (n, 2))
                     + parity[:, None] * rng.normal(0, np.sqrt(alternating_px2), 2))
            cov = np.broadcast_to((own_px2 + alternating_px2) * np.eye(2), (n, 2, 2)).copy()
            out.append(Detection(d.board, d.corners + error, d.ids, d.quality, d.grid, covariance=cov,
                                 unusable=[""] * n, shared_px2=np.zeros(n),
                                 alternating_px2=np.full(n, alternating_px2) if modelled else None))
        return out

    for modelled, low, high in ((True, 5.0, 7.0), (False, 0.0, 4.0)):
        nees = []
        for _ in range(200):
            pose = estimate_pose(shifted(left0, modelled), shifted(right0, modelled), target, cams)
            assert pose.valid, pose.reason
            e = np.concatenate([pose.t_m - t, rotation_error_rad(pose.R, R)])
            nees.append(e @ np.linalg.solve(pose.covariance, e))
        assert low < np.mean(nees) < high, (modelled, np.mean(nees))


def test_weighting_by_the_corner_covariance_is_more_accurate() -> None:
    """Every third corner 10x noisier than the others: the weighted fit (the detector's covariances)
    beats the fit that weighs every corner alike."""
    target, cams = robot_target(), stereo_cams()
    R, t = true_pose()
    rng = np.random.default_rng(3)
    left0, right0 = render_detections(target, cams, R, t)
    err_w, err_u = [], []
    for _ in range(60):
        dets = []
        for side in (left0, right0):
            out = []
            for d in side:
                sigma = np.where(np.arange(len(d.corners)) % 3 == 0, 0.6, 0.06)
                cov = sigma[:, None, None] ** 2 * np.eye(2)
                noisy = d.corners + rng.normal(0, 1, d.corners.shape) * sigma[:, None]
                out.append(Detection(d.board, noisy, d.ids, d.quality, d.grid, covariance=cov,
                                     unusable=[""] * len(cov)))
            dets.append(out)
        weighted = estimate_pose(dets[0], dets[1], target, cams)
        plain = estimate_pose([Detection(d.board, d.corners, d.ids, d.quality, d.grid) for d in dets[0]],
                              [Detection(d.board, d.corners, d.ids, d.quality, d.grid) for d in dets[1]],
                              target, cams, PoseSettings(outlier_sigmas=100.0))
        err_w.append(np.linalg.norm(weighted.t_m - t))
        err_u.append(np.linalg.norm(plain.t_m - t))
    assert np.sqrt(np.mean(np.square(err_w))) < 0.7 * np.sqrt(np.mean(np.square(err_u)))


def test_unusable_corners_are_left_out() -> None:
    """A corner the detector marked unusable does not enter the fit, however far off it is."""
    target, cams = robot_target(), stereo_cams()
    R, t = true_pose()
    left, right = render_detections(target, cams, R, t)
    d = left[0]
    corners = d.corners.copy()
    corners[2] += 40.0
    cov = np.broadcast_to(np.eye(2) * 0.01, (len(corners), 2, 2)).copy()
    cov[2] = np.nan
    reasons = [""] * len(corners)
    reasons[2] = "covariance not positive definite (a line or an edge, not a corner)"
    left = [Detection(d.board, corners, d.ids, d.quality, d.grid, covariance=cov, unusable=reasons)] + left[1:]
    pose = estimate_pose(left, right, target, cams)
    assert pose.valid and pose.outliers == 0
    assert pose.n_left == sum(len(x.corners) for x in left) - 1
    assert np.linalg.norm(pose.t_m - t) < 1e-6


def test_a_start_behind_the_camera_gives_an_invalid_pose_not_an_exception() -> None:
    """A start that puts corners behind a camera (their projection is undefined) is no pose, with a reason
    (it happened while leaving boards out one by one on a noisy sequence)."""
    from edgecal.pose.estimate import _estimate, corner_table

    target, cams = robot_target(), stereo_cams()
    R, t = true_pose()
    left, right = render_detections(target, cams, R, t)
    behind = estimate_pose(left, right, target, cams)
    behind.t_m = -behind.t_m
    pose = _estimate(corner_table(left, target), corner_table(right, target), target, cams, PoseSettings(),
                     start_pose=behind)
    assert not pose.valid and "behind a camera" in pose.reason


def test_a_light_gradient_widens_the_pose_sideways() -> None:
    """Corners that report a light gradient share an offset along it (LIGHT_SHIFT_PX2 x |gradient|, the same
    in both cameras): the pose's sigma grows across the view by about that offset's reach, not in depth,
    and the pose itself does not move (only its covariance models the offset)."""
    target, cams = robot_target(), stereo_cams()
    R, t = true_pose()
    left0, right0 = render_detections(target, cams, R, t)
    gradient = np.array([2e-3, 0.0])                 # 1/px: a 40 % light ramp across a 400 px half-width

    def with_light(dets: list[Detection], g: np.ndarray) -> list[Detection]:
        n = [len(d.corners) for d in dets]
        return [Detection(d.board, d.corners, d.ids, d.quality, d.grid, covariance=np.broadcast_to(
                    0.03 ** 2 * np.eye(2), (k, 2, 2)).copy(), unusable=[""] * k, shared_px2=np.full(k, 0.003 ** 2),
                    light_gradient=np.tile(g, (k, 1))) for d, k in zip(dets, n)]

    lit = estimate_pose(with_light(left0, gradient), with_light(right0, gradient), target, cams)
    dark = estimate_pose(with_light(left0, 0 * gradient), with_light(right0, 0 * gradient), target, cams)
    assert lit.valid and dark.valid
    assert np.allclose(lit.t_m, dark.t_m) and np.allclose(lit.R, dark.R)
    added = np.diag(lit.covariance - dark.covariance)[:3]
    offset_m = LIGHT_SHIFT_PX2 * 2e-3 * t[2] / cams.left.fx     # the common offset at the robot's range
    assert added[0] == pytest.approx(offset_m ** 2, rel=0.5)
    assert added[2] < 0.2 * added[0] and abs(added[1]) < 0.2 * added[0]


def test_refine_pose_takes_the_steps_least_squares_takes() -> None:
    """refine_pose runs MINPACK's Levenberg-Marquardt through leastsq (for its lower overhead): from a start
    off the truth, on noisy weighted corners, the same pose as least_squares(method="lm") gives, bit for bit."""
    import cv2
    from scipy.optimize import least_squares

    from edgecal.pose.estimate import _views, corner_covariances, corner_table
    from edgecal.pose.refine import _residuals_and_jacobian, _view_whitening, refine_pose

    target, cams = robot_target(), stereo_cams()
    R, t = true_pose()
    left, right = render_detections(target, cams, R, t)
    rng = np.random.default_rng(5)
    covs = [_random_covariances(rng, len(d.corners), 0.2) for d in left + right]
    noisy = _with_model_errors(left + right, covs, rng)
    left, right = noisy[:len(left)], noisy[len(left):]
    tl, tr = corner_table(left, target), corner_table(right, target)
    views = list(_views(cams, target, tl, tr, (corner_covariances(left, target), corner_covariances(right, target))))
    R0 = cv2.Rodrigues(np.array([0.01, -0.02, 0.015]))[0] @ R
    t0 = t + np.array([0.01, -0.005, 0.02])
    R_fit, t_fit, _res, _J = refine_pose(R0, t0, views)
    white = _view_whitening(views)

    def whitened(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        r, J = _residuals_and_jacobian(x, views)
        return (np.einsum("nij,nj->ni", white, r.reshape(-1, 2)).ravel(),
                np.einsum("nij,njk->nik", white, J.reshape(-1, 2, 6)).reshape(-1, 6))

    x0 = np.concatenate([cv2.Rodrigues(R0)[0].ravel(), t0])
    sol = least_squares(lambda x: whitened(x)[0], x0, jac=lambda x: whitened(x)[1], method="lm", max_nfev=50,
                        xtol=1e-12, ftol=1e-12, gtol=1e-12)
    assert np.array_equal(t_fit, sol.x[3:])
    assert np.array_equal(R_fit, cv2.Rodrigues(sol.x[:3].reshape(3, 1))[0])
    assert np.linalg.norm(t_fit - t) < 1e-3


def test_model_covariance_sums_by_group_as_add_at_does() -> None:
    """model_covariance's sums over each group's corners (a numba pass) against np.add.at, bit for bit."""
    from edgecal.pose.refine import _sum_by_group

    rng = np.random.default_rng(3)
    values = rng.standard_normal((150, 38, 6)) * 10.0 ** rng.uniform(-6, 6, (150, 1, 1))
    for groups in (np.zeros(150, dtype=np.int64), rng.integers(0, 6, 150)):
        expected = np.zeros((int(groups.max()) + 1, 38, 6))
        np.add.at(expected, groups, values)
        assert np.array_equal(_sum_by_group(groups, values, int(groups.max()) + 1), expected)


@pytest.mark.parametrize("lens", ["radtan", "rational"])
def test_the_pinhole_pass_gives_what_project_gives(lens: str) -> None:
    """refine_pose's one-pass residuals and Jacobian of a pinhole view (radtan, rational lens) against the same
    terms through camera.project, to rounding; a point behind the camera is NaN in both."""
    import cv2

    from edgecal.pose.estimate import _views, corner_table
    from edgecal.pose.refine import _projected_view, _view_terms

    target, cams = robot_target(), stereo_cams()
    if lens == "rational":
        cams = replace(cams, right=replace(cams.right, lens="rational",
                                           params=np.r_[cams.right.params, 0.02, -0.01, 0.005]))
    R, t = true_pose()
    left, right = render_detections(target, cams, R, t)
    x = np.r_[cv2.Rodrigues(R)[0].ravel() + [0.01, -0.02, 0.005], t + [0.003, 0.002, -0.01]]
    R_x, dR = cv2.Rodrigues(x[:3].reshape(3, 1))
    dR = dR.reshape(3, 3, 3)
    for v in _views(cams, target, corner_table(left, target), corner_table(right, target)):
        assert v.camera.lens == ("rational" if lens == "rational" and v.camera is cams.right else "radtan")
        r, J = _view_terms(R_x, dR, x[3:], v)
        r_ref, J_ref = _projected_view(R_x, dR, x[3:], v)
        assert np.abs(r - r_ref).max() < 1e-9 and np.abs(J - J_ref).max() < 1e-12 * np.abs(J_ref).max()
    behind = x[3:] * [1.0, 1.0, -1.0]                # the robot as far behind the rig as it was in front
    r, _J = _view_terms(R_x, dR, behind, v)
    r_ref, _J = _projected_view(R_x, dR, behind, v)
    assert np.array_equal(np.isnan(r), np.isnan(r_ref)) and np.isnan(r).any()
