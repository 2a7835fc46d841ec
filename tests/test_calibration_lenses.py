"""Calibration with every lens model: planar mono/stereo, the box, honest σ (Monte Carlo), fisheye rectification."""

from __future__ import annotations

import numpy as np
import pytest

from edgecal.calibration.acceptance import acceptance_problems
from edgecal.calibration.lens_choice import choose_lens_model
from edgecal.calibration.mono import calibrate_box_mono
from edgecal.calibration.planar import calibrate_planar
from edgecal.calibration.refine import Observation, RefineOptions, refine
from edgecal.calibration.settings import Acceptance, PlanarSettings
from edgecal.calibration.stereo import rectification_maps
from edgecal.calibration.types import RigidTransform
from edgecal.camera import CameraModel, project
from edgecal.synth.corners import cube_box_target, project_target, stereo_truth
from edgecal.targets import planar_target

SIZE = (1280, 800)


def _lens_rig(lens: str) -> tuple[CameraModel, CameraModel, RigidTransform]:
    """Two cameras of one lens model and T_right_left (mm): a 160 deg fisheye or a wide rational lens."""
    if lens == "fisheye":
        f = 640 / np.radians(80.0)
        left = CameraModel(f, f * 1.001, 641.0, 398.0, "fisheye", np.array([0.03, -0.012, 0.004, -0.0008]), SIZE)
        right = CameraModel(f * 1.01, f * 1.011, 633.0, 404.0, "fisheye", np.array([0.028, -0.01, 0.003, -0.0005]),
                            SIZE)
    else:
        left = CameraModel(600.0, 600.5, 641.0, 398.0, "rational",
                           np.array([0.4, -0.05, 0.0008, -0.0005, 0.01, 0.75, 0.02, 0.004]), SIZE)
        right = CameraModel(606.0, 606.6, 633.0, 404.0, "rational",
                            np.array([0.38, -0.04, -0.0006, 0.0004, 0.008, 0.73, 0.025, 0.003]), SIZE)
    rot = RigidTransform.looking_at(np.zeros(3), np.array([0.05, 0.0, 1.0]), up=np.array([0.0, -1.0, 0.0])).rotation
    return left, right, RigidTransform.from_rt(rot, np.array([-80.0, 0.5, 1.0]))


def _planar_views(left: CameraModel, right: CameraModel, rig: RigidTransform, n: int, noise: float, seed: int):
    """``n`` stereo views of a 9x6 board (30 mm), spread over the (wide) field of view."""
    target = planar_target(9, 6, 30.0)
    rng = np.random.default_rng(seed)
    centre_board = np.array([120.0, 75.0, 0.0])
    views_l, views_r, poses = [], [], []
    while len(views_l) < n:
        # the camera at 250-450 mm, looking at the board from up to 50 deg off its normal, the board anywhere
        # in the image: aim at a point beside the board
        tilt = np.radians(rng.uniform(-50, 50, 2))
        dist = rng.uniform(250.0, 450.0)
        eye = centre_board + dist * np.array([np.sin(tilt[0]), np.sin(tilt[1]), -np.cos(tilt[0]) * np.cos(tilt[1])])
        aim = centre_board + rng.uniform(-1, 1, 3) * [250.0, 180.0, 0.0]
        pl = RigidTransform.looking_at(eye, aim, up=np.array([0.0, -1.0, 0.0]))
        pr = RigidTransform.from_rt(rig.rotation @ pl.rotation, rig.rotation @ pl.tvec + rig.tvec)
        a = project_target(target, left, pl, SIZE, noise, rng)
        b = project_target(target, right, pr, SIZE, noise, rng)
        if len(a) == 54 and len(b) == 54:
            views_l.append(a)
            views_r.append(b)
            poses.append(pl)
    return views_l, views_r, poses


@pytest.mark.parametrize("lens", ["fisheye", "rational"])
def test_planar_stereo_with_each_lens_model(lens: str) -> None:
    left, right, rig = _lens_rig(lens)
    vl, vr, _ = _planar_views(left, right, rig, 16, 0.1, seed=3)
    cal = calibrate_planar(vl, vr, SIZE, RefineOptions(distortion=lens))
    assert [c.lens for c in cal.cameras] == [lens, lens]
    for c, truth in enumerate((left, right)):
        assert abs(cal.cameras[c].fx / truth.fx - 1) < 2e-3                   # focal within 0.2 %
        for name, value in zip(truth.intrinsic_names, truth.intrinsics):
            std = cal.camera_std[c][name]
            assert np.isfinite(std) and std > 0, name
            assert abs(cal.cameras[c].intrinsics[truth.intrinsic_names.index(name)] - value) < 5 * std, name
    assert np.all(np.abs(cal.translation_mm - rig.tvec) < 4 * cal.translation_std_mm)
    assert cal.rms_px < 0.15 and cal.reconstruction.mean_mm < 0.5
    assert cal.rectification.epipolar_rms_px < 0.3   # the corner noise, through both cameras


def test_fisheye_rectification_maps_put_a_point_on_one_row() -> None:
    left, right, rig = _lens_rig("fisheye")
    vl, vr, _ = _planar_views(left, right, rig, 12, 0.05, seed=4)
    cal = calibrate_planar(vl, vr, SIZE, RefineOptions(distortion="fisheye"))
    rect = cal.rectification
    maps = [rectification_maps(cal.cameras[i], r, p, SIZE) for i, (r, p) in enumerate(((rect.r1, rect.p1),
                                                                                      (rect.r2, rect.p2)))]
    # a point 1.2 m ahead: the rectified rows agree, and the maps send the rectified pixel back to its projection
    X_left = np.array([[60.0, -40.0, 1200.0], [-200.0, 150.0, 900.0]])
    for X in X_left:
        rows = []
        for i, (r, p) in enumerate(((rect.r1, rect.p1), (rect.r2, rect.p2))):
            X_cam = X if i == 0 else rig.apply(X[None])[0]
            # P's 4th column places the right camera for points in the rectified left frame; in its own
            # rotated frame only P's 3x3 part applies
            h = p[:, :3] @ (r @ X_cam)
            u, v = h[:2] / h[2]
            rows.append(v)
            mx, my = maps[i]
            src = np.array([mx[int(round(v)), int(round(u))], my[int(round(v)), int(round(u))]])
            # the nearest rectified pixel maps back to within a pixel or two of the exact projection
            assert np.linalg.norm(src - project(X_cam[None], cal.cameras[i])[0]) < 2.0
        assert abs(rows[0] - rows[1]) < 0.2   # the calibrated rig is within noise of the true one


def test_fisheye_sigma_matches_the_spread() -> None:
    """Monte Carlo: over noise draws the spread of each intrinsic matches the σ the solver reports."""
    left, right, rig = _lens_rig("fisheye")
    exact, _, poses = _planar_views(left, right, rig, 8, 0.0, seed=5)
    rng = np.random.default_rng(6)
    est, std = [], []
    for _ in range(30):
        obs = [Observation(0, v, cs.object_mm, cs.image_px + rng.normal(0, 0.2, cs.image_px.shape))
               for v, cs in enumerate(exact)]
        res = refine(obs, [left], poses, options=RefineOptions(distortion="fisheye", outlier_sigmas=1e9))
        est.append(res.cameras[0].intrinsics)
        std.append([res.std_of(f"cam0.{n}") for n in left.intrinsic_names])
    ratio = np.std(est, axis=0, ddof=1) / np.mean(std, axis=0)
    # 30 draws: the sample std is within ~35 % of the truth at 2.5 sigma
    assert np.all((ratio > 0.65) & (ratio < 1.4)), dict(zip(left.intrinsic_names, np.round(ratio, 2)))
    bias = np.abs(np.mean(est, axis=0) - left.intrinsics) / (np.mean(std, axis=0) / np.sqrt(len(est)))
    assert np.all(bias < 4.0), dict(zip(left.intrinsic_names, np.round(bias, 1)))


def test_box_mono_with_a_fisheye_lens() -> None:
    truth = _lens_rig("fisheye")[0]
    _, _, pose, _ = stereo_truth(image_size=SIZE, focal_px=truth.fx)
    box = project_target(cube_box_target(), truth, pose, SIZE, 0.05, np.random.default_rng(7))
    cal = calibrate_box_mono(box, SIZE, RefineOptions(distortion="fisheye"))
    assert cal.cameras[0].lens == "fisheye"
    assert abs(cal.cameras[0].fx / truth.fx - 1) < 0.01 and cal.rms_px < 0.1


def test_an_undetermined_lens_model_is_named() -> None:
    """k1..k6 of the rational model from two nearly frontal views: the solver names what it cannot determine."""
    left, right, rig = _lens_rig("rational")
    target = planar_target(9, 6, 30.0)
    views = [project_target(target, left, RigidTransform.looking_at(np.array([120.0, 75.0, -z]),
                                                                    np.array([120.0, 75.0, 0.0]),
                                                                    up=np.array([0.0, -1.0, 0.0])), SIZE, 0.1)
             for z in (500.0, 520.0)]
    cal = calibrate_planar(views, None, SIZE, RefineOptions(distortion="rational"), PlanarSettings(min_views=2))
    problems = acceptance_problems(cal, Acceptance())
    assert problems[0].startswith("the corners cannot determine camera k1, camera k2"), problems
    assert "rational lens model" in problems[0]


def test_a_wrong_lens_model_is_named_in_the_refusal() -> None:
    """A radtan k1k2 fit to a 160 deg fisheye leaves radial residuals growing to the rim: the refusal says so."""
    left, right, rig = _lens_rig("fisheye")
    vl, _, _ = _planar_views(left, right, rig, 12, 0.1, seed=9)
    bounds = Acceptance(max_rms_px=0.5)
    cal = calibrate_planar(vl, None, SIZE, RefineOptions(distortion="k1k2"))
    problems = acceptance_problems(cal, bounds)
    assert any("is radial" in p and "radtan lens model does not fit" in p for p in problems), problems
    good = calibrate_planar(vl, None, SIZE, RefineOptions(distortion="fisheye"))
    assert acceptance_problems(good, bounds) == []


@pytest.mark.parametrize("lens, expected", [("fisheye", "fisheye"), ("radtan", "k1k2")])
def test_auto_keeps_the_simplest_supported_model(lens: str, expected: str) -> None:
    if lens == "fisheye":
        left, right, rig = _lens_rig("fisheye")
    else:
        left, right, _, rig = stereo_truth(image_size=SIZE, dist=(-0.2, 0.05, 0.0, 0.0, 0.0))
    vl, _, _ = _planar_views(left, right, rig, 12, 0.1, seed=10)
    cal = choose_lens_model(lambda o: calibrate_planar(vl, None, SIZE, o), RefineOptions(), Acceptance(),
                            candidates=("none", "k1", "k1k2", "fisheye", "k1k2p1p2k3", "rational"))
    assert cal.notes[0].startswith(f"distortion auto: chose {expected} "), cal.notes[:2]
    assert "simpler models rejected: none: residual" in cal.notes[1]


def test_unknown_lens_model_lists_the_known_ones(tmp_path) -> None:
    from edgecal.calibration.settings import load_calibration_settings
    from edgecal.errors import ConfigError
    cfg = tmp_path / "c.yaml"
    cfg.write_text("distortion: ocam\n")
    with pytest.raises(ConfigError, match="distortion.*rational.*fisheye.*auto"):
        load_calibration_settings(cfg)
