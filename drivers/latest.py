"""Latest-frame-wins capture: a background thread reads a source and keeps only the newest frame.

The live loop must always work on the newest image: if it is slower than the camera, the frames it
could not take are overwritten (and counted in ``dropped``) instead of piling up in a queue and
adding latency.
"""

from __future__ import annotations

import threading
import time

from edgecal.drivers.base import Source, StereoSource
from edgecal.errors import DeviceError, DeviceLost, DeviceTimeout, InputError


class LatestFrameSource(Source):
    """Wrap ``inner``: a thread reads it continuously; ``read`` returns the newest unread frame.

    ``dropped`` counts frames that were overwritten before anyone read them. An error in the thread
    (e.g. DeviceError when the camera stops sending) is raised by the next ``read`` and ends the
    thread; an InputError for one unreadable frame (a corrupt file in a replay) is raised once and
    reading goes on. When a finite inner source ends, ``read`` returns the last unread frame, then None.
    An ``on_demand`` inner source (a replay with pace: fast) is read only once the last frame was taken:
    it would otherwise make and overwrite frames as fast as it can, starving the consumer of the CPU.
    """

    def __init__(self, inner: Source, timeout_s: float = 2.0) -> None:
        super().__init__(inner.uri)
        self.inner = inner
        self.live = inner.live
        self.timeout_s = timeout_s
        self._cond = threading.Condition()
        self._slot: object | None = None
        self._error: BaseException | None = None
        self._frame_errors: list[InputError] = []
        self._ended = False
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._dropped = 0
        self.delivered = 0

    @property
    def dropped(self) -> int:
        """Frames overwritten before being read, plus what the inner source dropped."""
        return self._dropped + self.inner.dropped

    def describe(self) -> dict:
        """The inner source's description."""
        return self.inner.describe()

    def _open(self) -> None:
        """Open the inner source and start the reader thread."""
        if self._thread is not None:
            return
        self.inner.open()
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name=f"capture {self.uri}", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        try:
            while not self._stop.is_set():
                if self.inner.on_demand:
                    with self._cond:
                        while self._slot is not None and not self._stop.is_set():
                            self._cond.wait(0.1)
                    if self._stop.is_set():
                        return
                try:
                    frame = self.inner.read(self.timeout_s)
                except InputError as exc:
                    # One unreadable frame (a corrupt file in a replay): report it once, keep reading.
                    with self._cond:
                        self._frame_errors.append(exc)
                        self._cond.notify_all()
                    continue
                with self._cond:
                    if frame is None:
                        self._ended = True
                        self._cond.notify_all()
                        return
                    if self._slot is not None:
                        self._dropped += 1
                    self._slot = frame
                    self._cond.notify_all()
        except BaseException as exc:  # handed to the reader, who raises it
            with self._cond:
                self._error = exc
                self._cond.notify_all()

    def _read(self, timeout_s: float | None):
        """The newest frame not yet returned; DeviceTimeout if none arrives within the timeout, DeviceLost
        when the capture thread has died (the inner source's DeviceError is raised again as it was)."""
        timeout = self.timeout_s if timeout_s is None else timeout_s
        deadline = time.monotonic() + timeout
        with self._cond:
            while self._slot is None:
                if self._frame_errors:
                    raise self._frame_errors.pop(0)
                if self._error is not None:
                    err = self._error
                    if isinstance(err, DeviceError):
                        # The same kind (lost, timeout) with a fresh traceback on every read.
                        raise type(err)(str(err)) from err
                    raise DeviceLost(f"{self.uri}: capture thread failed: {err}") from err
                if self._ended:
                    return None
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise DeviceTimeout(f"{self.uri}: no frame within {timeout:g} s "
                                      "(camera stopped sending or is disconnected?)")
                self._cond.wait(remaining)
            frame, self._slot = self._slot, None
            self.delivered += 1
            self._cond.notify_all()          # an on-demand reader waits for the slot to be free
            return frame

    def _close(self) -> None:
        """Stop the thread and close the inner source (also after an error)."""
        self._stop.set()
        with self._cond:
            self._cond.notify_all()
        thread, self._thread = self._thread, None
        try:
            if thread is not None:
                # The inner read returns within its timeout, so the thread ends by then.
                thread.join(self.timeout_s + 1.0)
        finally:
            self.inner.close()


class LatestStereoFrameSource(LatestFrameSource, StereoSource):
    """LatestFrameSource over a StereoSource (keeps the StereoSource type for callers that check it)."""
