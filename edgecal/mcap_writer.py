"""An MCAP file of ROS 2 messages (and JSON ones) that a kill leaves readable: the writer behind
``edgecal record --out FILE.mcap`` and the pose log sink.

Written with the ``mcap`` library in zstd chunks. A chunk is closed and handed to the operating system
when it fills up or when ``flush_s`` has passed since the last one, so a killed process loses at most
the messages of the chunk in progress (at most ``flush_s`` of them): everything before it is in the file
and readable without the summary a clean close appends (edgecal's ``mcap:`` reads such files, so do
Foxglove and ``mcap recover``). With ``max_bytes`` the log rotates: the file is finished and the next
one, ``NAME.1.mcap``, ``NAME.2.mcap``..., started. A file that exists is never overwritten unless
``force``; with ``continue_numbering`` (a daemon restarted) the next free number is used instead.
The file is created with the umask's permissions.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

from mcap.writer import CompressionType, Writer

from edgecal.errors import InputError
from edgecal.fileio import permission_denied
from edgecal.ros_messages import cdr, schema_text

CHUNK_BYTES = 1 << 20          # mcap's default chunk size: images fill it quickly, poses by flush_s
LIBRARY = "edgecal"


def numbered(path: Path, index: int) -> Path:
    """``path`` for part ``index`` of a rotated log: part 0 is ``path`` itself, then NAME.1.mcap, ..."""
    return path if index == 0 else path.with_name(f"{path.stem}.{index}{path.suffix}")


class McapLogWriter:
    """Writes ROS 2 (CDR) and JSON messages into an MCAP file (rotated by size), flushing chunks by time."""

    def __init__(self, path: str | Path, force: bool = False, flush_s: float = 1.0, max_bytes: int | None = None,
                 continue_numbering: bool = False, metadata: dict[str, str] | None = None) -> None:
        self.base = Path(path).expanduser()
        if self.base.suffix != ".mcap":
            raise InputError(f"{self.base}: an MCAP log file name ends in .mcap")
        self.force = force
        self.flush_s = flush_s
        self.max_bytes = max_bytes
        self.metadata = dict(metadata or {})
        self.index = 0
        if continue_numbering:
            while numbered(self.base, self.index).exists():
                self.index += 1
        self.messages = 0
        self.files: list[Path] = []
        self._file: Any = None
        self._writer: Writer | None = None
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._last_flush = time.monotonic()
        self._open()

    @property
    def path(self) -> Path:
        """The file being written now."""
        return numbered(self.base, self.index)

    def _open(self) -> None:
        path = self.path
        if path.exists() and not self.force:
            raise InputError(f"{path}: exists (choose another file name, or --force to replace it)")
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            self._file = open(path, "wb")
        except PermissionError:
            raise permission_denied(path, "MCAP file") from None
        except OSError as exc:
            raise InputError(f"{path}: cannot write ({exc.strerror or exc})") from None
        self._writer = Writer(self._file, chunk_size=CHUNK_BYTES, compression=CompressionType.ZSTD)
        self._writer.start(profile="ros2", library=LIBRARY)
        if self.metadata:
            self._writer.add_metadata("edgecal", self.metadata)
        self._schemas.clear()
        self._channels.clear()
        self.files.append(path)

    def _channel(self, topic: str, msgtype: str, encoding: str) -> int:
        key = f"{topic}\0{msgtype}"
        cid = self._channels.get(key)
        if cid is not None:
            return cid
        assert self._writer is not None
        sid = self._schemas.get(msgtype)
        if sid is None:
            if encoding == "cdr":
                sid = self._writer.register_schema(msgtype, "ros2msg", schema_text(msgtype).encode())
            else:
                sid = self._writer.register_schema(msgtype, "jsonschema", json.dumps({"type": "object"}).encode())
            self._schemas[msgtype] = sid
        cid = self._writer.register_channel(topic, encoding, sid)
        self._channels[key] = cid
        return cid

    def _add(self, cid: int, data: bytes, log_time_ns: int, publish_time_ns: int | None, sequence: int) -> None:
        assert self._writer is not None
        self._writer.add_message(cid, int(log_time_ns), data,
                                 int(log_time_ns if publish_time_ns is None else publish_time_ns), sequence)
        self.messages += 1
        now = time.monotonic()
        if now - self._last_flush >= self.flush_s:
            self.flush()
        if self.max_bytes is not None and self._file.tell() >= self.max_bytes:
            self.rotate()

    def write(self, topic: str, msg: Any, log_time_ns: int, publish_time_ns: int | None = None,
              sequence: int = 0) -> None:
        """Append a ROS 2 message (built by edgecal.ros_messages) on ``topic``."""
        self._add(self._channel(topic, msg.__msgtype__, "cdr"), cdr(msg), log_time_ns, publish_time_ns, sequence)

    def write_json(self, topic: str, name: str, message: dict[str, Any], log_time_ns: int) -> None:
        """Append a JSON object on ``topic`` (schema ``name``)."""
        data = json.dumps(message, separators=(",", ":"), allow_nan=False).encode("utf-8")
        self._add(self._channel(topic, name, "json"), data, log_time_ns, None, 0)

    def flush(self) -> None:
        """Close the chunk in progress and hand everything to the operating system."""
        if self._writer is not None:
            self._writer.flush()
        self._last_flush = time.monotonic()

    def rotate(self) -> None:
        """Finish this file (with its summary) and continue in the next numbered one."""
        self._finish()
        self.index += 1
        self._open()

    def _finish(self) -> None:
        if self._writer is not None:
            writer, self._writer = self._writer, None
            try:
                writer.finish()
            finally:
                self._file.close()

    def close(self) -> None:
        """Finish the file (summary and index written); safe to call twice."""
        self._finish()

    def __enter__(self) -> McapLogWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
