"""Where the live loop's messages go: the ZeroMQ pose stream and the sinks beside it (MCAP log, Foxglove),
held together, swapped on a reload and closed as one.

Every output is a Sink (edgecal.publish.sinks); the loop hands each frame and status message to
:meth:`LoopOutputs.send` and does not know which outputs there are. What is hard here is a reload: a new
endpoint is bound before the old socket is let go, and the socket may be lost (the port taken meanwhile),
in which case it is bound again at the next status period (:meth:`LoopOutputs.rebind`).
Not thread-safe: the loop calls it under its I/O lock (its abort() releases the outputs from another thread).
"""

from __future__ import annotations

import logging
from typing import Any

from edgecal.errors import EdgecalError
from edgecal.publish.publisher import PosePublisher, PublishSettings
from edgecal.publish.sinks import Sink, close_all, fan_out

log = logging.getLogger("edgecal.stream")    # the loop's stream: its journal lines keep the name they had


class LoopOutputs:
    """The pose stream (``publisher``; None while it could not be bound) and the configured ``sinks``."""

    def __init__(self) -> None:
        self.publisher: PosePublisher | None = None
        self.sinks: list[Sink] = []

    @property
    def all(self) -> list[Sink]:
        """Every output: the ZeroMQ stream (when bound) and the configured sinks."""
        return ([self.publisher] if self.publisher is not None else []) + self.sinks

    def send(self, call: str, arg: Any) -> None:
        """``sink.<call>(arg)`` ("frame" or "status") on every output (a failing one is logged and counted)."""
        fan_out(self.all, call, arg)

    def bind(self, settings: PublishSettings) -> None:
        """Bind the pose stream (PublishError when the endpoint cannot be bound)."""
        self.publisher = PosePublisher.from_settings(settings)

    def rebind(self, settings: PublishSettings) -> None:
        """Bind the pose stream again after a failed reload lost it (tried once per status period)."""
        self.bind(settings)
        log.info("pose stream bound again on %s", settings.endpoint)

    def counters(self) -> dict[str, Any]:
        """The status message's figures of the outputs: what the sinks dropped or failed on (a stalled disk
        shows here) and the connections the stream refused (a flood of subscribers; publish.max_connections)."""
        out: dict[str, Any] = {}
        if self.sinks:
            out["sinks"] = {s.name: {"dropped": s.dropped, "failures": s.failures} for s in self.sinks}
        if self.publisher is not None:
            out["refused_connections"] = self.publisher.refused_connections
        return out

    def reconfigure(self, new: PublishSettings, old: PublishSettings, sinks: list[Sink] | None) -> list[Sink]:
        """Take a reloaded config's outputs: the stream bound as ``new`` says (``old``: the running settings) and
        ``sinks`` (built and opened by the caller; None: the running ones stay). On a failure the running
        outputs stay as they were (the socket included), ``sinks`` are closed and the error is raised. Returns
        the sinks let go, for the caller to close (outside its lock: closing a log file may take a while)."""
        try:
            if self.publisher is None:          # lost in an earlier failed reload: bind the new one
                self.bind(new)
            elif new != old:
                self._replace_publisher(new, old)
        except BaseException:
            close_all(sinks or [])
            raise
        if sinks is None:
            return []
        old_sinks, self.sinks = self.sinks, sinks
        return old_sinks

    def _replace_publisher(self, new: PublishSettings, old: PublishSettings) -> None:
        """Bind with ``new`` in place of the running socket. A new endpoint is bound before the old one is let go
        (if it is taken, nothing changes); the same endpoint with other settings is closed and bound again, and
        bound with ``old`` again if that fails (if that fails too, ``publisher`` is None: see rebind)."""
        assert self.publisher is not None
        if new.endpoint != old.endpoint:
            publisher = PosePublisher.from_settings(new)
            self.publisher.close()
            self.publisher = publisher
            return
        self.publisher.close()
        self.publisher = None
        try:
            self.bind(new)
        except Exception:
            try:
                self.bind(old)
            except EdgecalError as exc:     # the port was taken meanwhile: retried every status period
                log.error("cannot bind the pose stream again: %s", exc)
            raise

    def close(self, linger_s: float = 0.0) -> None:
        """Close the stream (``linger_s``: how long queued messages may take to leave) and every sink."""
        if self.publisher is not None:
            self.publisher.close(linger_s)
            self.publisher = None
        close_all(self.sinks)
        self.sinks = []
