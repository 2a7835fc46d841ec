"""What `edgecal calibrate` says about its result: views named by file (natural order), --json, the
provenance in rig.yaml, the corners file and --corners re-solving, --camera-name; `edgecal --version` and
plain --help text."""

import json
import re

import cv2
import numpy as np
import pytest
import yaml

from edgecal.calibration.io import load_rig
from edgecal.calibration.views import corners_path
from edgecal.cli import build_parser, main
from edgecal.synth.handheld import handheld_rig, handheld_sequence

NUMBERS = [1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11]  # 10 and 11 sort after 9 only in natural order


@pytest.fixture(scope="module")
def views(tmp_path_factory):
    """Eleven stereo views of a 9x6 board (30 mm squares), files left1.png .. left11.png, and the rig."""
    d = tmp_path_factory.mktemp("views")
    rig = handheld_rig(3, stereo=True)
    (d / "left").mkdir()
    (d / "right").mkdir()
    frames = handheld_sequence(3, rig, n_poses=len(NUMBERS), hold_frames=1, move_frames=0)
    for n, f in zip(NUMBERS, frames):
        cv2.imwrite(str(d / "left" / f"left{n}.png"), f.left.image)
        cv2.imwrite(str(d / "right" / f"right{n}.png"), f.right.image)
    # one view without a board, to be named as skipped
    blank = np.full_like(f.left.image, 120)
    cv2.imwrite(str(d / "left" / "left12.png"), blank)
    cv2.imwrite(str(d / "right" / "right12.png"), blank)
    return d, rig


def _calibrate(d, out, *extra):
    return main(["calibrate", "--board", "9x6", "--square-mm", "30", "--left", str(d / "left"),
                 "--right", str(d / "right"), "--out", str(out), *extra])


def test_json_names_every_view_by_file_in_natural_order(views, tmp_path, capsys):
    d, rig = views
    out = tmp_path / "rig.yaml"
    assert _calibrate(d, out, "--json") == 0
    cap = capsys.readouterr()
    doc = json.loads(cap.out)  # stdout is exactly one JSON object
    assert doc["verdict"] == "accepted" and doc["problems"] == []
    assert [v["view"] for v in doc["views"]] == [f"left{n}.png" for n in NUMBERS + [12]]
    assert doc["views"][0]["files"] == [str(d / "left" / "left1.png"), str(d / "right" / "right1.png")]
    skipped = doc["views"][-1]
    assert not skipped["used"] and "board not found" in skipped["why_not"]
    assert all(v["used"] and v["rms_px"]["left"] < 0.5 and v["corners"]["right"] == 54 for v in doc["views"][:-1])
    assert "left12.png: skipped, board not found in either image" in cap.err
    fx = doc["cameras"]["left"]["fx"]
    assert abs(fx["value"] / rig.left.fx - 1) < 0.01 and fx["std"] > 0
    assert doc["cameras"]["left"]["distortion"]["k3"]["std"] is None  # fixed in the k1k2 model: null, not NaN
    assert abs(doc["stereo"]["baseline_mm"] - 80.0) < 1.0
    assert doc["bounds"]["max_rms_px"] == 1.0 and doc["rms_px"] < 0.5


def test_provenance_corners_file_and_resolve(views, tmp_path, capsys):
    d, rig = views
    out = tmp_path / "rig.yaml"
    assert _calibrate(d, out, "--camera-name", "stereo_left", "stereo_right") == 0
    text = capsys.readouterr().out
    assert f"wrote {corners_path(out)}" in text
    prov = load_rig(out).provenance
    assert prov["target"] == "chessboard-9x6" and prov["square_mm"] == 30.0
    assert prov["boards"][0]["inner_corners"] == [9, 6]
    assert [v["files"][0] for v in prov["views"]][:3] == [str(d / "left" / f"left{n}.png") for n in (1, 2, 3)]
    assert prov["views"][-1]["used"] == 0
    assert re.fullmatch(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\dZ", prov["created"])
    assert prov["edgecal_version"] and prov["settings"]["refine"]["distortion"] == "k1k2"
    info = yaml.safe_load((tmp_path / "rig.right.camera_info.yaml").read_text())
    assert info["camera_name"] == "stereo_right"
    # one row per corner: view, camera, file, board, col, row, x, y (+ a row for the view with no board)
    rows = [r for r in corners_path(out).read_text().splitlines() if not r.startswith("#")]
    assert rows[0] == "view,camera,file,board,col,row,x,y,cov_xx,cov_xy,cov_yy"
    assert len(rows) == 1 + 11 * 2 * 54 + 2
    # re-solve from the corners file alone, no images needed
    for p in (d / "left").iterdir():
        p.rename(p.with_suffix(".moved"))
    try:
        out2 = tmp_path / "again.yaml"
        assert main(["calibrate", "--board", "9x6", "--square-mm", "30", "--corners", str(corners_path(out)),
                     "--out", str(out2), "--json"]) == 0
        doc = json.loads(capsys.readouterr().out)
    finally:
        for p in (d / "left").iterdir():
            p.rename(p.with_suffix(".png"))
    a, b = load_rig(out), load_rig(out2)
    assert np.allclose(a.cameras[0].camera_matrix, b.cameras[0].camera_matrix, rtol=1e-5)
    assert np.allclose(a.stereo.t_right_left_m, b.stereo.t_right_left_m, atol=1e-6)  # corners kept to 1e-4 px
    assert doc["provenance"]["corners_file"] == str(corners_path(out))
    assert not corners_path(out2).exists()  # a re-solve does not copy its corners


def test_refused_json_is_still_one_object(views, tmp_path, capsys):
    d, _ = views
    cfg = tmp_path / "strict.yaml"
    cfg.write_text("acceptance:\n  max_rms_px: 0.001\n")
    out = tmp_path / "rig.yaml"
    assert _calibrate(d, out, "--json", "--config", str(cfg)) == 4
    cap = capsys.readouterr()
    doc = json.loads(cap.out)
    assert doc["verdict"] == "refused" and "reprojection RMS" in doc["problems"][0]
    assert not out.exists() and not corners_path(out).exists()
    assert cap.err.strip().splitlines()[-1].startswith("edgecal: error: calibration refused")


def test_bad_corners_file_is_one_line(views, tmp_path, capsys):
    bad = tmp_path / "c.csv"
    bad.write_text("# edgecal-corners/1\n# image_size: 640 480\n# cameras: camera\n"
                   "view,camera,file,board,col,row,x,y\nv1.png,camera,v1.png,chessboard-9x6,12,0,1,2\n")
    rc = main(["calibrate", "--board", "9x6", "--square-mm", "30", "--corners", str(bad), "--out",
               str(tmp_path / "r.yaml")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "line 5: corner (12,0) is outside board" in err[0]


def test_camera_name_count_must_match(views, tmp_path, capsys):
    d, _ = views
    assert _calibrate(d, tmp_path / "r.yaml", "--camera-name", "only_one") == 2
    assert "one name per camera (2)" in capsys.readouterr().err


def test_version_and_plain_help(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    from edgecal import __version__
    assert capsys.readouterr().out.strip() == f"edgecal {__version__}"
    parser = build_parser()
    sub = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction")
    for name, p in sub.choices.items():
        text = p.format_help()
        assert "``" not in text and ":func:" not in text and ":class:" not in text, name
