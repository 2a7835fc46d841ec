"""Aravis against a real GigE Vision fake camera on loopback (arv-fake-gv-camera-0.8), opened by IP.

The fake camera listens on 127.0.0.1 only (never a network scan). One fake camera can own the GigE
Vision port at a time, so the fixture holds a file lock while its camera runs. These tests must run in
CI (``make test`` installs the Debian packages and PyGObject); they skip only outside CI.
"""

from __future__ import annotations

import json
import time

import numpy as np
import pytest

from edgecal.drivers import open_source
from edgecal.errors import DeviceAbsent, DeviceError, DeviceTimeout

from .aravis_fake import FakeCamera, require_aravis


def test_stream_from_the_fake_gige_camera(fake_camera: FakeCamera) -> None:
    with open_source("aravis:127.0.0.1?fps=50&width=320&height=240&timeout_s=2&packet_size=1000") as src:
        frames = [src.read() for _ in range(8)]
        info = src.describe()
    assert info["device"]["device_id"] == "EDGECAL" and info["pixel_format"] == "Mono8"
    assert info["device"]["packet_size"] == 1000    # ~80 GVSP packets per frame, reassembled
    assert all(f.image.shape == (240, 320) and f.image.dtype == np.uint8 for f in frames)
    assert all(f.image.std() > 0 for f in frames)               # a real test pattern, not zeros
    stamps = np.array([f.stamp_ns for f in frames])
    assert np.all(np.diff(stamps) > 0)
    assert 10e6 < np.median(np.diff(stamps)) < 30e6          # 50 fps -> 20 ms from the device's clock
    now = time.monotonic_ns()
    assert all(0 <= now - f.stamp_ns < 5e9 and f.stamp_ns <= f.recv_ns + 1e6 for f in frames)  # monotonic clock
    seqs = [f.seq for f in frames]
    assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs)


def test_exposure_change_while_streaming(fake_camera: FakeCamera) -> None:
    with open_source("aravis:127.0.0.1?fps=50&exposure_us=2000&gain_db=1") as src:
        before = [src.read() for _ in range(3)]
        assert before[-1].exposure_us == pytest.approx(2000) and before[-1].gain_db == pytest.approx(1)
        applied = src.set_exposure_us(8000)
        assert applied == pytest.approx(8000)
        after = [src.read() for _ in range(6)]
    assert after[-1].exposure_us == pytest.approx(8000)
    # The fake sensor's brightness follows the exposure: the last frames are brighter.
    assert after[-1].image.mean() > before[-1].image.mean() + 5


@pytest.mark.parametrize("fmt, dtype, ndim", [("Mono16", np.uint16, 2), ("BayerRG8", np.uint8, 3),
                                               ("RGB8", np.uint8, 3)])
def test_pixel_formats_are_converted(fake_camera: FakeCamera, fmt: str, dtype: type, ndim: int) -> None:
    with open_source(f"aravis:127.0.0.1?fps=50&width=128&height=96&pixel_format={fmt}") as src:
        f = src.read()
    assert f.image.dtype == dtype and f.image.ndim == ndim and f.image.shape[:2] == (96, 128)


def test_software_and_hardware_triggers(fake_camera: FakeCamera) -> None:
    with open_source("aravis:127.0.0.1?trigger=software&timeout_s=1") as src:
        seqs = []
        for _ in range(3):
            seqs.append(src.read().seq)
            time.sleep(0.15)     # free running at 25 fps, ~4 frames would pass meanwhile
    assert seqs == [seqs[0], seqs[0] + 1, seqs[0] + 2]   # one frame per trigger, none in between
    with open_source("aravis:127.0.0.1?trigger=hardware&timeout_s=0.4") as src:
        t0 = time.monotonic()
        with pytest.raises(DeviceTimeout, match=r"no frame within 0.4 s .*waiting for a trigger"):
            src.read()           # no pulse on Line1: a clear error after the timeout
        assert time.monotonic() - t0 < 1.5


def test_close_releases_the_camera_for_the_next_user(fake_camera: FakeCamera) -> None:
    for _ in range(2):   # the second open needs the control channel the first one held
        with open_source("aravis:127.0.0.1?fps=50") as src:
            assert src.read().image.size > 0
    with pytest.raises(RuntimeError, match=r"read\(\) before open\(\)"):     # a bug of the caller's
        src.read()


def test_absent_camera_is_a_clear_error(gv_lock: None) -> None:
    t0 = time.monotonic()
    with pytest.raises(DeviceAbsent, match=r"aravis:127.0.0.1: cannot open the camera .*edgecal sources"):
        with open_source("aravis:127.0.0.1"):
            pass
    assert time.monotonic() - t0 < 5.0


def test_builtin_fake_interface() -> None:
    require_aravis()
    with open_source("aravis:fake?fps=30&width=64&height=48") as src:
        f = src.read()
    assert f.image.shape == (48, 64)


def test_capture_command_on_the_builtin_fake(capsys: pytest.CaptureFixture) -> None:
    require_aravis()
    from edgecal.cli import main
    assert main(["capture", "aravis:fake?fps=50&width=64&height=48", "--frames", "4", "--json"]) == 0
    rows = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert len(rows) == 4 and all(r["size"] == "64x48" for r in rows)
    # A live camera: the age (capture to print) is known and small, intervals follow the 50 fps clock.
    assert all(0 <= r["age_ms"] < 2000 for r in rows)
    assert all(5 < r["interval_ms"] < 60 for r in rows[1:])


@pytest.mark.parametrize("fmt, origin", [("BayerRG8", (0, 0)), ("BayerGR8", (0, 1)), ("BayerGB8", (1, 0)),
                                          ("BayerBG8", (1, 1))])
def test_bayer_patterns_decode_to_the_right_colours(fmt: str, origin: tuple[int, int]) -> None:
    from edgecal.drivers.aravis import convert_buffer
    # A flat scene of B=50, G=100, R=200 seen through the mosaic named by ``fmt``: ``origin`` is where the
    # red site sits in the 2x2 cell (row, col).
    h, w = 8, 8
    mosaic = np.full((h, w), 100, np.uint8)
    ry, rx = origin
    mosaic[ry::2, rx::2] = 200
    mosaic[1 - ry::2, 1 - rx::2] = 50
    bgr = convert_buffer(mosaic.tobytes(), w, h, fmt)
    assert tuple(int(v) for v in bgr[4, 4]) == (50, 100, 200)
    grey16 = convert_buffer(np.arange(12, dtype=np.uint16).tobytes(), 4, 3, "Mono16")
    assert grey16.dtype == np.uint16 and grey16[2, 3] == 11


def test_sources_lists_the_fake_and_probes_by_address(fake_camera: FakeCamera, capsys: pytest.CaptureFixture,
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    from edgecal.cli import main
    for key, value in (("DEPTHAI_TELEMETRY", "0"), ("DEPTHAI_SEARCH_TIMEOUT", "300"), ("DEPTHAI_PROTOCOL", "usb")):
        monkeypatch.setenv(key, value)
    assert main(["sources", "--no-network", "--fake", "--probe", "aravis:127.0.0.1", "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    aravis = next(d for d in data["drivers"] if d["driver"] == "aravis")
    assert aravis["usable"] and any(s["uri"] == "aravis:fake" for s in aravis["sources"])
    assert data["probes"] == [{"uri": "aravis:127.0.0.1", "name": data["probes"][0]["name"], "usable": True,
                               "why": "", "size": "512x512"}]


def test_clock_mapping_keeps_the_device_spacing() -> None:
    from edgecal.drivers.aravis import ClockMapper
    rng = np.random.default_rng(1)
    period, n = 10_000_000, 400
    device = 5_000_000_000_000 + np.arange(n) * period          # a perfectly regular camera clock
    transport = rng.exponential(1_000_000, n) + 300_000          # network delay: >= 0.3 ms, long tail
    recv = 123_000_000 + device - 5_000_000_000_000 + transport.astype(np.int64)
    m = ClockMapper()
    stamps = np.array([m.to_monotonic(int(d), int(r)) for d, r in zip(device, recv)])
    assert np.all(stamps[:30] <= recv[:30])                       # warm-up: an upper bound, never after receipt
    after = np.diff(stamps[30:])
    assert np.abs(after - period).max() <= 20_000 + 200           # slewed by <= 20 us a frame (+ 20 ppm drift)
    true_capture = recv - transport.astype(np.int64)
    # Stamps lag the true capture by the fastest packets' delay (0.3 ms here), no more.
    lag = np.median(stamps[100:] - true_capture[100:])
    assert 300_000 - 20_000 <= lag < 300_000 + 100_000


# Last in this file: it leaves libaravis tearing down a dead session (finished before the test ends).
def test_camera_killed_mid_stream_raises_after_the_timeout(fake_camera: FakeCamera) -> None:
    src = open_source("aravis:127.0.0.1?fps=50&timeout_s=0.5")
    src.open()
    try:
        src.read()
        fake_camera.kill()
        t0 = time.monotonic()
        with pytest.raises(DeviceError, match=r"no frame within 0.5 s|lost contact"):
            for _ in range(100):   # frames already in flight may still arrive
                src.read()
        assert time.monotonic() - t0 < 1.5
    finally:
        t1 = time.monotonic()
        src.close()
    assert time.monotonic() - t1 < 0.5     # close() did not wait for the dead camera
    assert src._camera is None and src._stream is None
    # libaravis's teardown of the dead session retries its GigE Vision commands for ~10 s; a camera that
    # comes back answers them at once. Wait for it here so no later test shares libaravis with it.
    back = FakeCamera()
    try:
        assert src.release_thread is not None
        src.release_thread.join(8.0)
        assert not src.release_thread.is_alive()
    finally:
        back.kill()


def test_close_after_an_unnoticed_death_is_bounded(fake_camera: FakeCamera) -> None:
    src = open_source("aravis:127.0.0.1?fps=50&timeout_s=0.5")
    src.open()
    src.read()
    fake_camera.kill()          # nobody reads: the source does not know yet
    t0 = time.monotonic()
    src.close()
    assert time.monotonic() - t0 < 1.5
    back = FakeCamera()         # answers the background teardown so it ends before the next test
    try:
        src.release_thread.join(8.0)
        assert not src.release_thread.is_alive()
    finally:
        back.kill()
