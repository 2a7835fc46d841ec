"""A camera that takes long to open (a GigE camera that does not answer): the loop opens it in a background
thread (edgecal.stream.opener), keeps publishing status meanwhile, takes it when it comes, and a stop during
the open neither waits for it nor leaves the camera open."""

from __future__ import annotations

import threading
import time
from pathlib import Path

from edgecal.drivers.base import Source, StereoSource
from edgecal.publish.subscriber import MessageCollector
from edgecal.stream import LiveLoop, load_live_config
from edgecal.stream.loop import default_source_factory
from edgecal.stream.opener import SourceOpener

from .live_fixtures import free_endpoint, render_robot, run_in_thread, wait_until, write_config


class _SlowToOpen(StereoSource):
    """A replayed stereo camera whose open blocks until ``answer`` is set, at the device boundary."""

    def __init__(self, inner: Source, answer: threading.Event) -> None:
        super().__init__(inner.uri)
        self.inner = inner
        self.answer = answer
        self.closed = False

    def _open(self) -> None:
        assert self.answer.wait(20), "the test never let the camera answer"
        self.inner.open()

    def _read(self, timeout_s):
        return self.inner.read(timeout_s)

    def _close(self) -> None:
        self.closed = True
        self.inner.close()


def _config(tmp_path: Path, endpoint: str) -> Path:
    folder = tmp_path / "robot"
    folder.mkdir()
    render_robot(folder, 2)
    return write_config(tmp_path / "live.yaml", folder, endpoint,
                        source_extra={"pace": "fast", "loop": True, "latest_only": False},
                        loop={"camera_lost_after_s": 0.3, "status_period_s": 0.1})


def test_a_camera_that_opens_late_is_waited_for_with_status_then_used(tmp_path: Path) -> None:
    endpoint = free_endpoint()
    cfg = _config(tmp_path, endpoint)
    answer = threading.Event()
    sub = MessageCollector(endpoint)
    loop = LiveLoop(load_live_config(cfg), source_factory=lambda spec: _SlowToOpen(default_source_factory(spec),
                                                                                   answer))
    th, result = run_in_thread(loop)
    try:
        assert sub.wait_for(lambda: any("takes long" in m["message"] for m in sub.of("status")), 30)
        n = len(sub.of("status"))
        assert sub.wait_for(lambda: len(sub.of("status")) >= n + 3, 5)     # status keeps coming meanwhile
        assert not sub.of("pose")
        answer.set()
        assert sub.wait_for(lambda: len(sub.of("pose")) >= 2, 20)
        assert sub.wait_for(lambda: sub.of("status")[-1]["state"] == "running", 5)
    finally:
        answer.set()
        loop.request_stop()
        th.join(10)
        sub.close()
    assert not th.is_alive() and result == [0]


def test_a_stop_during_a_slow_open_ends_at_once_and_the_late_camera_is_closed(tmp_path: Path) -> None:
    endpoint = free_endpoint()
    cfg = _config(tmp_path, endpoint)
    answer = threading.Event()
    opened: list[_SlowToOpen] = []

    def slow(spec):
        opened.append(_SlowToOpen(default_source_factory(spec), answer))
        return opened[-1]

    loop = LiveLoop(load_live_config(cfg), source_factory=slow)
    th, result = run_in_thread(loop)
    try:
        assert wait_until(lambda: loop.state == "camera-lost", 30)
        t0 = time.monotonic()
        loop.request_stop()
        th.join(5)
        assert not th.is_alive() and result == [0]
        assert time.monotonic() - t0 < 2.0              # the loop did not wait for the camera to answer
        assert len(opened) == 1 and not opened[0].closed
    finally:
        answer.set()                                     # the camera answers after the loop has gone
        th.join(10)
    assert wait_until(lambda: opened[0].closed, 10)      # and is released: nobody else would close it


def test_the_opener_reports_why_a_source_did_not_open(tmp_path: Path) -> None:
    endpoint = free_endpoint()
    spec = load_live_config(_config(tmp_path, endpoint)).source

    def broken(spec):
        raise ValueError("a driver's bug")

    opener = SourceOpener(spec, broken)
    assert opener.wait(5)
    source, why = opener.result()
    assert source is None and why.startswith(f"cannot open {spec.uri}: ") and "a driver's bug" in why
    opener = SourceOpener(spec, default_source_factory)
    assert opener.wait(20)
    source, why = opener.result()
    assert source is not None and why == ""
    source.close()
