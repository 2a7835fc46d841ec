"""Calibration weighted by the corners' covariances: more accurate when corners differ in quality, and
its sigma matches the spread of the errors (|error| / sigma median about 0.67)."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from edgecal.calibration.planar import calibrate_planar
from edgecal.calibration.refine import RefineOptions
from edgecal.calibration.types import CornerSet, RigidTransform
from edgecal.camera import CameraModel
from edgecal.synth.corners import project_target, stereo_truth
from edgecal.targets import planar_target

SIZE = (640, 480)


def _exact_views(rng: np.random.Generator, cam: CameraModel, n: int) -> Iterator[CornerSet]:
    """Exact projections of n hand-held views of a 9x6 board (drawn lazily: the caller's draws for each
    view's errors follow that view's pose draws)."""
    target = planar_target(9, 6, 25.0)
    for _ in range(n):
        centre = np.array([100.0, 62.5, 0.0]) + rng.normal(0, 30, 3) * [1, 1, 0]
        tilt = np.radians(rng.uniform(-35, 35, 2))
        eye = centre + 480.0 * np.array([np.sin(tilt[0]), np.sin(tilt[1]), -np.cos(tilt[0]) * np.cos(tilt[1])])
        yield project_target(target, cam, RigidTransform.looking_at(eye, centre, up=np.array([0.0, -1.0, 0.0])),
                             SIZE)


def _views(rng: np.random.Generator, n: int = 8) -> tuple[object, list[CornerSet]]:
    """Exact projections of n views of a 9x6 board, each corner with its own anisotropic covariance and
    an error drawn from it: every third corner 8x noisier (a blurred or low-contrast corner)."""
    cam = stereo_truth(dist=(-0.2, 0.1, 0.0, 0.0, 0.0))[0]
    views = []
    for cs in _exact_views(rng, cam, n):
        m = len(cs)
        s = np.where(np.arange(m) % 3 == 0, 0.4, 0.05)[:, None] * rng.uniform(0.6, 1.4, size=(m, 2))
        a = rng.uniform(0, np.pi, m)
        rot = np.stack([np.cos(a), -np.sin(a), np.sin(a), np.cos(a)], axis=1).reshape(m, 2, 2)
        cov = rot @ (s[:, :, None] ** 2 * np.eye(2)) @ np.transpose(rot, (0, 2, 1))
        err = np.einsum("nij,nj->ni", np.linalg.cholesky(cov), rng.standard_normal((m, 2)))
        views.append(CornerSet(cs.object_mm, cs.image_px + err, cs.keys, cov))
    return cam, views


def test_weighted_planar_calibration_is_more_accurate_and_honest() -> None:
    rng = np.random.default_rng(4)
    err_w, err_u, z = [], [], []
    options = RefineOptions(distortion="k1k2")
    for _ in range(6):
        cam, views = _views(rng)
        weighted = calibrate_planar(views, None, SIZE, options)
        plain = calibrate_planar([CornerSet(v.object_mm, v.image_px, v.keys) for v in views], None, SIZE, options)
        truth = cam.camera_matrix
        for cal, out in ((weighted, err_w), (plain, err_u)):
            out.append(cal.cameras[0].camera_matrix[0, 0] - truth[0, 0])
        std = weighted.camera_std[0]
        est = weighted.cameras[0].camera_matrix
        z += [abs(est[0, 0] - truth[0, 0]) / std["fx"], abs(est[1, 1] - truth[1, 1]) / std["fy"],
              abs(est[0, 2] - truth[0, 2]) / std["cx"], abs(est[1, 2] - truth[1, 2]) / std["cy"]]
    assert np.sqrt(np.mean(np.square(err_w))) < 0.8 * np.sqrt(np.mean(np.square(err_u)))
    assert 0.35 < np.median(z) < 1.0, np.median(z)


def test_a_noisy_corner_is_not_an_outlier_when_its_covariance_says_so() -> None:
    """Outliers are judged in the corners' own sigmas: the noisy third of the corners stays in."""
    cam, views = _views(np.random.default_rng(9))
    cal = calibrate_planar(views, None, SIZE, RefineOptions(distortion="k1k2"))
    assert len(cal.dropped) <= 2, cal.dropped


def test_corners_file_keeps_covariances_and_names_a_bad_one(tmp_path) -> None:
    """NAME.corners.csv carries each corner's covariance (a re-solve weighs as the first solve did); a row
    whose covariance is not positive definite is refused naming its line."""
    import pytest

    from edgecal.calibration.views import View, corners_text, read_corners
    from edgecal.errors import ConfigError

    target = planar_target(9, 6, 25.0)
    _cam, views = _views(np.random.default_rng(2), n=2)
    cs = [CornerSet(v.object_mm, v.image_px, tuple((target.boards[0].name, c, r) for _b, c, r in v.keys),
                    v.image_cov_px2) for v in views]
    path = tmp_path / "rig.corners.csv"
    path.write_text(corners_text([View(f"v{i}.png", (f"v{i}.png",)) for i in range(2)], [cs], SIZE, target))
    back = read_corners(path, target)
    assert np.allclose(back.corners[0][1].image_cov_px2, cs[1].image_cov_px2, rtol=1e-5)
    lines = path.read_text().splitlines()
    fields = lines[5].split(",")
    fields[-1] = "-1"
    lines[5] = ",".join(fields)
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(ConfigError, match="line 6: the covariance"):
        read_corners(path, target)


def _real_like_views(rng: np.random.Generator, n: int = 8) -> tuple[object, list[CornerSet]]:
    """Views whose covariances know the corners' relative quality but not what a real lens and sensor add:
    every corner errs by 0.12 px on top (the covariances say 0.01-0.03 px), and one corner in twenty is
    misdetected by 4-8 px with a covariance of 0.5 px (as the detector flags a corner it sees poorly)."""
    cam = stereo_truth(dist=(-0.2, 0.1, 0.0, 0.0, 0.0))[0]
    views = []
    for cs in _exact_views(rng, cam, n):
        m = len(cs)
        s = rng.uniform(0.01, 0.03, m)
        err = rng.normal(0.0, 0.12, (m, 2)) + s[:, None] * rng.standard_normal((m, 2))
        bad = rng.random(m) < 0.05
        s[bad] = 0.5
        a = rng.uniform(0, 2 * np.pi, m)
        err[bad] = rng.uniform(4.0, 8.0, (int(bad.sum()), 1)) * np.stack([np.cos(a), np.sin(a)], axis=1)[bad]
        views.append(CornerSet(cs.object_mm, cs.image_px + err, cs.keys, s[:, None, None] ** 2 * np.eye(2)))
    return cam, views


def test_covariances_that_miss_the_real_error_cost_no_accuracy() -> None:
    """When the corners scatter far more than their covariances say, the weighted solve widens them by what
    the fit shows (a noise floor): it drops the misdetected corners as the unweighted one does, is as
    accurate, and its sigma stays honest."""
    rng = np.random.default_rng(11)
    err_w, err_u, z, floors = [], [], [], []
    options = RefineOptions(distortion="k1k2")
    for _ in range(5):
        cam, views = _real_like_views(rng)
        n_bad = sum(int(np.sum(v.image_cov_px2[:, 0, 0] > 0.1)) for v in views)
        weighted = calibrate_planar(views, None, SIZE, options)
        plain = calibrate_planar([CornerSet(v.object_mm, v.image_px, v.keys) for v in views], None, SIZE, options)
        assert len(weighted.dropped) >= n_bad, (len(weighted.dropped), n_bad)
        truth = cam.camera_matrix
        for cal, out in ((weighted, err_w), (plain, err_u)):
            k = cal.cameras[0].camera_matrix
            out.append([k[0, 0] - truth[0, 0], k[1, 1] - truth[1, 1], k[0, 2] - truth[0, 2], k[1, 2] - truth[1, 2]])
        std = weighted.camera_std[0]
        z += list(np.abs(err_w[-1]) / [std["fx"], std["fy"], std["cx"], std["cy"]])
        floors.append(weighted.noise_floor_px)
    rms_w, rms_u = np.sqrt(np.mean(np.square(err_w))), np.sqrt(np.mean(np.square(err_u)))
    assert rms_w < 1.1 * rms_u, (rms_w, rms_u)
    assert 0.08 < np.median(floors) < 0.16, floors
    assert 0.35 < np.median(z) < 1.0, np.median(z)


def test_right_covariances_get_no_floor() -> None:
    """Where the covariances are right (errors drawn from them) the floor is ~0 and nothing changes."""
    from edgecal.calibration.refine import noise_floor_px2

    rng = np.random.default_rng(3)
    cov = rng.uniform(0.01, 0.3, (2000, 1, 1)) ** 2 * np.eye(2)
    r = np.einsum("nij,nj->ni", np.linalg.cholesky(cov), rng.standard_normal((2000, 2)))
    assert np.sqrt(noise_floor_px2(r, cov)) < 0.02
    # the same errors with 0.1 px more on both axes: the floor finds it
    r2 = r + rng.normal(0.0, 0.1, r.shape)
    assert 0.08 < np.sqrt(noise_floor_px2(r2, cov)) < 0.12


REAL = __import__("pathlib").Path(__file__).resolve().parents[2] / "shared" / "data" / "real" / "opencv_stereo_9x6"


@__import__("pytest").mark.skipif(not REAL.is_dir(), reason="shared real data not present")
def test_bouguet_set_weighted_loses_nothing_against_unweighted() -> None:
    """Real photos: the covariances say ~0.02 px, the corners scatter by ~0.13 px and a few corners at the
    board's rim are misdetected by several px. The weighted solve must drop those as the unweighted one
    does and agree with it within its sigma (before the noise floor: epipolar RMS 0.45 px against 0.11,
    cy 1.2 px = 2.5 sigma apart)."""
    import edgecal
    from edgecal.images import load_grey

    target = planar_target(9, 6, 30.0)
    board = target.boards[0]

    def corners(path) -> CornerSet:
        d = next(d for d in edgecal.detect(load_grey(path), target) if d.complete)
        ok = d.usable()
        return CornerSet(board.board_points_mm(d.ids[ok]), d.corners[ok],
                         tuple((board.name, int(a), int(b)) for a, b in d.ids[ok]), d.covariance[ok])

    left = [corners(p) for p in sorted(REAL.glob("left*.jpg"))]
    right = [corners(p) for p in sorted(REAL.glob("right*.jpg"))]
    options = RefineOptions(distortion="k1k2p1p2k3")
    weighted = calibrate_planar(left, right, (640, 480), options)
    plain = calibrate_planar([CornerSet(v.object_mm, v.image_px, v.keys) for v in left],
                             [CornerSet(v.object_mm, v.image_px, v.keys) for v in right], (640, 480), options)
    assert weighted.rectification.epipolar_rms_px < 1.2 * plain.rectification.epipolar_rms_px
    assert weighted.reconstruction.mean_mm < 1.1 * plain.reconstruction.mean_mm
    for name in ("fx", "fy", "cx", "cy"):
        a = weighted.cameras[0].intrinsics[weighted.cameras[0].intrinsic_names.index(name)]
        b = plain.cameras[0].intrinsics[plain.cameras[0].intrinsic_names.index(name)]
        assert abs(a - b) < weighted.camera_std[0][name], (name, a, b, weighted.camera_std[0][name])
    assert 0.08 < weighted.noise_floor_px < 0.2
    assert any("scatter more than the detector's covariances say" in n for n in weighted.notes)


def test_calibration_weighs_corners_without_the_light_shift_of_their_board() -> None:
    """A shift all of a view's corners share (the light field's, LIGHT_SHIFT_PX2 x |grad log L|) is absorbed
    by that view's pose: calibration's weights leave it out of the detector's covariances."""
    from edgecal.calibration.assign import assign
    from edgecal.detection.corner_covariance import LIGHT_SHIFT_PX2
    from edgecal.detection.types import Detection

    target = planar_target(9, 6, 25.0)
    board = target.boards[0]
    ids = board.ids()
    n = len(ids)
    xy = np.column_stack([100.0 + 30.0 * ids[:, 0], 80.0 + 30.0 * ids[:, 1]])
    cov = np.broadcast_to(0.02 ** 2 * np.eye(2), (n, 2, 2)).copy()
    light = np.tile([1.5e-3, -0.5e-3], (n, 1))
    shift2 = LIGHT_SHIFT_PX2 ** 2 * float(np.sum(light[0] ** 2))
    det = Detection(board.name, xy, ids, np.ones(n), (board.cols, board.rows),
                    covariance=cov + 0.5 * shift2 * np.eye(2), unusable=[""] * n, light_gradient=light)
    result = assign([det], target)
    assert result is not None and result.corners.image_cov_px2 is not None
    assert np.allclose(result.corners.image_cov_px2, cov)
    det.light_gradient = None
    unlit = assign([det], target)
    assert unlit is not None and np.allclose(unlit.corners.image_cov_px2, cov + 0.5 * shift2 * np.eye(2))
