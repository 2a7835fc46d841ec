"""bench/detect.py's adapters and bookkeeping on one image edgecal renders itself (no shared data).

Timing is not tested here; these tests check that each reference detector's corner order is read
correctly (a wrong layout would score every board as not found) and that results are written safely.
"""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import numpy as np
import pytest

from edgecal.errors import InputError
from edgecal.scoring import score_image
from edgecal.synth.scenes import planar_view
from edgecal.synth.truth import ground_truth_from_mapping

BENCH = Path(__file__).resolve().parents[1] / "bench" / "detect.py"


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location("bench_detect", BENCH)
    module = importlib.util.module_from_spec(spec)
    sys.modules["bench_detect"] = module  # dataclasses look their module up there
    try:
        spec.loader.exec_module(module)
        yield module
    finally:
        sys.modules.pop("bench_detect", None)


@pytest.fixture(scope="module")
def item(bench):
    view = planar_view(11, size=(640, 480), cols=7, rows=5, square_px=32.0, tilt_max_deg=30.0,
                       photometric="clean", background="uniform")
    truth = ground_truth_from_mapping(view.truth, "planar_view(11)")
    target = bench._target_from_boards(view.truth["target"]["boards"], "7x5")
    return bench.Item("planar_11", view.image, target, truth)


@pytest.mark.parametrize("name", ["opencv", "opencv_sb", "libcbdetect", "calib_targets"])
def test_reference_adapter_reads_the_corner_order(bench, item, name):
    if name == "libcbdetect":
        pytest.importorskip("libCBDetect")
    if name == "calib_targets":
        pytest.importorskip("calib_targets")
    (det,) = bench.load_detectors([name])
    assert det.run is not None, det.status
    found, reported = det.run(item.grey, item.target)
    assert reported >= 1 and len(found) == 1
    score = score_image(found, item.truth, policy="grid")
    assert score.n_found == 1 and score.false_boards == 0
    assert score.found_errors().max() < 0.5


def test_run_one_scores_and_times(bench, item):
    (det,) = bench.load_detectors(["opencv"])
    result = bench.run_one(det, item, repeat=2)
    assert result.ms > 0 and result.score.n_found == 1 and result.grids == [(7, 5)]
    sr = bench.SetResult("opencv", [result])
    summary = sr.summary()
    assert summary["found"] == 1 and summary["truth_boards"] == 1 and summary["false_boards"] == 0
    table = bench.format_table(bench.BenchSet("one", [item]), {"opencv": sr})
    assert "opencv" in table and "1/1" in table


def test_plausibility_is_used_without_truth(bench, item):
    (det,) = bench.load_detectors(["opencv"])
    blind = bench.Item(item.name, item.grey, item.target, None, expect=(7, 5))
    assert bench.run_one(det, blind, repeat=1).plausible is True
    wrong = bench.Item(item.name, item.grey, item.target, None, expect=(8, 5))
    assert bench.run_one(det, wrong, repeat=1).plausible is False


def test_missing_package_is_reported_not_fatal(bench, monkeypatch):
    import builtins

    real_import = builtins.__import__

    def no_checkerboard(name, *args, **kwargs):
        if name == "checkerboard":
            raise ImportError("No module named 'checkerboard'")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_checkerboard)
    (det,) = bench.load_detectors(["checkerboard"])
    assert det.run is None and "unavailable" in det.status


def test_json_is_written_atomically_and_not_clobbered(bench, tmp_path):
    out = tmp_path / "r.json"
    bench.write_json_atomic(out, {"a": 1}, force=False)
    assert json.loads(out.read_text()) == {"a": 1}
    with pytest.raises(bench.EdgecalError, match="--force"):
        bench.write_json_atomic(out, {"a": 2}, force=False)
    bench.write_json_atomic(out, {"a": 2}, force=True)
    assert json.loads(out.read_text()) == {"a": 2}
    assert [p.name for p in tmp_path.iterdir()] == ["r.json"]


def test_main_rejects_unknown_detector(bench, capsys):
    assert bench.main(["--detectors", "nope", "--sets", "none"]) == 2
    assert "unknown detector" in capsys.readouterr().err


def test_calib_targets_counts_only_grids_of_the_asked_size(bench, item):
    pytest.importorskip("calib_targets")
    (det,) = bench.load_detectors(["calib_targets"])
    other = bench._target_from_boards([{"name": "b", "cols": 6, "rows": 5}], "6x5")
    found, reported = det.run(item.grey, other)
    assert found == [] and reported == 0


def test_load_opencv_corners_dat(bench, tmp_path):
    r, c = np.mgrid[0:2, 0:3]
    ids = np.stack([c.ravel(), r.ravel()], axis=1)  # row-major (col, row), as OpenCV lists them
    xy = 100.0 + ids * np.array([20.0, 18.0]) + ids[:, ::-1] * np.array([-4.0, 3.0])
    flat = ", ".join(f"{v:.6e}" for v in xy.ravel())
    p = tmp_path / "c.dat"
    p.write_text(f"isFound: 1\ncorners:\n   rows: 2\n   cols: 3\n   data: [ {flat} ]\n")
    gt = bench.load_opencv_corners_dat(p, "c.png", (320, 240), 3, 2)
    assert not gt.exact
    assert np.allclose(gt.boards[0].corners, xy, atol=1e-5)
    assert (gt.boards[0].ids == ids).all()
    with pytest.raises(InputError, match="expected 10"):
        bench.load_opencv_corners_dat(p, "c.png", (320, 240), 5, 1)


def test_load_ocamcalib_json_puts_the_cols_axis_first(bench, tmp_path):
    # 3 x 2 inner corners, the board's Y axis carries the 3 columns (as in Fisheye190Pts.json)
    pts, xyz = [], []
    for x in range(2):
        for y in range(3):
            xyz.append([x * 30.0, y * 30.0, 0.0])
            pts.append([10.0 + 20 * y, 5.0 + 20 * x])
    data = {"inner_corners": [3, 2], "square_mm": 30,
            "views": [{"image": "v1.jpg", "points_xy_zero_based": pts, "board_XYZ_mm": xyz}]}
    p = tmp_path / "pts.json"
    p.write_text(json.dumps(data))
    refs = bench.load_ocamcalib_json(p)
    board = refs["v1.jpg"].boards[0]
    assert (board.cols, board.rows) == (3, 2)
    assert board.ids[:, 0].max() == 2 and board.ids[:, 1].max() == 1
    assert np.allclose(board.corners[board.ids[:, 0] == 2][:, 0], 50.0)


def test_noisy_copies_keep_truth_and_differ_by_the_noise(bench, item) -> None:
    sets = [bench.BenchSet("rendered/x", [item], "note"), bench.BenchSet("timing/x", [item], timing_only=True)]
    (noisy,) = bench.with_added_noise(sets, 2.0, 3)
    assert noisy.name == "rendered/x +noise 2" and [it.name for it in noisy.items] == [f"{item.name}~{k}"
                                                                                      for k in range(3)]
    diffs = [it.grey.astype(float) - item.grey for it in noisy.items]
    assert all(it.truth is item.truth and it.grey.dtype == np.uint8 for it in noisy.items)
    assert all(1.6 < d.std() < 2.4 for d in diffs) and not np.array_equal(diffs[0], diffs[1])
    again = bench.with_added_noise(sets, 2.0, 3)[0]
    assert all(np.array_equal(a.grey, b.grey) for a, b in zip(noisy.items, again.items))  # seeded


def test_the_noise_option_rejects_absurd_values(bench, capsys) -> None:
    assert bench.main(["--noise", "-1", "--detectors", "edgecal"]) == 2
    assert "--noise must be 0-64" in capsys.readouterr().err
