"""The ``publish:`` fields of the live config that name frames, stamps and the outputs beside ZeroMQ.

::

    publish:
      endpoint: tcp://127.0.0.1:5560     # the ZeroMQ stream (edgecal/stream/config.py reads these three)
      allow_remote: false
      hwm: 4
      frame_id: rig                      # the parent frame of the pose (the rig = left camera)
      child_frame_id: robot              # the frame whose pose is measured
      stamp: monotonic                   # ROS header stamps: the source's stamp_ns, or realtime (CLOCK_REALTIME)
      record: out/poses.mcap             # or {path: ..., max_mb: 1024, flush_s: 1.0}
      foxglove: {port: 8765}             # a live Foxglove WebSocket server (see foxglove_sink.py)

Read by edgecal.config.read_settings from the fields below, so every mistake names its ``publish.`` field.
"""

from __future__ import annotations

import ipaddress
import re
from dataclasses import dataclass

from edgecal.config import ConfigReader, read_settings, section_keys, setting

STAMPS = ("monotonic", "realtime")
_FRAME_NAME = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_./-]*$")   # a tf2 frame name: no spaces, no leading '/'


@dataclass(frozen=True)
class RecordSettings:
    """The MCAP pose log."""

    path: str = setting(doc="the .mcap file (numbered files beside it after a rotation)")
    max_mb: float = setting(1024.0, doc="rotate to the next numbered file beyond this size (MiB)", positive=True)
    flush_s: float = setting(1.0, doc="chunks reach the file at least this often: what a kill can lose (s)",
                             minimum=0.05, maximum=60)
    queue: int = setting(1000, doc="messages waiting for the writer thread before new ones are dropped",
                         minimum=10, maximum=1_000_000)


def _is_local(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


@dataclass(frozen=True)
class FoxgloveSettings:
    """The live Foxglove WebSocket server."""

    port: int = setting(8765, doc="TCP port (0: any free one)", minimum=0, maximum=65535)
    host: str = setting("127.0.0.1", doc="interface to serve on; another than loopback needs allow_remote")
    allow_remote: bool = setting(False, doc="serve beyond the loopback interface on purpose")
    image_hz: float = setting(5.0, doc="images (and corner annotations) per camera per second, at most",
                              minimum=0, maximum=120)
    image_width: int = setting(640, doc="images are downscaled to at most this width ...", minimum=16,
                               maximum=8192)
    jpeg_quality: int = setting(70, doc="... and sent as JPEG of this quality", minimum=1, maximum=100)

    def config_problem(self) -> tuple[str, str] | None:
        """A host beyond loopback without allow_remote."""
        if not self.allow_remote and not _is_local(self.host):
            return ("host", f"{self.host[:80]!r} is reachable from other machines: set foxglove.allow_remote: true "
                            "to serve there on purpose")
        return None


def _read_record(r: ConfigReader, key: str) -> RecordSettings | None:
    """``record: FILE.mcap`` or ``record: {path: FILE.mcap, max_mb: ...}``; null: no log."""
    raw = r.data[key]
    if raw is None:
        return None
    if isinstance(raw, str):
        record = read_settings(RecordSettings, ConfigReader({"path": raw}, r.source, r.path(key)))
        if not record.path.endswith(".mcap"):
            raise r.fail(key, f"{record.path[:80]!r} must name a .mcap file")
        return record
    s = r.section(key)
    record = read_settings(RecordSettings, s)
    if not record.path.endswith(".mcap"):
        raise s.fail("path", f"{record.path[:80]!r} must name a .mcap file")
    return record


def _read_foxglove(r: ConfigReader, key: str) -> FoxgloveSettings | None:
    """``foxglove: true`` (the defaults), a mapping of its settings, or null/false: no server."""
    raw = r.data[key]
    if raw is None or raw is False:
        return None
    if raw is True:
        return FoxgloveSettings()
    return read_settings(FoxgloveSettings, r.section(key))


def _frame_name(name: str) -> str | None:
    if not _FRAME_NAME.match(name):
        return f"{name[:80]!r} is not a tf2 frame name (letters, digits, _ . / -, no leading '/')"
    return None


@dataclass(frozen=True)
class OutputSettings:
    """Frame names, stamps, and the optional MCAP log and Foxglove server."""

    frame_id: str = setting("rig", doc="the parent frame of the pose (the rig = left camera)")
    child_frame_id: str = setting("robot", doc="the frame whose pose is measured")
    stamp: str = setting("monotonic", doc="ROS header stamps: the source's stamp_ns, or realtime (CLOCK_REALTIME)",
                         choices=STAMPS)
    record: RecordSettings | None = setting(None, doc="the MCAP pose log: FILE.mcap or {path, max_mb, ...}",
                                            read=_read_record)
    foxglove: FoxgloveSettings | None = setting(None, doc="a live Foxglove WebSocket server: true or {port, ...}",
                                                read=_read_foxglove)

    def config_problem(self) -> tuple[str, str] | None:
        """Frame names that tf2 cannot use."""
        for key in ("frame_id", "child_frame_id"):
            problem = _frame_name(getattr(self, key))
            if problem:
                return (key, problem)
        if self.child_frame_id == self.frame_id:
            return ("child_frame_id", f"must differ from frame_id ({self.frame_id})")
        return None


OUTPUT_FIELDS = section_keys(OutputSettings)


def read_outputs(r: ConfigReader, *, ignore: tuple[str, ...] = ()) -> OutputSettings:
    """The output fields of a ``publish:`` section; ``ignore``: the ZeroMQ ones (read by the live config)."""
    return read_settings(OutputSettings, r, ignore=ignore)


__all__ = ["OUTPUT_FIELDS", "STAMPS", "FoxgloveSettings", "OutputSettings", "RecordSettings", "read_outputs"]
