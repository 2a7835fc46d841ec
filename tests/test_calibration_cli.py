"""`edgecal calibrate` end to end on rendered box pairs (render -> detect -> assign -> calibrate), and its
one-line errors for bad input."""

import json

import cv2
import numpy as np
import pytest

from edgecal.calibration.io import load_rig
from edgecal.cli import main
from edgecal.config import packaged_config_path
from edgecal.synth.scenes import box_stereo

BOX = str(packaged_config_path("targets/box-100mm.yaml"))


@pytest.fixture(scope="module")
def box_pair(tmp_path_factory):
    d = tmp_path_factory.mktemp("box")
    view = box_stereo(7, size=(800, 600), photometric="clean", supersampling=6)
    cv2.imwrite(str(d / "L.png"), view.left.image)
    cv2.imwrite(str(d / "R.png"), view.right.image)
    (d / "pair.json").write_text(json.dumps(view.pair))
    return d, view.pair


def _error_line(capsys):
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("edgecal: error: "), err
    return err[0]


def test_box_stereo_end_to_end(box_pair, tmp_path, capsys):
    d, truth = box_pair
    out = tmp_path / "rig.yaml"
    rc = main(["calibrate", "--target", BOX, "--left", str(d / "L.png"), "--right", str(d / "R.png"),
               "--out", str(out), "--report", str(tmp_path / "report"), "--distortion", "k1k2p1p2"])
    text = capsys.readouterr().out
    assert rc == 0, text
    assert "3-D reconstruction error" in text and "±" in text
    rig = load_rig(out)
    k_true = np.array(truth["left"]["K"])
    assert abs(rig.cameras[0].camera_matrix[0, 0] / k_true[0, 0] - 1) < 0.01
    t_true = np.array(truth["T_right_left_mm"]) * 1e-3
    assert np.linalg.norm(rig.stereo.t_right_left_m - t_true) < 1e-3  # within 1 mm
    for name in ("overlay_left.png", "overlay_right.png", "residual_histogram.png", "per_board_error.png",
                 "summary.txt"):
        assert (tmp_path / "report" / name).is_file()
    # a second run must not replace the file without --force
    rc = main(["calibrate", "--target", BOX, "--left", str(d / "L.png"), "--right", str(d / "R.png"),
               "--out", str(out)])
    assert rc == 2 and "--force" in _error_line(capsys)


def test_box_mono(box_pair, tmp_path, capsys):
    d, truth = box_pair
    out = tmp_path / "cam.yaml"
    assert main(["calibrate", "--target", BOX, "--left", str(d / "R.png"), "--out", str(out)]) == 0
    rig = load_rig(out)
    assert not rig.is_stereo
    assert abs(rig.cameras[0].camera_matrix[0, 0] / np.array(truth["right"]["K"])[0, 0] - 1) < 0.02


def test_refused_calibration_is_not_written(box_pair, tmp_path, capsys):
    d, _ = box_pair
    cfg = tmp_path / "strict.yaml"
    cfg.write_text("acceptance:\n  max_rms_px: 0.0001\n")
    out = tmp_path / "rig.yaml"
    rc = main(["calibrate", "--target", BOX, "--left", str(d / "L.png"), "--right", str(d / "R.png"),
               "--out", str(out), "--config", str(cfg)])
    line = _error_line(capsys)
    assert rc == 4 and "reprojection RMS" in line and "> 0.0001 px" in line
    assert not out.exists()


def test_missing_image(tmp_path, capsys):
    rc = main(["calibrate", "--target", BOX, "--left", str(tmp_path / "nope.png"), "--out", str(tmp_path / "r.yaml")])
    assert rc == 2 and "nope.png: image file not found" in _error_line(capsys)


def test_images_of_different_sizes(box_pair, tmp_path, capsys):
    d, _ = box_pair
    small = tmp_path / "small.png"
    cv2.imwrite(str(small), np.zeros((240, 320), np.uint8))
    rc = main(["calibrate", "--target", BOX, "--left", str(d / "L.png"), "--right", str(small),
               "--out", str(tmp_path / "r.yaml")])
    line = _error_line(capsys)
    assert rc == 2 and "small.png" in line and "320x240" in line


def test_board_not_seen_in_one_camera(box_pair, tmp_path, capsys):
    d, _ = box_pair
    blank = tmp_path / "blank.png"
    cv2.imwrite(str(blank), np.full((600, 800), 128, np.uint8))
    rc = main(["calibrate", "--target", BOX, "--left", str(d / "L.png"), "--right", str(blank),
               "--out", str(tmp_path / "r.yaml")])
    line = _error_line(capsys)
    assert rc == 2 and "blank.png" in line and "right image" in line


def test_target_with_a_wrong_field(box_pair, tmp_path, capsys):
    d, _ = box_pair
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: x\nboards:\n  - name: a\n    inner_corners: [4, 5]\n    square_mm: -3\n")
    rc = main(["calibrate", "--target", str(bad), "--left", str(d / "L.png"), "--out", str(tmp_path / "r.yaml")])
    assert rc == 2 and "boards[0].square_mm" in _error_line(capsys)


def test_board_needs_square_size(box_pair, tmp_path, capsys):
    d, _ = box_pair
    rc = main(["calibrate", "--board", "9x6", "--left", str(d / "L.png"), "--out", str(tmp_path / "r.yaml")])
    assert rc == 2 and "--square-mm" in _error_line(capsys)


# ../shared beside the repository (as in CI)
REAL = __import__("pathlib").Path(__file__).resolve().parents[2] / "shared" / "data" / "real" / "opencv_stereo_9x6"


@pytest.mark.skipif(not REAL.is_dir(), reason="shared real data not present")
def test_planar_stereo_cli_on_bouguet_pairs(tmp_path, capsys):
    """Planar multi-view through the CLI with edgecal's own detector, on 6 pairs of Bouguet's set."""
    names = ["01", "02", "03", "06", "07", "08"]
    out = tmp_path / "rig.yaml"
    rc = main(["calibrate", "--board", "9x6", "--square-mm", "30",
               "--left", *[str(REAL / f"left{n}.jpg") for n in names],
               "--right", *[str(REAL / f"right{n}.jpg") for n in names], "--out", str(out)])
    assert rc == 0, capsys.readouterr()
    rig = load_rig(out)
    assert abs(rig.cameras[0].camera_matrix[0, 0] - 533.0) < 15.0
    assert abs(np.linalg.norm(rig.stereo.t_right_left_m) - 0.0998) < 0.002
