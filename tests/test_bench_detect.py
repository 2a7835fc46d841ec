"""bench/detect.py's adapters and bookkeeping on one image edgecal renders itself (no shared data).

Timing is not tested here; these tests check that each reference detector's corner order is read
correctly (a wrong layout would score every board as not found) and that results are written safely.
"""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import pytest

from edgecal.evaluate import ground_truth_from_mapping, score_image
from edgecal.synth.scenes import planar_view

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
