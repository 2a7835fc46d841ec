"""``rosbag:PATH?topic=T`` / ``rosbag:PATH?left=L&right=R``: image topics of a ROS 1 ``.bag`` file or a
ROS 2 bag folder (sqlite3 or mcap storage), read with ``rosbags`` (no ROS installation needed).

ROS 1 messages are deserialised into the same ROS 2 types (``sensor_msgs/msg/Image``; rosbags maps the
names), so both kinds go through the same conversion. Bags without embedded message definitions
(older ROS 2 sqlite3 bags) are decoded with the ROS 2 Humble type set. rosbags reads a bag through its
index, so a ROS 1 bag cut short before its index was written is refused at open ("reindex it":
``rosbag reindex``); a break while reading gives the frames before it and one InputError, as ``mcap:``.

A ROS 2 recorder that was killed leaves a folder without ``metadata.yaml`` (it is written at the end) and,
with mcap storage, a file without its summary; rosbags cannot open that. Such a folder's ``.mcap`` files
are then read record by record as ``mcap:`` reads them (drivers/mcap_source.py), one after the other, so
the frames recorded before the kill are still delivered.
"""

from __future__ import annotations

import logging
import sqlite3
import struct
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from mcap.exceptions import McapError
from rosbags.highlevel import AnyReader, AnyReaderError
from rosbags.rosbag1 import ReaderError as Ros1ReaderError
from rosbags.rosbag2 import ReaderError as Ros2ReaderError
from rosbags.serde import SerdeError
from rosbags.typesys import Stores, get_typestore

from edgecal.drivers.base import Source
from edgecal.drivers.mcap_source import McapLog
from edgecal.drivers.robolog import LogCorrupt, LogMessage, MessageLog, TopicInfo, open_log_source
from edgecal.drivers.ros_images import describe_msg
from edgecal.drivers.spec import SourceSpec
from edgecal.errors import InputError

# What a broken bag raises inside rosbags: its own errors, and the sqlite/struct/mcap/zstd ones underneath
# that it lets through for data cut short or garbled.
log = logging.getLogger("edgecal.drivers")

_READ_ERRORS = (AnyReaderError, Ros1ReaderError, Ros2ReaderError, SerdeError, McapError, sqlite3.Error,
                struct.error, ValueError, KeyError, IndexError, EOFError, OSError)


def _reader(path: Path) -> Any:
    try:
        return AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
    except _READ_ERRORS as exc:
        raise InputError(f"{path}: not a readable ROS bag ({_why(exc)})") from None


def _why(exc: BaseException) -> str:
    text = " ".join(str(a) for a in exc.args) or type(exc).__name__
    return text if len(text) <= 80 else text[:77] + "..."


class RosbagLog(MessageLog):
    """A ROS 1 bag or a ROS 2 bag folder: its topics and its decoded messages in time order."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path).expanduser()
        if not self.path.exists():
            raise InputError(f"{self.path}: no such bag (a ROS 1 .bag file or a ROS 2 bag folder)")
        if self.path.is_file() and self.path.suffix != ".bag":
            raise InputError(f"{self.path}: a ROS 1 bag ends in .bag; a ROS 2 bag is the folder with "
                             "metadata.yaml (for a bare .mcap file use mcap:)")
        self._topics: dict[str, TopicInfo] | None = None
        self.broken: LogCorrupt | None = None
        # The folder's .mcap files, read directly when rosbags cannot open the bag (a killed recorder).
        self._parts = sorted(self.path.glob("*.mcap")) if self.path.is_dir() else []
        self._direct: list[McapLog] | None = None

    def _open(self) -> Any:
        """An open rosbags reader; None when the bag is read directly from its .mcap files instead."""
        if self._direct is not None:
            return None
        try:
            reader = _reader(self.path)
            reader.open()
        except (InputError, *_READ_ERRORS) as exc:
            if self._parts:
                log.warning("%s: rosbags cannot open it (%s); reading its .mcap files directly", self.path, _why(exc))
                self._direct = [McapLog(p) for p in self._parts]
                return None
            hint = (" (a ROS 1 bag cut short has no index: `rosbag reindex` it)" if "index" in str(exc).lower()
                    else " (no metadata.yaml: `ros2 bag reindex` it)" if self.path.is_dir()
                    and not (self.path / "metadata.yaml").exists() else "")
            text = str(exc) if isinstance(exc, InputError) else f"{self.path}: cannot open the bag: {_why(exc)}"
            raise InputError(f"{text}{hint}") from None
        return reader

    def _direct_messages(self, topics: tuple[str, ...]) -> Iterator[LogMessage]:
        assert self._direct is not None
        for part in self._direct:
            try:
                yield from part.messages(topics)
            except LogCorrupt as exc:
                raise LogCorrupt(exc.offset, f"{part.path.name}: {exc.detail}") from None

    def messages(self, topics: tuple[str, ...]) -> Iterator[LogMessage]:
        """Decoded messages on ``topics`` in time order (rosbags merges the bag's files by time)."""
        reader = self._open()
        if reader is None:
            yield from self._direct_messages(topics)
            return
        try:
            conns = [c for c in reader.connections if c.topic in topics]
            if not conns:
                return
            it = reader.messages(connections=conns)
            n = 0
            while True:
                try:
                    conn, log_time, raw = next(it)
                    msg = reader.deserialize(raw, conn.msgtype)
                except StopIteration:
                    return
                except _READ_ERRORS as exc:
                    raise LogCorrupt(None, f"after message {n}: {_why(exc)}") from None
                n += 1
                yield LogMessage(conn.topic, conn.msgtype, int(log_time), msg)
        finally:
            reader.close()

    def topics(self) -> dict[str, TopicInfo]:
        """Topics, types and counts from the bag's index; image topics with their first message's size
        and encoding."""
        if self._topics is not None:
            return self._topics
        reader = self._open()
        if reader is None:
            out: dict[str, TopicInfo] = {}
            for part in self._direct or []:
                for name, info in part.topics().items():
                    have = out.setdefault(name, TopicInfo(name, info.msgtype, 0, info.encoding, info.size))
                    have.count += info.count
                self.broken = self.broken or part.broken
            self._topics = out
            return out
        try:
            out = {name: TopicInfo(name, t.msgtype or "", int(t.msgcount))
                   for name, t in reader.topics.items()}
        finally:
            reader.close()
        images = tuple(t for t, i in out.items() if i.is_image)
        seen: set[str] = set()
        try:
            for m in self.messages(images):
                if m.topic not in seen:
                    seen.add(m.topic)
                    d = describe_msg(m.msgtype, m.msg)
                    out[m.topic].encoding, out[m.topic].size = d["encoding"], d["size"]
                if len(seen) == len(images):
                    break
        except LogCorrupt as exc:
            self.broken = exc
        self._topics = out
        return out


def open_rosbag(spec: SourceSpec) -> Source:
    """The ``rosbag:`` source of ``spec``."""
    return open_log_source(spec, RosbagLog(spec.target))
