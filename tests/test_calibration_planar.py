"""Planar multi-view calibration: recovers the cameras, rejects a bad view, reports coverage and std."""

from pathlib import Path

import cv2
import numpy as np
import pytest

from edgecal.calibration.checks import DegenerateInput
from edgecal.calibration.planar import calibrate_planar, coverage
from edgecal.calibration.types import CornerSet, RigidTransform
from edgecal.synth.corners import project_target, stereo_truth
from edgecal.targets import planar_target

SIZE = (640, 480)
# ../shared beside the repository (as in CI)
REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "real" / "opencv_stereo_9x6"


def _views(n=8, noise=0.1, seed=0):
    cl, cr, _, rig = stereo_truth(dist=(-0.2, 0.1, 0.0, 0.0, 0.0))
    target = planar_target(9, 6, 25.0)
    rng = np.random.default_rng(seed)
    left, right = [], []
    for _ in range(n):
        centre = np.array([100.0, 62.5, 0.0]) + rng.normal(0, 30, 3) * [1, 1, 0]
        tilt = np.radians(rng.uniform(-35, 35, 2))
        eye = centre + 480.0 * np.array([np.sin(tilt[0]), np.sin(tilt[1]), -np.cos(tilt[0]) * np.cos(tilt[1])])
        pl = RigidTransform.looking_at(eye, centre, up=np.array([0.0, -1.0, 0.0]))
        pr = RigidTransform.from_rt(rig.rotation @ pl.rotation, rig.rotation @ pl.tvec + rig.tvec)
        left.append(project_target(target, cl, pl, SIZE, noise, rng))
        right.append(project_target(target, cr, pr, SIZE, noise, rng))
    return (cl, cr, rig), left, right


def test_planar_stereo_recovers_rig_with_honest_std():
    (cl, cr, rig), left, right = _views()
    cal = calibrate_planar(left, right, SIZE)
    for c, truth in enumerate((cl, cr)):
        err = cal.cameras[c].camera_matrix[0, 0] - truth.camera_matrix[0, 0]
        assert abs(err) < 5 * cal.camera_std[c]["fx"], (err, cal.camera_std[c]["fx"])
    assert np.all(np.abs(cal.translation_mm - rig.tvec) < 5 * cal.translation_std_mm + 1e-6)
    assert cal.rms_px < 0.2 and cal.reconstruction.mean_mm < 1.0
    assert any("coverage" in n for n in cal.notes)


def test_planar_mono_rejects_a_bad_view():
    (cl, _, _), left, _ = _views(n=7, seed=1)
    bad = left[3]
    left[3] = CornerSet(bad.object_mm, bad.image_px + np.random.default_rng(0).normal(0, 3.0, bad.image_px.shape),
                        bad.keys)
    names = [f"img{i}.png" for i in range(len(left))]
    cal = calibrate_planar(left, None, SIZE, view_names=names)
    assert any(n.startswith("img3.png: skipped, fits far worse") for n in cal.notes), cal.notes
    assert 3 not in cal.view_index and cal.skipped_views[3].startswith("fits far worse")
    assert abs(cal.cameras[0].camera_matrix[0, 0] / cl.camera_matrix[0, 0] - 1) < 0.01


def test_too_few_views_say_so():
    _, left, _ = _views(n=2)
    with pytest.raises(DegenerateInput, match="only 2 views"):
        calibrate_planar(left, None, SIZE)


def test_coverage_of_a_corner_only_set():
    cs = CornerSet(np.zeros((3, 3)), np.array([[5.0, 5.0], [10.0, 8.0], [630.0, 470.0]]), (("b", 0, 0),) * 3)
    assert coverage([cs], SIZE) == pytest.approx(2 / 48)


@pytest.mark.skipif(not REAL.is_dir(), reason="shared real data not present")
def test_bouguet_stereo_set_matches_published_baseline():
    """OpenCV's stereo sample (Bouguet's fifth example): |T| ~ 99.8 mm, fc ~ 533 px (SOURCE.md)."""
    board = planar_target(9, 6, 30.0).boards[0]

    def corners(path):
        g = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        ok, c = cv2.findChessboardCorners(g, (9, 6), flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
        assert ok
        c = cv2.cornerSubPix(g, c, (11, 11), (-1, -1), (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.01))
        return CornerSet(board.board_points_mm(), c.reshape(-1, 2).astype(float),
                         tuple((board.name, int(a), int(b)) for a, b in board.ids()))

    left = [corners(p) for p in sorted(REAL.glob("left*.jpg"))]
    right = [corners(p) for p in sorted(REAL.glob("right*.jpg"))]
    cal = calibrate_planar(left, right, (640, 480))
    assert abs(cal.cameras[0].camera_matrix[0, 0] - 533.0) < 5.0
    assert abs(np.linalg.norm(cal.translation_mm) - 99.8) < 1.0


def test_natural_sort_pairs_2_before_10(tmp_path):
    """Folders of numbered images sort by number: left2 before left10 (a string sort would pair wrongly)."""
    from edgecal.images import expand_image_args
    for n in (1, 2, 10, 11):
        (tmp_path / f"left{n}.png").write_bytes(b"")
    (tmp_path / "notes.txt").write_text("not an image")
    assert [p.name for p in expand_image_args([str(tmp_path)])] == ["left1.png", "left2.png", "left10.png",
                                                                     "left11.png"]
