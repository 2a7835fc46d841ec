"""Subscribing to the pose stream: the one SUB-socket set-up that ``edgecal listen``, the demo, the tests and
the benchmarks use, and a minimal example to copy for your own subscriber.

A message is two frames, the topic (``pose`` or ``status``) and a UTF-8 JSON object (schema:
edgecal.publish.messages, README.md "Pose stream"). :class:`PoseSubscriber` connects, subscribes and
receives in the caller's thread; :class:`MessageCollector` reads one in a background thread and keeps (or
hands on) every message. A CURVE-secured stream needs this subscriber's keys (edgecal.publish.curve).
Nothing here publishes or knows the live loop.
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable, Iterable
from typing import Any

import zmq

from edgecal.errors import InputError
from edgecal.publish.curve import ClientKeys
from edgecal.publish.messages import POSE_TOPIC, STATUS_TOPIC

TOPICS = (POSE_TOPIC.decode(), STATUS_TOPIC.decode())
POLL_SLICE_S = 0.05       # a collector's thread checks for a stop request at least this often


def parse_message(frames: list[bytes]) -> dict[str, Any] | None:
    """The JSON object of one ``[topic, body]`` message; None for anything else (wrong frame count, not UTF-8,
    not JSON, not an object)."""
    if len(frames) != 2:
        return None
    try:
        msg = json.loads(frames[1].decode("utf-8"))
    except (UnicodeDecodeError, ValueError, RecursionError):
        return None
    return msg if isinstance(msg, dict) else None


class PoseSubscriber:
    """A SUB socket connected to ``endpoint`` and subscribed to ``topics`` (default: pose and status).

    ``keys``: this subscriber's CURVE key pair and the publisher's public key, for a secured stream.
    ``context``: a ZeroMQ context to share (many subscribers in one process; default: its own, closed with it).
    ``receive_hwm`` / ``receive_buffer``: ZeroMQ's RCVHWM and the kernel's SO_RCVBUF (bytes), for a subscriber
    that must hold little; ``reconnect_interval_s``: the wait before reconnecting after the publisher dropped
    the connection (ZeroMQ's default 0.1 s). None leaves ZeroMQ's default. A malformed endpoint is an
    InputError naming it. Not thread-safe (a ZeroMQ socket): use it from one thread, or via MessageCollector.
    """

    def __init__(self, endpoint: str, topics: Iterable[str] = TOPICS, *, keys: ClientKeys | None = None,
                 context: zmq.Context | None = None, receive_hwm: int | None = None,
                 receive_buffer: int | None = None, reconnect_interval_s: float | None = None) -> None:
        self.endpoint = endpoint
        self._own_context = context is None
        self._ctx = context if context is not None else zmq.Context()
        self._sock = self._ctx.socket(zmq.SUB)
        self._sock.setsockopt(zmq.LINGER, 0)
        if receive_hwm is not None:
            self._sock.setsockopt(zmq.RCVHWM, receive_hwm)
        if receive_buffer is not None:
            self._sock.setsockopt(zmq.RCVBUF, receive_buffer)
        if reconnect_interval_s is not None:
            self._sock.setsockopt(zmq.RECONNECT_IVL, int(reconnect_interval_s * 1000))
        if keys is not None:
            self._sock.curve_secretkey = keys.secret
            self._sock.curve_publickey = keys.public
            self._sock.curve_serverkey = keys.server_public
        for topic in topics:
            self._sock.setsockopt(zmq.SUBSCRIBE, topic.encode())
        try:
            self._sock.connect(endpoint)
        except zmq.ZMQError as exc:
            self.close()
            raise InputError(f"{endpoint}: not a ZeroMQ endpoint ({exc}); e.g. tcp://127.0.0.1:5560") from None

    def receive_frames(self, timeout_s: float) -> list[bytes] | None:
        """The next message's frames as they came, or None when none arrives within ``timeout_s`` (0: only
        one already queued)."""
        if not self._sock.poll(int(timeout_s * 1000)):
            return None
        return self._sock.recv_multipart()

    def receive(self, timeout_s: float) -> dict[str, Any] | None:
        """The next message that is a topic and a JSON object (others are skipped), or None after ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        while True:
            frames = self.receive_frames(max(0.0, deadline - time.monotonic()))
            if frames is None:
                return None
            msg = parse_message(frames)
            if msg is not None:
                return msg

    def close(self) -> None:
        """Close the socket (and its own context); safe to call twice."""
        if not self._sock.closed:
            self._sock.close(linger=0)
        if self._own_context and not self._ctx.closed:
            self._ctx.term()

    def __enter__(self) -> PoseSubscriber:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class MessageCollector:
    """A PoseSubscriber read by a background thread: every JSON message goes to ``on_message``, by default
    appended to ``messages``. ``on_message`` runs in that thread.

    ``close(drain_s)`` waits ``drain_s`` first, for messages still on their way (e.g. a loop's last status),
    then takes what is already queued and stops.
    """

    def __init__(self, endpoint: str, topics: Iterable[str] = TOPICS, *, keys: ClientKeys | None = None,
                 on_message: Callable[[dict[str, Any]], None] | None = None) -> None:
        self.endpoint = endpoint
        self.messages: list[dict[str, Any]] = []
        self._on_message = on_message or self.messages.append
        self._subscriber = PoseSubscriber(endpoint, topics, keys=keys)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="subscriber", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while True:
            stopping = self._stop.is_set()
            frames = self._subscriber.receive_frames(0.0 if stopping else POLL_SLICE_S)
            if frames is None:
                if stopping:            # asked to stop and nothing left in the queue
                    return
                continue
            msg = parse_message(frames)
            if msg is not None:
                self._on_message(msg)

    def of(self, kind: str) -> list[dict[str, Any]]:
        """The messages collected so far whose ``type`` is ``kind`` ("pose", "status")."""
        return [m for m in list(self.messages) if m.get("type") == kind]

    def wait_for(self, condition: Callable[[], bool], timeout_s: float = 20.0) -> bool:
        """Poll ``condition()`` every 20 ms until it is true (True) or ``timeout_s`` passes (False)."""
        deadline = time.monotonic() + timeout_s
        while not condition():
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.02)
        return True

    def close(self, drain_s: float = 0.0) -> list[dict[str, Any]]:
        """Stop the thread (after ``drain_s``) and close the socket; the collected messages. Safe to call twice."""
        if drain_s > 0:
            time.sleep(drain_s)
        self._stop.set()
        self._thread.join()
        self._subscriber.close()
        return self.messages

    def __enter__(self) -> MessageCollector:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
