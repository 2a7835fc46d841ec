"""Calibration weighted by the corners' covariances: more accurate when corners differ in quality, and
its sigma matches the spread of the errors (|error| / sigma median about 0.67)."""

from __future__ import annotations

import numpy as np

from edgecal.calibration.planar import calibrate_planar
from edgecal.calibration.refine import RefineOptions
from edgecal.calibration.types import CornerSet, RigidTransform
from edgecal.synth.corners import project_target, stereo_truth
from edgecal.targets import planar_target

SIZE = (640, 480)


def _views(rng: np.random.Generator, n: int = 8) -> tuple[object, list[CornerSet]]:
    """Exact projections of n views of a 9x6 board, each corner with its own anisotropic covariance and
    an error drawn from it: every third corner 8x noisier (a blurred or low-contrast corner)."""
    cam = stereo_truth(dist=(-0.2, 0.1, 0.0, 0.0, 0.0))[0]
    target = planar_target(9, 6, 25.0)
    views = []
    for _ in range(n):
        centre = np.array([100.0, 62.5, 0.0]) + rng.normal(0, 30, 3) * [1, 1, 0]
        tilt = np.radians(rng.uniform(-35, 35, 2))
        eye = centre + 480.0 * np.array([np.sin(tilt[0]), np.sin(tilt[1]), -np.cos(tilt[0]) * np.cos(tilt[1])])
        cs = project_target(target, cam, RigidTransform.looking_at(eye, centre, up=np.array([0.0, -1.0, 0.0])), SIZE)
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
