"""One small interface between the live loop and everything it publishes to.

The loop builds one :class:`FrameOutput` per stereo frame and hands it, and each status message, to
every :class:`Sink`; it does not know what they are. The sinks: the ZeroMQ JSON stream
(:class:`edgecal.publish.publisher.PosePublisher`), the MCAP pose log (``publish.record``,
mcap_sink.py) and the live Foxglove server (``publish.foxglove``, foxglove_sink.py).

A sink must not block: it drops what it cannot pass on and counts it. A sink that raises (a full disk,
a bug) is logged and counted by :func:`fan_out` and the loop and the other sinks go on.
"""

from __future__ import annotations

import abc
import logging
import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

from edgecal.drivers.base import StereoFrame
from edgecal.pose.types import Pose
from edgecal.publish.sink_settings import OutputSettings

log = logging.getLogger("edgecal.publish")


@dataclass
class FrameOutput:
    """What the loop made of one stereo frame.

    message:    the JSON pose message (schema version 1) as the ZeroMQ stream sends it.
    detections: the boards found (tracked or searched) in the left and the right image: the corners the
                pose was fitted to, in pixels of the full-size images.
    capture_ns: the pair's capture time on this host's CLOCK_MONOTONIC (the receive time for replays).
    """

    frame: StereoFrame
    pose: Pose
    message: dict[str, Any]
    detections: tuple[list, list] = field(default_factory=lambda: ([], []))
    capture_ns: int = 0


class Sink(abc.ABC):
    """Something the loop publishes to. Every call returns at once (drop, never wait)."""

    name: str = "sink"
    failures: int = 0           # calls that raised (counted by fan_out)

    @abc.abstractmethod
    def frame(self, out: FrameOutput) -> None:
        """Pass on one frame's pose (and, for sinks that show them, its images and corners)."""

    @abc.abstractmethod
    def status(self, message: dict[str, Any]) -> None:
        """Pass on one status message (see edgecal.publish.messages.status_message)."""

    @abc.abstractmethod
    def close(self) -> None:
        """Release the socket/file/server; safe to call twice."""

    @property
    def dropped(self) -> int:
        """Messages this sink knowingly dropped (a full queue, a slow client)."""
        return 0


def fan_out(sinks: Iterable[Sink], call: str, arg: Any) -> None:
    """``sink.<call>(arg)`` for every sink; one that raises is logged (first time, then every 1000th) and
    counted, and the others still get it."""
    for sink in sinks:
        try:
            getattr(sink, call)(arg)
        except Exception as exc:  # noqa: BLE001 - a failing output must not stop the pose loop (weeks of uptime)
            sink.failures += 1
            if sink.failures == 1 or sink.failures % 1000 == 0:
                log.error("%s sink failed (%d times): %r", sink.name, sink.failures, exc)


def close_all(sinks: Iterable[Sink]) -> None:
    """Close every sink, also when one of them fails to close."""
    for sink in sinks:
        try:
            sink.close()
        except Exception as exc:  # noqa: BLE001 - the others must still be closed
            log.error("closing the %s sink failed: %r", sink.name, exc)


def ros_stamp_ns(out: FrameOutput, stamp: str) -> int:
    """The stamp ROS messages carry for ``out``: ``monotonic`` = the source's stamp_ns as the JSON stream has
    it; ``realtime`` = CLOCK_REALTIME at capture (the host-monotonic capture time shifted by the clocks' offset
    now), what ROS tools expect."""
    if stamp == "realtime":
        return int(out.capture_ns + (time.time_ns() - time.monotonic_ns()))
    return int(out.frame.stamp_ns)


def build_sinks(outputs: OutputSettings) -> list[Sink]:
    """The sinks ``outputs`` asks for beside ZeroMQ (the MCAP log, the Foxglove server), opened.

    A sink that cannot start (a file that cannot be written, a port in use) raises its error; the ones
    already opened are closed first.
    """
    sinks: list[Sink] = []
    try:
        if outputs.record is not None:
            from edgecal.publish.mcap_sink import McapSink
            sinks.append(McapSink(outputs.record, outputs))
        if outputs.foxglove is not None:
            from edgecal.publish.foxglove_sink import FoxgloveSink
            sinks.append(FoxgloveSink(outputs.foxglove, outputs))
    except BaseException:
        close_all(sinks)
        raise
    return sinks
