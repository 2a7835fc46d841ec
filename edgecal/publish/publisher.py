"""ZeroMQ PUB socket that never blocks the loop.

Each message is two frames: the topic (b"pose" or b"status", so subscribers can filter) and the JSON
body. Sends are non-blocking with a small high-water mark: a slow or dead subscriber loses messages,
the loop never waits for it. ZeroMQ drops silently at a subscriber's high-water mark, so the publisher
cannot count those losses; ``send_failures`` counts only sends the socket itself refused.

With CURVE keys (required beyond the loopback interface; see edgecal.publish.curve) the stream is
encrypted and only subscribers whose public key the publisher knows are let in.

Connections are bounded twice, so that a flood of them cannot take the daemon's file descriptors (which
it needs for the camera, the config and its logs): one that has not finished ZeroMQ's handshake within
``handshake_timeout_s`` is dropped by ZeroMQ (idle TCP connections, a port scan), and at most
``max_connections`` are held at once (:class:`ConnectionLimit`; clients that complete the handshake at
once and stay, e.g. a loop opening SUB sockets).

:class:`PublishSettings` is the ``publish:`` section's part that configures this socket, read by
edgecal.config.read_settings (the same section's frame names and other outputs: sink_settings.py).
"""

from __future__ import annotations

import ipaddress
import logging
import os
import socket
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import zmq
from zmq.auth.thread import ThreadAuthenticator
from zmq.utils.monitor import recv_monitor_message

from edgecal.config import ConfigReader, setting
from edgecal.errors import ConfigError, InputError, PublishError, quote
from edgecal.publish.curve import AllowedKeys, ServerKeys, load_server_keys, read_key_file
from edgecal.publish.messages import POSE_TOPIC, STATUS_TOPIC, encode
from edgecal.publish.sinks import FrameOutput, Sink

log = logging.getLogger(__name__)

DEFAULT_ENDPOINT = "tcp://127.0.0.1:5560"
HANDSHAKE_TIMEOUT_S = 2.0        # publish.handshake_timeout_s: see PosePublisher
# publish.max_connections: subscriber connections held at once (a robot has a handful of subscribers; with
# LimitNOFILE=4096, or even the default 1024, this leaves the daemon its descriptors whatever connects).
MAX_CONNECTIONS = 64
LIMIT_LOG_PERIOD_S = 10.0        # at most one "refusing connections" warning per this


def _tcp_host_port(endpoint: str) -> tuple[str, str]:
    """HOST and PORT of ``tcp://HOST:PORT`` (brackets of an IPv6 HOST removed); either may be empty."""
    rest = endpoint.partition("://")[2]
    host, _, port = rest.rpartition(":")
    return host.strip("[]") if host.startswith("[") else host, port


def is_local_endpoint(endpoint: str) -> bool:
    """True for ipc:// and inproc:// endpoints and for tcp:// on a loopback address or 'localhost'."""
    scheme = endpoint.partition("://")[0]
    if scheme in ("ipc", "inproc"):
        return True
    host, _ = _tcp_host_port(endpoint)
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False        # '*', an interface name or a host name: not local


def endpoint_problem(endpoint: str, allow_remote: bool) -> str | None:
    """What is wrong with ``endpoint`` as the place to bind the pose stream (None: nothing).

    Checked here rather than left to ZeroMQ, whose bind() error does not say which part is wrong: a tcp
    endpoint is ``tcp://HOST:PORT`` with PORT 1-65535 (not ``*``: subscribers could not know the port ZeroMQ
    picks); binding beyond the loopback interface needs ``allow_remote``.
    """
    scheme, sep, rest = endpoint.partition("://")
    if not sep or scheme not in ("tcp", "ipc", "inproc"):
        return "must start with tcp://, ipc:// or inproc://, e.g. tcp://127.0.0.1:5560"
    if not rest:
        return f"needs an address after {scheme}://"
    if scheme == "tcp":
        host, port = _tcp_host_port(endpoint)
        if ":" not in rest or not host:
            return "must be tcp://HOST:PORT (with a port), e.g. tcp://127.0.0.1:5560"
        if not (port.isascii() and port.isdigit()) or not 1 <= int(port) <= 65535:
            return f"needs a port from 1 to 65535, not {quote(port)}"
        if ":" in host and not rest.startswith("["):
            return "must put an IPv6 address in brackets, e.g. tcp://[::1]:5560"
    if not allow_remote and not is_local_endpoint(endpoint):
        return "is reachable from other machines: set publish.allow_remote: true to bind there on purpose"
    return None


def check_endpoint(endpoint: str, allow_remote: bool) -> str:
    """``endpoint`` if it can be bound (see endpoint_problem); ConfigError quoting it otherwise."""
    problem = endpoint_problem(endpoint, allow_remote)
    if problem is not None:
        raise ConfigError(f"endpoint {quote(endpoint)} {problem}")
    return endpoint


class ConnectionLimit:
    """Holds a bound socket's accepted connections to ``limit``: beyond it, a new one is shut down at once.

    ZeroMQ has no such option. Its socket monitor reports each accepted connection with its descriptor
    (and each disconnection); a thread of ours counts them and shuts down (``shutdown(2)`` on a duplicate
    of the descriptor) those accepted while ``limit`` are held. ZeroMQ then sees the connection end and
    releases it as it would any closed connection; its descriptor is never closed under ZeroMQ. Before
    acting, the descriptor is checked to be a TCP/IPC connection on this socket's own address (a
    descriptor number the process has since reused elsewhere is left alone).
    """

    # MONITOR_STOPPED too: ZeroMQ sends it (and so ends the watching thread) only to a monitor that asked for it.
    EVENTS = zmq.EVENT_ACCEPTED | zmq.EVENT_DISCONNECTED | zmq.EVENT_MONITOR_STOPPED

    def __init__(self, sock: zmq.Socket, limit: int, local: int | str) -> None:
        self.limit = limit
        self.refused = 0              # connections shut down because ``limit`` were held
        self._local = local           # this socket's address as getsockname() gives it (tcp: port; ipc: path)
        self._held: set[int] = set()
        self._sock = sock
        self._monitor = sock.get_monitor_socket(self.EVENTS)
        self._last_log = 0.0
        self._thread = threading.Thread(target=self._run, name="publish-connections", daemon=True)
        self._thread.start()

    @property
    def held(self) -> int:
        """Connections accepted and not yet ended."""
        return len(self._held)

    def _run(self) -> None:
        monitor = self._monitor
        try:
            while True:
                event = recv_monitor_message(monitor)
                kind, fd = event["event"], int(event["value"])
                if kind == zmq.EVENT_MONITOR_STOPPED:
                    return
                if kind == zmq.EVENT_DISCONNECTED:
                    self._held.discard(fd)
                elif kind == zmq.EVENT_ACCEPTED:
                    if len(self._held) < self.limit:
                        self._held.add(fd)
                    elif self._shut(fd):
                        self._refused()
        except zmq.ZMQError:          # the context is terminating: nothing left to watch
            return
        finally:
            monitor.close(linger=0)

    def _shut(self, fd: int) -> bool:
        """Shut down the connection on ``fd`` if it is one of this socket's; whether it was."""
        try:
            dup = socket.socket(fileno=os.dup(fd))
        except OSError:               # closed meanwhile (the peer left at once), or not a socket
            return False
        try:
            name = dup.getsockname()
            mine = (name[1] if isinstance(name, tuple) else name) == self._local
            if mine:
                dup.shutdown(socket.SHUT_RDWR)
            return mine
        except OSError:
            return False
        finally:
            dup.close()               # only the duplicate: the descriptor stays ZeroMQ's

    def _refused(self) -> None:
        self.refused += 1
        now = time.monotonic()
        if now - self._last_log >= LIMIT_LOG_PERIOD_S:
            self._last_log = now
            log.warning("refusing pose-stream connections: %d held (publish.max_connections); %d refused so far",
                        len(self._held), self.refused)

    def close(self) -> None:
        """Stop watching (the monitor's stop event ends the thread); call before closing the socket."""
        try:
            self._sock.disable_monitor()
        except zmq.ZMQError:
            pass
        self._thread.join(1.0)


def _local_address(sock: zmq.Socket) -> int | str:
    """What getsockname() of an accepted connection gives for the bound endpoint: the port (tcp), the path (ipc)."""
    endpoint = sock.getsockopt_string(zmq.LAST_ENDPOINT)
    scheme, _, rest = endpoint.partition("://")
    if scheme == "tcp":
        return int(rest.rpartition(":")[2])
    return rest


def _read_curve(r: ConfigReader, key: str) -> ServerKeys | None:
    """``curve: {server_key, client_keys}``: both key files checked, each error naming its field."""
    if r.data[key] is None:
        return None
    s = r.section(key)
    s.reject_unknown(("server_key", "client_keys"))
    server_key = Path(s.string("server_key")).expanduser()
    client_keys = Path(s.string("client_keys")).expanduser()
    try:
        read_key_file(server_key, need_secret=True)    # its own field named when it is the wrong one
    except InputError as exc:
        raise s.fail("server_key", f"cannot be used: {exc}") from None
    try:
        return load_server_keys(server_key, client_keys)
    except InputError as exc:
        raise s.fail("client_keys", f"cannot be used: {exc}") from None


@dataclass(frozen=True)
class PublishSettings:
    """Where and how poses are published (the ``publish:`` section also holds the OutputSettings)."""

    endpoint: str = setting(DEFAULT_ENDPOINT, doc="the ZeroMQ PUB endpoint (loopback unless allow_remote)")
    allow_remote: bool = setting(False, doc="bind beyond the loopback interface on purpose (needs curve)")
    hwm: int = setting(4, doc="messages queued per subscriber before they are dropped", minimum=1, maximum=1000)
    handshake_timeout_s: float = setting(HANDSHAKE_TIMEOUT_S, doc="a connection that has not spoken ZeroMQ by then "
                                                                  "is dropped (s)", minimum=0.1, maximum=60)
    # required beyond loopback; optional (and then enforced) on it
    curve: ServerKeys | None = setting(None, doc="CURVE keys: {server_key, client_keys} (`edgecal keys`)",
                                       read=_read_curve)
    max_connections: int = setting(MAX_CONNECTIONS, doc="connections held at once; one accepted beyond is shut "
                                                        "down at once (a flood cannot take the descriptors)",
                                   minimum=1, maximum=10_000)

    def config_problem(self) -> tuple[str, str] | None:
        """An endpoint that cannot be bound, or one beyond loopback without keys."""
        problem = endpoint_problem(self.endpoint, self.allow_remote)
        if problem is not None:
            return ("endpoint", f"{problem} (got {quote(self.endpoint)})")
        if self.curve is None and not is_local_endpoint(self.endpoint):
            return ("curve", f"is missing: beyond the loopback interface ({quote(self.endpoint)}) only subscribers "
                             "with a known key may listen; give curve.server_key and curve.client_keys "
                             "(`edgecal keys` makes key pairs)")
        return None


class PosePublisher(Sink):
    """A bound PUB socket; ``send_pose``/``send_status`` return False when the socket refused the message.

    As a Sink (edgecal.publish.sinks) it sends each frame's JSON pose message and each status message.
    """

    name = "zeromq"

    def __init__(self, endpoint: str = DEFAULT_ENDPOINT, hwm: int = 4, context: zmq.Context | None = None, *,
                 curve: ServerKeys | None = None, handshake_timeout_s: float = HANDSHAKE_TIMEOUT_S,
                 max_connections: int = MAX_CONNECTIONS) -> None:
        self.endpoint = endpoint
        self.sent = 0
        self.send_failures = 0
        self._own_context = context is None
        self._ctx = context or zmq.Context()
        self._auth: ThreadAuthenticator | None = None
        self._limit: ConnectionLimit | None = None
        self._sock = self._ctx.socket(zmq.PUB)
        self._sock.setsockopt(zmq.SNDHWM, hwm)
        self._sock.setsockopt(zmq.LINGER, 0)       # close at once: queued messages are stale anyway
        # A connection that has not finished ZeroMQ's handshake within this is dropped: idle TCP connections
        # (a port scan, a flood) cannot hold file descriptors and starve real subscribers.
        self._sock.setsockopt(zmq.HANDSHAKE_IVL, int(handshake_timeout_s * 1000))
        if curve is not None:
            # pyzmq's ZAP handler checks each subscriber's public key during the CURVE handshake.
            self._auth = ThreadAuthenticator(self._ctx, log=logging.getLogger("edgecal.publish.zap"))
            self._auth.start()
            self._auth.configure_curve_callback("*", AllowedKeys(curve.clients))
            self._sock.curve_secretkey = curve.secret
            self._sock.curve_publickey = curve.public
            self._sock.curve_server = True
        try:
            self._sock.bind(endpoint)
        except zmq.ZMQError as exc:
            self.close()
            raise PublishError(f"cannot bind the pose stream to {endpoint} ({exc}); is another edgecal running?") \
                from None
        if not endpoint.startswith("inproc://"):      # inproc peers hold no descriptors
            self._limit = ConnectionLimit(self._sock, max_connections, _local_address(self._sock))

    @classmethod
    def from_settings(cls, settings: PublishSettings) -> PosePublisher:
        """The pose stream's socket, bound as the config's ``publish:`` section says."""
        return cls(settings.endpoint, settings.hwm, curve=settings.curve,
                   handshake_timeout_s=settings.handshake_timeout_s, max_connections=settings.max_connections)

    @property
    def refused_connections(self) -> int:
        """Connections shut down at accept because ``max_connections`` were held."""
        return self._limit.refused if self._limit is not None else 0

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

    def close(self, linger_s: float = 0.0) -> None:
        """Close the socket (and the context if this publisher created it); safe to call twice.

        ``linger_s``: how long messages still queued may take to leave (0: dropped at once).
        """
        if self._limit is not None:
            self._limit.close()
            self._limit = None
        if not self._sock.closed:
            self._sock.close(linger=int(linger_s * 1000))
        if self._auth is not None:
            self._auth.stop()
            self._auth = None
        if self._own_context and not self._ctx.closed:
            self._ctx.term()

    def __enter__(self) -> PosePublisher:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
