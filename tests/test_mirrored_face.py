"""A box face described mirrored (x_axis × y_axis out of the box, or x/y swapped): the refusal says which
face and what to write in the target file."""

import cv2
import numpy as np
import pytest
import yaml

from edgecal.calibration.mirror import mirrored_faces
from edgecal.cli import main
from edgecal.config import packaged_config_path
from edgecal.geometry import triangulate_rays
from edgecal.synth.scenes import box_stereo
from edgecal.targets import load_target

BOX = packaged_config_path("targets/box-100mm.yaml")


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    d = tmp_path_factory.mktemp("mirror")
    view = box_stereo(7, size=(800, 600), photometric="clean", supersampling=6)
    cv2.imwrite(str(d / "L.png"), view.left.image)
    cv2.imwrite(str(d / "R.png"), view.right.image)
    return d


def _target_with(d, name, change):
    doc = yaml.safe_load(BOX.read_text())
    change(doc["boards"])
    path = d / f"{name}.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


def _refusal(capsys, d, target):
    rc = main(["calibrate", "--target", str(target), "--left", str(d / "L.png"), "--right", str(d / "R.png"),
               "--out", str(d / "rig.yaml")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 4 and err[-1].startswith("edgecal: error: calibration refused"), err
    return err[-1]


def test_reversed_x_axis_is_named_with_the_fix(pair, capsys):
    def flip_side(boards):  # "side" printed the other way round: x reversed, origin at the other end
        boards[1]["x_axis"] = [0, -1, 0]
        boards[1]["origin_mm"] = [0.0, 71.0, 22.0]
    target = _target_with(pair, "flipped", flip_side)
    line = _refusal(capsys, pair, target)
    assert "board 'side' looks mirrored" in line
    assert "x_axis [0, 1, 0] and origin_mm [0, 29, 22]" in line and f"boards[1] in {target}" in line


def test_swapped_axes_are_named(pair, capsys):
    def swap_front(boards):
        boards[2]["x_axis"], boards[2]["y_axis"] = boards[2]["y_axis"], boards[2]["x_axis"]
    line = _refusal(capsys, pair, _target_with(pair, "swapped", swap_front))
    assert "board 'front' looks mirrored" in line and "x_axis [1, 0, 0] and y_axis [0, 0, -1] (swapped)" in line


def test_a_correct_target_gets_no_hint(pair, tmp_path, capsys):
    cfg = tmp_path / "strict.yaml"
    cfg.write_text("acceptance:\n  max_rms_px: 0.0001\n")
    rc = main(["calibrate", "--target", str(BOX), "--left", str(pair / "L.png"), "--right", str(pair / "R.png"),
               "--out", str(tmp_path / "rig.yaml"), "--config", str(cfg)])
    assert rc == 4 and "mirrored" not in capsys.readouterr().err


def test_mirrored_variants_cover_the_same_face():
    for board in load_target(BOX).boards:
        variants = [v for _, v in mirrored_faces(board)]
        for variant in variants[:2]:  # reversed x or y: the same corners, numbered the other way
            same = {tuple(p) for p in np.round(board.target_points_mm(), 9)}
            assert same == {tuple(p) for p in np.round(variant.target_points_mm(), 9)}
        for variant in variants:
            assert np.allclose(variant.normal, -board.normal)  # a mirror image: the normal flips


def test_triangulating_a_ray_that_is_not_finite_gives_nan_not_a_crash():
    """A bad fit (a mirrored face) left rays the lens could not unproject: the SVD failed with a traceback."""
    vl = np.array([[0.0, 0.0, 1.0], [np.nan, np.nan, np.nan]])
    vr = np.array([[-0.1, 0.0, 1.0], [0.1, 0.0, 1.0]])
    p = triangulate_rays(vl, vr, np.eye(3), np.array([-100.0, 0.0, 0.0]))
    assert np.allclose(p[0], [0.0, 0.0, 1000.0]) and np.all(np.isnan(p[1]))
