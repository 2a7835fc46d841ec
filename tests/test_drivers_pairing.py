"""The latest-frame-wins queue and the stereo pairing of two mono sources by timestamp."""

from __future__ import annotations

import time

import numpy as np
import pytest

from edgecal.drivers import LatestFrameSource, PairedStereoSource, TimestampPairer, open_source
from edgecal.drivers.base import Source
from edgecal.errors import DeviceLost, DeviceTimeout

from .driver_frames import ListSource, frames_at

MS = 1_000_000


def test_pairer_pairs_within_the_bound_and_drops_orphans() -> None:
    rng = np.random.default_rng(3)
    period = 33 * MS
    n = 40
    base = np.arange(n) * period
    left = base + rng.integers(-800_000, 800_000, n)     # +-0.8 ms jitter
    right = base + rng.integers(-800_000, 800_000, n)
    lost_left, lost_right = {5, 17}, {9, 30, 31}
    p = TimestampPairer(max_skew_ns=2 * MS)
    for i in range(n):
        if i not in lost_left:
            p.push_left(frames_at([left[i]])[0])
        if i not in lost_right:
            p.push_right(frames_at([right[i]])[0])
    pairs = []
    while (pair := p.pop_pair()) is not None:
        pairs.append(pair)
    expected = [i for i in range(n) if i not in lost_left | lost_right]
    got = [int(round(pr.left.stamp_ns / period)) for pr in pairs]
    # The last index can stay queued (its partner might still come), everything else is decided.
    assert got == expected[:len(got)] and len(got) >= len(expected) - 1
    assert all(pr.skew_ns <= 2 * MS for pr in pairs)
    assert p.dropped_left == len(lost_right - lost_left) and p.dropped_right == len(lost_left - lost_right)


def test_pairer_drops_pairs_further_apart_than_the_bound() -> None:
    p = TimestampPairer(max_skew_ns=1 * MS)
    for s in (0, 33 * MS, 66 * MS):
        p.push_left(frames_at([s])[0])
    for s in (300_000, 33 * MS + 5 * MS, 66 * MS - 200_000):   # the middle one is 5 ms off
        p.push_right(frames_at([s])[0])
    a, b = p.pop_pair(), p.pop_pair()
    assert (a.left.stamp_ns, b.left.stamp_ns) == (0, 66 * MS) and p.pop_pair() is None
    assert p.dropped == 2


def test_paired_stereo_source_reads_both_sides_and_counts_drops() -> None:
    left = ListSource(frames_at([i * 10 * MS for i in range(10)], "L"))
    right = ListSource(frames_at([i * 10 * MS + 400_000 for i in range(10) if i != 4], "R"))
    with PairedStereoSource(left, right, max_skew_ns=1 * MS) as stereo:
        pairs = list(stereo)
        assert stereo.dropped == 1
    assert [p.left.seq for p in pairs] == [0, 1, 2, 3, 5, 6, 7, 8, 9]
    assert all(p.skew_ns == 400_000 for p in pairs)
    assert left.closed and right.closed


def test_paired_stereo_gives_up_with_a_clear_error_when_clocks_never_match() -> None:
    left = ListSource(frames_at([i * 10 * MS for i in range(500)]), period_s=0.001)
    right = ListSource(frames_at([i * 10 * MS + 3 * MS for i in range(500)]), period_s=0.001)
    with PairedStereoSource(left, right, max_skew_ns=1 * MS, timeout_s=0.2) as stereo:
        t0 = time.monotonic()
        # The heads alternate between 3 ms and 7 ms apart as the older one is dropped each time.
        with pytest.raises(DeviceTimeout, match=r"no left/right pair within 0.2 s; the last heads were (3|7)\.000 ms "
                                              r"apart, max_skew_ms is 1"):
            stereo.read()
        assert time.monotonic() - t0 < 1.0


def test_stereo_uri_pairs_two_replays(tmp_path) -> None:
    import cv2

    from .driver_frames import render_frame
    for side in ("l", "r"):
        (tmp_path / side).mkdir()
        for i in range(4):
            cv2.imwrite(str(tmp_path / side / f"{i}.png"), render_frame(i))
    with open_source(f"stereo:replay:{tmp_path / 'l'}?pace=fast,replay:{tmp_path / 'r'}?pace=fast") as src:
        pairs = list(src)
    assert len(pairs) == 4 and all(p.skew_ns == 0 for p in pairs)


def test_latest_frame_wins_and_counts_the_overwritten() -> None:
    src = ListSource(frames_at([i * MS for i in range(30)]), period_s=0.005)
    with LatestFrameSource(src, timeout_s=1.0) as latest:
        time.sleep(0.06)               # the consumer is busy: ~12 frames arrive meanwhile
        first = latest.read()
        got = [first]
        while (f := latest.read()) is not None:
            got.append(f)
            time.sleep(0.012)          # slower than the camera
        assert first.seq >= 5          # not the oldest frame: the newest at the time
        seqs = [f.seq for f in got]
        assert seqs == sorted(seqs) and seqs[-1] == 29
        assert latest.dropped == 30 - len(got) > 0
    assert src.closed


class _Stalls(Source):
    """Delivers a few frames, then behaves like a camera that stopped sending."""

    uri = "stall:"

    def __init__(self) -> None:
        self.n = 0
        self.closed = False

    def _open(self) -> None:
        pass

    def _read(self, timeout_s):
        self.n += 1
        if self.n > 3:
            time.sleep(timeout_s)
            raise DeviceTimeout(f"stall: no frame within {timeout_s:g} s")
        return frames_at([self.n * MS])[0]

    def _close(self) -> None:
        self.closed = True


def test_latest_frame_reports_a_stalled_camera_after_the_timeout() -> None:
    inner = _Stalls()
    with LatestFrameSource(inner, timeout_s=0.15) as latest:
        latest.read(0.5)
        t0 = time.monotonic()
        with pytest.raises(DeviceTimeout, match="no frame within 0.15 s"):
            while True:
                latest.read(1.0)
        assert time.monotonic() - t0 < 0.6
    assert inner.closed


class _Fails(ListSource):
    """Delivers its frames, then fails on reading with ``error`` (an unplug, or a driver's own bug)."""

    def __init__(self, error: Exception) -> None:
        super().__init__(frames_at([MS, 2 * MS]), uri="fails")
        self.error = error

    def _read(self, timeout_s):
        if self.i >= len(self.frames):
            raise self.error
        return super()._read(timeout_s)


def test_latest_frame_tells_a_lost_camera_and_a_dead_capture_thread_apart_from_a_timeout() -> None:
    # The kind of the reader thread's error reaches the caller on every read after it: a lost camera
    # stays DeviceLost (the loop reopens it at once), a bug that killed the thread is a DeviceLost too.
    for error, kind, text in ((DeviceLost("fails: lost contact with the camera"), DeviceLost, "^fails: lost contact"),
                              (ValueError("bad buffer"), DeviceLost, "^fails: capture thread failed: bad buffer")):
        with LatestFrameSource(_Fails(error), timeout_s=0.2) as latest:
            got = []
            with pytest.raises(kind, match=text):
                for _ in range(10):
                    got.append(latest.read(1.0))
            assert 1 <= len(got) <= 2           # the first frame may have been overwritten by the second
            with pytest.raises(kind, match=text):
                latest.read(1.0)


def test_every_source_refuses_a_read_before_open_as_a_programming_error(tmp_path) -> None:
    # One guard in the Source base: RuntimeError (a bug of the caller), not a DeviceError.
    import cv2
    for side in ("left", "right"):
        (tmp_path / side).mkdir()
        cv2.imwrite(str(tmp_path / side / "000.png"), np.zeros((8, 8), np.uint8))
    sources = [open_source(f"replay:{tmp_path / 'left'}"), open_source(f"replay:{tmp_path}"),
               open_source(f"replay:{tmp_path / 'left'}?latest_only=true"), ListSource([]),
               PairedStereoSource(ListSource([]), ListSource([]), MS)]
    for src in sources:
        with pytest.raises(RuntimeError, match=r"read\(\) before open\(\) \(use the source as a context manager\)"):
            src.read()
        with src:
            src.read()
        with pytest.raises(RuntimeError, match="before open"):     # closed again
            src.read()


def test_latest_only_setting_wraps_the_source(tmp_path) -> None:
    import cv2

    from .driver_frames import render_frame
    for i in range(3):
        cv2.imwrite(str(tmp_path / f"{i}.png"), render_frame(i))
    # Paced (a camera at 100 fps): frames come faster than they are read, and only the newest is kept.
    # (pace=fast makes a frame per read instead: tests/test_drivers_replay.py.)
    with open_source(f"replay:{tmp_path}?fps=100&latest_only=true") as src:
        assert isinstance(src, LatestFrameSource)
        time.sleep(0.2)
        last = src.read(1.0)
        assert last.seq == 2 and src.read(1.0) is None and src.dropped == 2


def test_latest_frame_reader_survives_one_unreadable_frame(tmp_path) -> None:
    import cv2

    from edgecal.errors import InputError

    from .driver_frames import render_frame
    for i in range(4):
        cv2.imwrite(str(tmp_path / f"{i}.png"), render_frame(i))
    (tmp_path / "1.png").write_bytes(b"truncated")
    with open_source(f"replay:{tmp_path}?fps=50&latest_only=true") as src:
        got, errors = [], 0
        while True:
            try:
                f = src.read(1.0)
            except InputError:
                errors += 1
                continue
            if f is None:
                break
            got.append(f.seq)
    # Frames are 20 ms apart: normally all three good ones arrive; under heavy load one may be overwritten.
    assert errors == 1 and got[-1] == 3 and set(got) <= {0, 2, 3} and got == sorted(got)
