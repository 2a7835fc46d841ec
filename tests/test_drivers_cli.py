"""edgecal record / capture / sources on rendered frames (no camera needed)."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from edgecal.cli import main
from edgecal.drivers import open_source

from .driver_frames import render_frame


def _board_image(shift: int) -> np.ndarray:
    """A 10x7-square chessboard (9x6 inner corners) on white, shifted by ``shift`` px."""
    img = np.full((240, 320), 255, np.uint8)
    for r in range(7):
        for c in range(10):
            if (r + c) % 2 == 0:
                img[30 + r * 25:55 + r * 25, 20 + c * 25 + shift:45 + c * 25 + shift] = 0
    return img


@pytest.fixture(autouse=True)
def _depthai_quiet(monkeypatch: pytest.MonkeyPatch) -> None:
    # `edgecal sources` asks depthai for devices: no telemetry, a short USB-only search.
    for key, value in (("DEPTHAI_TELEMETRY", "0"), ("DEPTHAI_SEARCH_TIMEOUT", "300"), ("DEPTHAI_PROTOCOL", "usb"),
                       ("DEPTHAI_LEVEL", "off")):
        monkeypatch.setenv(key, value)


@pytest.fixture
def board_folder(tmp_path: Path) -> Path:
    folder = tmp_path / "imgs"
    folder.mkdir()
    for i in range(4):
        cv2.imwrite(str(folder / f"{i:02d}.png"), _board_image(i))
    return folder


def test_capture_prints_timestamps_and_detections(board_folder: Path, tmp_path: Path,
                                                  capsys: pytest.CaptureFixture) -> None:
    assert main(["capture", f"replay:{board_folder}?pace=fast&fps=25", "--frames", "3", "--board", "9x6",
                 "--json", "--out", str(tmp_path / "rec")]) == 0
    rows = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert [r["stamp_ns"] for r in rows] == [0, 40_000_000, 80_000_000]
    assert rows[1]["interval_ms"] == 40.0 and rows[0]["size"] == "320x240"
    board = {"board": "chessboard-9x6", "copy": 0, "corners": 54, "of": 54, "complete": True}
    assert all(r["boards"] == [board] for r in rows)
    with open_source(f"replay:{tmp_path / 'rec'}?pace=fast") as rec:   # --out wrote a replayable recording
        assert [f.stamp_ns for f in rec] == [0, 40_000_000, 80_000_000]


def test_capture_text_output_without_a_target(board_folder: Path, capsys: pytest.CaptureFixture) -> None:
    assert main(["capture", f"replay:{board_folder}?pace=fast", "--frames", "2"]) == 0
    out = capsys.readouterr().out
    assert "seq=1 stamp_ns=33333333 +33.33ms" in out and "detection skipped" in out


def test_record_then_replay_is_bit_exact(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    src = tmp_path / "src"
    src.mkdir()
    frames = [render_frame(i, (30, 40, 3)) for i in range(5)]
    for i, f in enumerate(frames):
        cv2.imwrite(str(src / f"{i}.png"), f)
    assert main(["record", f"replay:{src}?pace=fast&fps=10", "--out", str(tmp_path / "rec"), "--frames", "4"]) == 0
    assert "recorded 4 frames" in capsys.readouterr().err
    with open_source(f"replay:{tmp_path / 'rec'}?pace=fast") as rep:
        got = list(rep)
    assert [f.stamp_ns for f in got] == [0, 100_000_000, 200_000_000, 300_000_000]
    assert all(np.array_equal(a, b.image) for a, b in zip(frames, got))
    manifest = json.loads((tmp_path / "rec" / "manifest.json").read_text())
    assert manifest["source"]["uri"] == f"replay:{src}" and manifest["source"]["settings"]["fps"] == 10.0
    # An existing recording is never overwritten without --force: exit code 2 and one line.
    assert main(["record", f"replay:{src}?pace=fast", "--out", str(tmp_path / "rec")]) == 2
    assert "not empty" in capsys.readouterr().err


def test_bad_source_uri_is_one_line(capsys: pytest.CaptureFixture) -> None:
    assert main(["capture", "replay:x?pace=slow"]) == 2
    assert capsys.readouterr().err.strip() == (
        "edgecal: error: source URI 'replay:x?pace=slow': "
        "field 'pace' must be one of recorded, fast, realtime (got 'slow')")


def test_sources_without_network(capsys: pytest.CaptureFixture) -> None:
    assert main(["sources", "--no-network", "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    drivers = {d["driver"]: d for d in data["drivers"]}
    assert set(drivers) == {"replay", "v4l2", "aravis", "dc1394", "depthai"}
    assert drivers["replay"]["usable"] and all(isinstance(d["why"], str) for d in drivers.values())
