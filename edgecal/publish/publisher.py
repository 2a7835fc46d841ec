"""ZeroMQ PUB socket that never blocks the loop.

Each message is two frames: the topic (b"pose" or b"status", so subscribers can filter) and the JSON
body. Sends are non-blocking with a small high-water mark: a slow or dead subscriber loses messages,
the loop never waits for it. ZeroMQ drops silently at a subscriber's high-water mark, so the publisher
cannot count those losses; ``send_failures`` counts only sends the socket itself refused.
"""

from __future__ import annotations

import ipaddress
import logging
from typing import Any
from urllib.parse import urlsplit

import zmq

from edgecal.errors import ConfigError, DeviceError
from edgecal.publish.messages import POSE_TOPIC, STATUS_TOPIC, encode
from edgecal.publish.sinks import FrameOutput, Sink

log = logging.getLogger(__name__)

DEFAULT_ENDPOINT = "tcp://127.0.0.1:5560"


def is_local_endpoint(endpoint: str) -> bool:
    """True for ipc:// and inproc:// endpoints and for tcp:// on a loopback address or 'localhost'."""
    parts = urlsplit(endpoint)
    if parts.scheme in ("ipc", "inproc"):
        return True
    host = (parts.hostname or "").strip("[]")
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False        # '*', an interface name or a host name: not local


def check_endpoint(endpoint: str, allow_remote: bool) -> str:
    """Validate ``endpoint``; binding beyond the loopback interface needs ``allow_remote``."""
    parts = urlsplit(endpoint)
    if parts.scheme not in ("tcp", "ipc", "inproc"):
        raise ConfigError(f"endpoint {endpoint!r}: must start with tcp://, ipc:// or inproc://")
    if parts.scheme == "tcp" and parts.port is None:
        raise ConfigError(f"endpoint {endpoint!r}: a tcp endpoint needs a port, e.g. tcp://127.0.0.1:5560")
    if not allow_remote and not is_local_endpoint(endpoint):
        raise ConfigError(f"endpoint {endpoint!r} is reachable from other machines: set "
                          f"publish.allow_remote: true to bind there on purpose")
    return endpoint


class PosePublisher(Sink):
    """A bound PUB socket; ``send_pose``/``send_status`` return False when the socket refused the message.

    As a Sink (edgecal.publish.sinks) it sends each frame's JSON pose message and each status message.
    """

    name = "zeromq"

    def __init__(self, endpoint: str = DEFAULT_ENDPOINT, hwm: int = 4, context: zmq.Context | None = None) -> None:
        self.endpoint = endpoint
        self.sent = 0
        self.send_failures = 0
        self._own_context = context is None
        self._ctx = context or zmq.Context()
        self._sock = self._ctx.socket(zmq.PUB)
        self._sock.setsockopt(zmq.SNDHWM, hwm)
        self._sock.setsockopt(zmq.LINGER, 0)       # close at once: queued messages are stale anyway
        try:
            self._sock.bind(endpoint)
        except zmq.ZMQError as exc:
            self.close()
            raise DeviceError(f"cannot bind the pose stream to {endpoint} ({exc}); is another edgecal running?") \
                from None

    def _send(self, topic: bytes, message: dict[str, Any]) -> bool:
        try:
            self._sock.send_multipart([topic, encode(message)], flags=zmq.NOBLOCK)
        except zmq.Again:
            self.send_failures += 1
            return False
        self.sent += 1
        return True

    def send_pose(self, message: dict[str, Any]) -> bool:
        """Publish a pose message without waiting."""
        return self._send(POSE_TOPIC, message)

    def send_status(self, message: dict[str, Any]) -> bool:
        """Publish a status message without waiting."""
        return self._send(STATUS_TOPIC, message)

    def frame(self, out: FrameOutput) -> None:
        """Sink interface: publish the frame's pose message."""
        self.send_pose(out.message)

    def status(self, message: dict[str, Any]) -> None:
        """Sink interface: publish a status message."""
        self.send_status(message)

    def close(self) -> None:
        """Close the socket (and the context if this publisher created it); safe to call twice."""
        if not self._sock.closed:
            self._sock.close(linger=0)
        if self._own_context and not self._ctx.closed:
            self._ctx.term()

    def __enter__(self) -> "PosePublisher":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
