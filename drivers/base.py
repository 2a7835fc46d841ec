"""The one interface every camera driver implements.

A :class:`Source` is a context manager you iterate for :class:`Frame` objects::

    with open_source("replay:recordings/run1") as src:
        for frame in src:
            ...

A :class:`StereoSource` yields :class:`StereoFrame` objects (a left and a right frame taken together).
Timestamps are integers in nanoseconds: ``stamp_ns`` is the capture time from the device or the
kernel (CLOCK_MONOTONIC where the driver can map it), ``recv_ns`` the host's time.monotonic_ns() when
the frame reached edgecal.
"""

from __future__ import annotations

import abc
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np


@dataclass
class Frame:
    """One image from one camera."""

    image: np.ndarray            # uint8 (or uint16) grey (H, W) or BGR (H, W, 3)
    stamp_ns: int                # capture time (device/kernel), monotonic ns
    recv_ns: int                 # host receive time, time.monotonic_ns()
    seq: int                     # sequence number from the source (gaps = dropped frames)
    camera_id: str               # which camera
    exposure_us: float | None = None
    gain_db: float | None = None


@dataclass
class StereoFrame:
    """A left and a right frame taken together; ``skew_ns`` = |left.stamp_ns - right.stamp_ns|."""

    left: Frame
    right: Frame

    @property
    def skew_ns(self) -> int:
        """How far apart the two capture timestamps are."""
        return abs(self.left.stamp_ns - self.right.stamp_ns)

    @property
    def stamp_ns(self) -> int:
        """The pair's capture time: the earlier of the two."""
        return min(self.left.stamp_ns, self.right.stamp_ns)


class Source(abc.ABC):
    """A camera (or a replay of one). Open on ``__enter__``, release on ``__exit__``/``close()``.

    ``read(timeout_s)`` blocks for the next frame and raises DeviceError when none arrives in time
    or the device is gone; iteration ends (StopIteration) only when a finite source is exhausted.
    ``close()`` always releases the device, also after an error, and may be called twice.
    """

    uri: str = ""
    # True when stamp_ns is on this host's CLOCK_MONOTONIC now (a live camera), so that
    # time.monotonic_ns() - stamp_ns is the frame's age; False for replays of recorded stamps.
    live: bool = False
    # True when a frame is made when it is read, as fast as it is read (a replay with pace: fast): a
    # latest-frame-wins reader then waits for its frame to be taken instead of overwriting it in a spin.
    on_demand: bool = False

    def describe(self) -> dict:
        """The source's URI and settings as plain JSON-able values (written into recording manifests)."""
        return {"uri": self.uri}

    @property
    def dropped(self) -> int:
        """Frames this source knowingly discarded (overwritten, unpaired, lost by the device)."""
        return 0

    @abc.abstractmethod
    def open(self) -> None:
        """Open the device (or file) and start streaming."""

    @abc.abstractmethod
    def read(self, timeout_s: float | None = None):
        """The next frame (Frame, or StereoFrame for a StereoSource); None when a finite source ends."""

    @abc.abstractmethod
    def close(self) -> None:
        """Stop streaming and release the device; safe to call more than once."""

    def __enter__(self) -> Source:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __iter__(self) -> Iterator:
        while True:
            frame = self.read()
            if frame is None:
                return
            yield frame


class StereoSource(Source):
    """A Source whose ``read`` returns StereoFrame pairs."""
