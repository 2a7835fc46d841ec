"""systemd's notify protocol, spoken directly: one datagram per state change to $NOTIFY_SOCKET.

No libsystemd binding is needed: the protocol is a UNIX datagram of ``KEY=VALUE`` lines. Without
$NOTIFY_SOCKET (not started by systemd) every call is a no-op.
"""

from __future__ import annotations

import os
import socket


class SystemdNotifier:
    """Sends READY=1, WATCHDOG=1, STATUS=..., STOPPING=1 to the socket named by $NOTIFY_SOCKET."""

    def __init__(self, address: str | None = None) -> None:
        addr = os.environ.get("NOTIFY_SOCKET") if address is None else address
        self._sock: socket.socket | None = None
        self._addr: str | None = None
        if addr:
            # An abstract-namespace socket is written with a leading '@' and addressed with a NUL.
            self._addr = "\0" + addr[1:] if addr.startswith("@") else addr
            self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
            # A full receive queue on the other end must never stall the loop: drop the message instead.
            self._sock.setblocking(False)

    @property
    def enabled(self) -> bool:
        """Whether a notify socket was given."""
        return self._sock is not None

    def notify(self, *lines: str) -> bool:
        """Send ``lines`` as one message; False when disabled or the send failed (never raises, never blocks)."""
        if self._sock is None or self._addr is None:
            return False
        try:
            self._sock.sendto("\n".join(lines).encode("utf-8"), self._addr)
            return True
        except OSError:
            return False

    def ready(self, status: str = "") -> bool:
        """READY=1 (Type=notify: the service counts as started)."""
        return self.notify("READY=1", *([f"STATUS={status}"] if status else []))

    def watchdog(self) -> bool:
        """WATCHDOG=1 (the loop is alive)."""
        return self.notify("WATCHDOG=1")

    def status(self, text: str) -> bool:
        """STATUS=... (shown by systemctl status)."""
        return self.notify(f"STATUS={text}")

    def reloading(self) -> bool:
        """RELOADING=1 while the config is reloaded."""
        return self.notify("RELOADING=1")

    def stopping(self) -> bool:
        """STOPPING=1 before a clean exit."""
        return self.notify("STOPPING=1")

    def close(self) -> None:
        """Close the socket."""
        if self._sock is not None:
            self._sock.close()
            self._sock = None
