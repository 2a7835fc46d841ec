"""Opening a camera without stopping the loop: the source is created and opened in a background thread.

Opening can block for seconds (a GigE camera that does not answer, a replay decoding its preload); the live
loop (edgecal.stream.loop) keeps reporting status and petting the watchdog meanwhile, and takes the result
when it is there. When to open again (the back-off) is the loop's decision, not this module's.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

from edgecal.drivers.base import Source
from edgecal.drivers.spec import SourceSpec
from edgecal.errors import EdgecalError, clip, exception_summary

log = logging.getLogger("edgecal.stream")


class SourceOpener:
    """One attempt at creating and opening the source of ``spec`` with ``factory``, in its own thread.

    :meth:`wait` until it is done, then :meth:`result` gives the open source or why it did not open. A
    source that opens after :meth:`cancel` (the loop stopped meanwhile) is closed at once: nobody else
    would release the camera.
    """

    def __init__(self, spec: SourceSpec, factory: Callable[[SourceSpec], Source]) -> None:
        self.spec = spec
        self.started_ns = time.monotonic_ns()
        self._factory = factory
        self._lock = threading.Lock()
        self._source: Source | None = None
        self._why = "the source opener ended without a result"
        self._cancelled = False
        self._thread = threading.Thread(target=self._run, name="open-source", daemon=True)
        self._thread.start()

    def wait(self, timeout_s: float) -> bool:
        """Wait up to ``timeout_s`` for the attempt to end; True when it has."""
        self._thread.join(timeout_s)
        return not self._thread.is_alive()

    @property
    def elapsed_s(self) -> float:
        """How long the attempt has taken so far (s)."""
        return (time.monotonic_ns() - self.started_ns) / 1e9

    def result(self) -> tuple[Source | None, str]:
        """(the open source, "") or (None, why it did not open, one line naming the source); after :meth:`wait`."""
        with self._lock:
            source, self._source = self._source, None
            return source, "" if source is not None else self._why

    def cancel(self, wait_s: float = 0.2) -> None:
        """Give up on the attempt: a source already open, or opening within the next moments, is closed."""
        with self._lock:
            self._cancelled = True
            source, self._source = self._source, None
        if source is not None:
            source.close()
        self._thread.join(wait_s)

    def _run(self) -> None:
        spec = self.spec
        source = None
        try:
            source = self._factory(spec)     # latest-frame-wins: the source's latest_only
            source.open()
        except Exception as exc:  # DeviceError, InputError (a preload too large) or a driver's bug
            if not isinstance(exc, EdgecalError):
                log.exception("unexpected error while opening %s", spec.uri)
            if source is not None:
                try:
                    source.close()
                except Exception:  # the open already failed; its reason is what counts
                    log.debug("closing %s after a failed open failed", spec.uri, exc_info=True)
            why = str(exc) if isinstance(exc, EdgecalError) else exception_summary(exc)
            with self._lock:
                self._why = clip(f"cannot open {spec.uri}: {why}")
            return
        with self._lock:
            cancelled = self._cancelled
            if not cancelled:
                self._source = source
        if cancelled:
            source.close()
