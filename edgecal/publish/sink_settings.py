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

Validated here field by field, so every mistake names its ``publish.`` field.
"""

from __future__ import annotations

import ipaddress
import re
from dataclasses import dataclass

from edgecal.config import ConfigReader

OUTPUT_FIELDS = ("frame_id", "child_frame_id", "stamp", "record", "foxglove")
STAMPS = ("monotonic", "realtime")
_FRAME_NAME = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_./-]*$")   # a tf2 frame name: no spaces, no leading '/'


@dataclass(frozen=True)
class RecordSettings:
    """The MCAP pose log."""

    path: str
    max_mb: float = 1024.0          # rotate to the next numbered file beyond this size (MiB)
    flush_s: float = 1.0            # chunks reach the file at least this often: what a kill can lose
    queue: int = 1000               # messages waiting for the writer thread before new ones are dropped


@dataclass(frozen=True)
class FoxgloveSettings:
    """The live Foxglove WebSocket server."""

    port: int = 8765
    host: str = "127.0.0.1"         # another interface needs allow_remote
    allow_remote: bool = False
    image_hz: float = 5.0           # images (and corner annotations) per camera per second, at most
    image_width: int = 640          # images are downscaled to at most this width ...
    jpeg_quality: int = 70          # ... and sent as JPEG of this quality


@dataclass(frozen=True)
class OutputSettings:
    """Frame names, stamps, and the optional MCAP log and Foxglove server."""

    frame_id: str = "rig"
    child_frame_id: str = "robot"
    stamp: str = "monotonic"
    record: RecordSettings | None = None
    foxglove: FoxgloveSettings | None = None


def _frame_name(r: ConfigReader, key: str, default: str) -> str:
    name = r.string(key, default)
    if not _FRAME_NAME.match(name):
        raise r.fail(key, f"{name[:80]!r} is not a tf2 frame name (letters, digits, _ . / -, no leading '/')")
    return name


def _read_record(r: ConfigReader) -> RecordSettings | None:
    if not r.has("record") or r.raw("record") is None:
        return None
    if isinstance(r.raw("record"), str):
        s = ConfigReader({"path": r.raw("record")}, r.source, r.path("record"))
    else:
        s = r.section("record")
    s.reject_unknown(("path", "max_mb", "flush_s", "queue"))
    d = RecordSettings("")
    path = s.string("path")
    if not path.endswith(".mcap"):
        raise (r.fail("record", f"{path[:80]!r} must name a .mcap file") if isinstance(r.raw("record"), str)
               else s.fail("path", f"{path[:80]!r} must name a .mcap file"))
    return RecordSettings(path, s.number("max_mb", d.max_mb, positive=True),
                          s.number("flush_s", d.flush_s, minimum=0.05, maximum=60),
                          s.integer("queue", d.queue, minimum=10, maximum=1_000_000))


def _is_local(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def _read_foxglove(r: ConfigReader) -> FoxgloveSettings | None:
    if not r.has("foxglove") or r.raw("foxglove") in (None, False):
        return None
    s = r.section("foxglove", {}) if r.raw("foxglove") is not True else ConfigReader({}, r.source, r.path("foxglove"))
    s.reject_unknown(("port", "host", "allow_remote", "image_hz", "image_width", "jpeg_quality"))
    d = FoxgloveSettings()
    allow = s.boolean("allow_remote", d.allow_remote)
    host = s.string("host", d.host)
    if not allow and not _is_local(host):
        raise s.fail("host", f"{host[:80]!r} is reachable from other machines: set foxglove.allow_remote: true "
                             "to serve there on purpose")
    return FoxgloveSettings(port=s.integer("port", d.port, minimum=0, maximum=65535), host=host, allow_remote=allow,
                            image_hz=s.number("image_hz", d.image_hz, minimum=0, maximum=120),
                            image_width=s.integer("image_width", d.image_width, minimum=16, maximum=8192),
                            jpeg_quality=s.integer("jpeg_quality", d.jpeg_quality, minimum=1, maximum=100))


def read_outputs(r: ConfigReader) -> OutputSettings:
    """The output fields of a ``publish:`` section (the ZeroMQ ones are read by the live config)."""
    d = OutputSettings()
    frame_id = _frame_name(r, "frame_id", d.frame_id)
    child = _frame_name(r, "child_frame_id", d.child_frame_id)
    if child == frame_id:
        raise r.fail("child_frame_id", f"must differ from frame_id ({frame_id})")
    return OutputSettings(frame_id, child, r.string("stamp", d.stamp, choices=STAMPS), _read_record(r),
                          _read_foxglove(r))
