"""Stereo from two mono sources: frames paired by capture timestamp.

Two free-running (or externally triggered) cameras deliver frames whose timestamps are close but not
equal, and either may lose a frame. :class:`TimestampPairer` takes the two streams in timestamp order
and pairs the heads when they are within ``max_skew_ns``; otherwise the older head can have no partner
any more (the other side has already moved past it) and is dropped and counted.
"""

from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass

from edgecal.drivers.base import Frame, Source, StereoFrame, StereoSource
from edgecal.drivers.spec import SourceSettings, skew_setting
from edgecal.errors import DeviceTimeout


@dataclass(frozen=True)
class PairSettings(SourceSettings):
    """Settings of two mono sources paired by timestamp."""

    max_skew_ms: float = skew_setting()


class TimestampPairer:
    """Pairs two timestamp-ordered frame streams; frames without a partner within the bound are dropped."""

    def __init__(self, max_skew_ns: int) -> None:
        self.max_skew_ns = int(max_skew_ns)
        self.left: deque[Frame] = deque()
        self.right: deque[Frame] = deque()
        self.dropped_left = 0
        self.dropped_right = 0

    @property
    def dropped(self) -> int:
        """Frames dropped on either side."""
        return self.dropped_left + self.dropped_right

    def push_left(self, frame: Frame) -> None:
        """Add the next left frame."""
        self.left.append(frame)

    def push_right(self, frame: Frame) -> None:
        """Add the next right frame."""
        self.right.append(frame)

    def pop_pair(self) -> StereoFrame | None:
        """The next pair, or None until both heads are present and one pair can be decided."""
        while self.left and self.right:
            lf, rf = self.left[0], self.right[0]
            if abs(lf.stamp_ns - rf.stamp_ns) <= self.max_skew_ns:
                self.left.popleft()
                self.right.popleft()
                return StereoFrame(lf, rf)
            # The older head is further than the bound from the other side's head, and the other
            # side's later frames are later still: it can never be paired.
            if lf.stamp_ns < rf.stamp_ns:
                self.left.popleft()
                self.dropped_left += 1
            else:
                self.right.popleft()
                self.dropped_right += 1
        return None

    def needs(self) -> str:
        """Which side to read next: 'left', 'right' (an empty queue), or 'either'."""
        if not self.left:
            return "left"
        if not self.right:
            return "right"
        return "either"


class PairedStereoSource(StereoSource):
    """A StereoSource made of two mono Sources, paired by ``stamp_ns`` within ``max_skew_ns``.

    The two sources are read alternately in the caller's thread; their drivers buffer frames while
    the other side is being read (kernel/stream buffers), so nothing is lost by not reading both at
    once. ``dropped`` counts unpaired frames plus what the two sources dropped themselves.
    """

    def __init__(self, left: Source, right: Source, max_skew_ns: int, timeout_s: float = 2.0,
                 uri: str = "stereo:") -> None:
        super().__init__(uri)
        self.left = left
        self.right = right
        self.pairer = TimestampPairer(max_skew_ns)
        self.timeout_s = timeout_s
        self.live = left.live and right.live

    @property
    def dropped(self) -> int:
        """Unpaired frames plus frames the two sources dropped."""
        return self.pairer.dropped + self.left.dropped + self.right.dropped

    def describe(self) -> dict:
        """Both sides' descriptions and the pairing bound."""
        return {"uri": self.uri, "max_skew_ns": self.pairer.max_skew_ns,
                "left": self.left.describe(), "right": self.right.describe()}

    def _open(self) -> None:
        """Open both sides (the left is closed again if the right fails)."""
        self.left.open()
        try:
            self.right.open()
        except BaseException:
            self.left.close()
            raise

    def _read(self, timeout_s: float | None) -> StereoFrame | None:
        """The next pair; None when either side ends; DeviceError when no pair forms within the timeout.

        A side that keeps delivering frames that never pair (clocks far apart, a bound too tight) is a
        fault too: it is reported after the timeout, naming the measured skew.
        """
        timeout = self.timeout_s if timeout_s is None else timeout_s
        deadline = time.monotonic() + timeout
        last_skew: int | None = None
        while True:
            pair = self.pairer.pop_pair()
            if pair is not None:
                return pair
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                detail = (f"; the last heads were {last_skew / 1e6:.3f} ms apart, max_skew_ms is "
                          f"{self.pairer.max_skew_ns / 1e6:g}" if last_skew is not None else "")
                raise DeviceTimeout(f"{self.uri}: no left/right pair within {timeout:g} s{detail}")
            side = self.pairer.needs()
            if side == "either":
                side = "left"
            src = self.left if side == "left" else self.right
            frame = src.read(remaining)
            if frame is None:
                return None
            if side == "left":
                self.pairer.push_left(frame)
            else:
                self.pairer.push_right(frame)
            if self.pairer.left and self.pairer.right:
                last_skew = abs(self.pairer.left[0].stamp_ns - self.pairer.right[0].stamp_ns)

    def _close(self) -> None:
        """Close both sides, also if closing one of them fails."""
        try:
            self.left.close()
        finally:
            self.right.close()
