"""`edgecal collect` on replays of rendered hand-held sessions (consecutive, overlapping frames): it keeps
few views, the calibration from them is as accurate as from every frame, it stops at full coverage, and
what it writes is what `edgecal calibrate --left DIR` reads."""

import json
import shlex

import cv2
import numpy as np
import pytest

from edgecal.calibration.collection import Coverage, motion_px, view_measures
from edgecal.calibration.views import corner_set
from edgecal.cli import main
from edgecal.synth.handheld import handheld_rig, handheld_sequence
from edgecal.targets import parse_board_spec


def _render(folder, rig, seed, **kw):
    stereo = rig.right is not None
    for sub in (("left", "right") if stereo else (".",)):
        (folder / sub).mkdir(parents=True, exist_ok=True)
    n = 0
    for f in handheld_sequence(seed, rig, **kw):
        if stereo:
            cv2.imwrite(str(folder / "left" / f"{f.index:04d}.png"), f.left.image)
            cv2.imwrite(str(folder / "right" / f"{f.index:04d}.png"), f.right.image)
        else:
            cv2.imwrite(str(folder / f"{f.index:04d}.png"), f.left.image)
        n += 1
    return n


def _collect(capsys, source, out, *extra):
    rc = main(["collect", f"replay:{source}?pace=fast", "--board", "9x6", "--square-mm", "30", "--out", str(out),
               *extra])
    cap = capsys.readouterr()
    assert rc == 0, cap.err
    return cap.out.strip().splitlines(), cap.err


def _calibrate_json(capsys, argv):
    assert main(argv + ["--json"]) == 0
    return json.loads(capsys.readouterr().out)


@pytest.fixture(scope="module")
def mono_session(tmp_path_factory):
    d = tmp_path_factory.mktemp("session")
    rig = handheld_rig(11, stereo=False)
    n = _render(d, rig, 11, n_poses=14, hold_frames=3, move_frames=3)
    return d, rig, n


def test_keeps_few_views_as_accurate_as_all_frames(mono_session, tmp_path, capsys):
    d, rig, n_frames = mono_session
    out = tmp_path / "views"
    lines, err = _collect(capsys, d, out)
    kept = [ln for ln in lines if ln.startswith("kept ")]
    assert 6 <= len(kept) <= n_frames // 4, (len(kept), n_frames)
    assert all("X [" in ln and "skew [" in ln for ln in kept)
    assert f"kept {len(kept)} of " in err and "moving" in err and "near-duplicate" in err
    assert kept[-1].endswith("coverage complete") and "stopped: coverage is complete" in err
    assert int(err.split(f"kept {len(kept)} of ")[1].split()[0]) < n_frames  # it stopped before the end
    command = lines[-1]
    assert command.startswith("edgecal calibrate --board 9x6 --square-mm 30 --left ")
    argv = shlex.split(command)[1:] + ["--force"]  # the printed command, as a user would paste it
    from_kept = _calibrate_json(capsys, argv)
    assert [v["view"] for v in from_kept["views"]] == [f"{i:06d}.png" for i in range(len(kept))]
    from_all = _calibrate_json(capsys, ["calibrate", "--board", "9x6", "--square-mm", "30", "--left", str(d),
                                        "--out", str(tmp_path / "all.yaml")])
    assert len(from_all["views"]) == n_frames
    truth = dict(zip(("fx", "fy", "cx", "cy"), (rig.left.fx, rig.left.fy, rig.left.cx,
                                                 rig.left.cy)))
    for name, value in truth.items():
        k, a = from_kept["cameras"]["camera"][name], from_all["cameras"]["camera"][name]
        # as accurate: no further from the truth than every frame's result, within the kept result's own 3 sigma
        assert abs(k["value"] - value) <= abs(a["value"] - value) + 3 * k["std"], (name, k, a, value)
        assert abs(k["value"] - value) < 1.0


def test_stereo_pairs_collected_and_calibrated(tmp_path, capsys):
    d = tmp_path / "session"
    rig = handheld_rig(4, stereo=True)
    n_frames = _render(d, rig, 4, n_poses=12, hold_frames=3, move_frames=2)
    out = tmp_path / "views"
    lines, err = _collect(capsys, d, out, "--calibrate")
    kept = [ln for ln in lines if ln.startswith("kept ")]
    assert 6 <= len(kept) <= 12 and f"kept {len(kept)} of {n_frames} frames" in err
    assert "stopped: the source ended" in err and "coverage is not complete: " in err
    assert (out / "left").is_dir() and (out / "right").is_dir() and (out / "rig.yaml").is_file()
    assert (out / "report" / "summary.txt").is_file()
    assert "|T| = 80.0" in "\n".join(lines)  # the calibration at the end found the 80 mm baseline


def test_max_views_and_no_board(tmp_path, capsys):
    d = tmp_path / "session"
    rig = handheld_rig(2, stereo=False)
    _render(d, rig, 2, n_poses=6, hold_frames=3, move_frames=2)
    lines, err = _collect(capsys, d, tmp_path / "views", "--max-views", "2")
    assert len([ln for ln in lines if ln.startswith("kept ")]) == 2 and "(--max-views)" in err
    blank = tmp_path / "blank"
    blank.mkdir()
    for i in range(3):
        cv2.imwrite(str(blank / f"{i}.png"), np.full((480, 640), 128, np.uint8))
    rc = main(["collect", f"replay:{blank}?pace=fast", "--board", "9x6", "--square-mm", "30", "--out",
               str(tmp_path / "none")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and err[-1].startswith("edgecal: error: ") and "3 no board" in err[-1]


def test_measures_follow_ros_and_duplicates_are_skipped():
    target = parse_board_spec("9x6", 30)
    board = target.boards[0]
    ids = board.ids()
    size = (640, 480)
    # a fronto-parallel board in the middle: X = Y = 0.5, skew 0
    px = 200 + ids * [30.0, 30.0]
    cs = corner_set(target, [(board.name, int(c), int(r)) for c, r in ids], px)
    m = view_measures(cs, target, size)
    border = np.sqrt(240.0 * 150.0)
    assert np.isclose(m[0], (320 - border / 2) / (640 - border)) and abs(m[3]) < 1e-9
    assert np.isclose(m[2], np.sqrt(240 * 150 / (640 * 480)))
    cov = Coverage(1)
    cov.add(m[None])
    assert not cov.adds(m[None] + 0.01) and cov.adds(m[None] + [0.3, 0, 0, 0])
    assert "move it further left" in cov.missing() or "move it further right" in cov.missing()
    moved = corner_set(target, list(cs.keys), px + [0.4, 0.0])
    assert np.isclose(motion_px(cs, moved), 0.4) and motion_px(None, cs) == np.inf


def test_blurred_and_moved_boards_are_not_sharp():
    from edgecal.calibration.collection import edge_width_px, is_sharp, square_px
    from edgecal.commands.collect import Collector
    target = parse_board_spec("9x6", 30)
    rig = handheld_rig(11, stereo=False)
    frame = next(iter(handheld_sequence(11, rig, n_poses=1, hold_frames=1, move_frames=0)))
    cs = Collector(target, 1).consider([frame.left.image]).corners[0]
    assert len(cs) == 54
    sharp = edge_width_px(frame.left.image, cs, target)
    assert is_sharp(sharp, square_px(cs))
    blurred = cv2.GaussianBlur(frame.left.image, (0, 0), 1.5)
    assert not is_sharp(edge_width_px(blurred, cs, target), square_px(cs))
    streak = cv2.filter2D(frame.left.image, -1, np.full((1, 9), 1 / 9))  # 9 px of horizontal motion
    assert not is_sharp(edge_width_px(streak, cs, target), square_px(cs))


def test_small_squares_opencv_cannot_measure_are_not_called_blurred():
    """estimateChessboardSharpness answers 9999 on a far, tilted board (14 px squares): that was counted as a
    blurred board, and such views were never kept."""
    from edgecal.calibration.collection import edge_width_px, is_sharp, square_px
    from edgecal.commands.collect import Collector
    target = parse_board_spec("9x6", 30)
    rig = handheld_rig(5, stereo=True)
    frame = next(f for f in handheld_sequence(5, rig, n_poses=30) if f.index == 18)
    cs = Collector(target, 1).consider([frame.left.image]).corners[0]
    assert len(cs) == 54 and square_px(cs) < 16
    width = edge_width_px(frame.left.image, cs, target)
    assert is_sharp(width, square_px(cs)), width


def test_box_collect_keeps_the_first_still_view_of_every_face_and_calibrates(tmp_path, capsys):
    """A box's faces are strongly foreshortened: their sharp edges used to measure as blurred (3.8 px)."""
    from edgecal.config import packaged_config_path
    from edgecal.synth.scenes import box_stereo
    view = box_stereo(1, size=(800, 600), photometric="clean", supersampling=6)
    for sub in ("left", "right"):
        (tmp_path / "session" / sub).mkdir(parents=True)
    for i in range(3):  # the box held still for three frames
        cv2.imwrite(str(tmp_path / "session" / "left" / f"{i}.png"), view.left.image)
        cv2.imwrite(str(tmp_path / "session" / "right" / f"{i}.png"), view.right.image)
    box = str(packaged_config_path("targets/box-100mm.yaml"))
    rc = main(["collect", f"replay:{tmp_path / 'session'}?pace=fast", "--target", box, "--out",
               str(tmp_path / "views"), "--calibrate"])
    cap = capsys.readouterr()
    assert rc == 0, cap.err
    assert "kept 1 of 2 frames (1 moving) into" in cap.err and "stopped: the box view was kept" in cap.err
    assert f"edgecal calibrate --target {box} --left {tmp_path / 'views'}" in cap.out
    assert "3-D reconstruction error" in cap.out and (tmp_path / "views" / "rig.yaml").is_file()
