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
from typing import Any

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

    ``read(timeout_s)`` blocks for the next frame and raises DeviceTimeout when none arrives in time,
    DeviceLost when the device is gone (both DeviceError); iteration ends (StopIteration) only when a
    finite source is exhausted. ``close()`` always releases the device, also after an error, and may be
    called twice. ``read()`` before ``open()`` is a bug of the caller: RuntimeError.

    A driver implements ``_open``, ``_read`` and ``_close``; the public methods here keep the open state
    and the guard, so that no driver repeats them.
    """

    uri: str = ""
    # True when stamp_ns is on this host's CLOCK_MONOTONIC now (a live camera), so that
    # time.monotonic_ns() - stamp_ns is the frame's age; False for replays of recorded stamps.
    live: bool = False
    # True when a frame is made when it is read, as fast as it is read (a replay with pace: fast): a
    # latest-frame-wins reader then waits for its frame to be taken instead of overwriting it in a spin.
    on_demand: bool = False
    _is_open: bool = False

    def __init__(self, uri: str, settings: Any = None) -> None:
        self.uri = uri
        self.settings = settings        # the driver's settings (SourceSpec.settings), None for wrappers
        self._is_open = False

    @property
    def is_open(self) -> bool:
        """True between a successful ``open()`` and ``close()``."""
        return self._is_open

    def describe(self) -> dict:
        """The source's URI and settings as plain JSON-able values (written into recording manifests)."""
        return {"uri": self.uri}

    @property
    def dropped(self) -> int:
        """Frames this source knowingly discarded (overwritten, unpaired, lost by the device)."""
        return 0

    def open(self) -> None:
        """Open the device (or file) and start streaming."""
        self._open()
        self._is_open = True

    def read(self, timeout_s: float | None = None) -> Any:
        """The next frame (Frame, or StereoFrame for a StereoSource); None when a finite source ends."""
        self.require_open("read()")
        return self._read(timeout_s)

    def close(self) -> None:
        """Stop streaming and release the device; safe to call more than once (and after a failed open)."""
        self._is_open = False
        self._close()

    def require_open(self, call: str) -> None:
        """RuntimeError unless the source is open: ``call`` (e.g. "read()") was used before ``open()``."""
        if not self._is_open:
            raise RuntimeError(f"{self.uri}: {call} before open() (use the source as a context manager)")

    @abc.abstractmethod
    def _open(self) -> None:
        """The driver's open: connect, apply the settings, start streaming (raise DeviceError when it cannot)."""

    @abc.abstractmethod
    def _read(self, timeout_s: float | None) -> Any:
        """The driver's read of one frame (the source is open)."""

    @abc.abstractmethod
    def _close(self) -> None:
        """The driver's release of everything it holds; called also after a failed or no open."""

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
