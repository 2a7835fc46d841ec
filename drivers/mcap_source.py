"""``mcap:PATH?topic=T`` / ``mcap:PATH?left=L&right=R``: image topics of an MCAP file (ROS 2 messages).

Read with the ``mcap`` library's StreamReader, record by record in file order, so that a file without
its summary (a recorder that was killed) is read as far as it goes, and the byte offset of a broken
record can be named; messages are decoded by ``mcap-ros2-support`` (CDR with ros2msg schemas). The
summary, when there is one, gives the topic list and counts without a scan.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator
from pathlib import Path

from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Channel, Chunk, DataEnd, Footer, Message, Schema
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap_ros2.decoder import DecoderFactory
from zstandard import ZstdError

from edgecal.drivers.base import Source
from edgecal.drivers.robolog import LogCorrupt, LogMessage, MessageLog, TopicInfo, open_log_source
from edgecal.drivers.ros_images import IMAGE_TYPES, describe_msg
from edgecal.drivers.spec import SourceSpec
from edgecal.errors import InputError
from edgecal.fileio import permission_denied

# What a broken record raises inside the libraries: their own errors, and the struct/zstd/lz4/CDR errors
# of data that is cut short or garbled.
# (lz4 raises RuntimeError for bad frames; zstandard's ZstdError is an Exception of its own.)
_READ_ERRORS = (McapError, ValueError, struct.error, EOFError, IndexError, KeyError, TypeError, OSError, MemoryError,
                RuntimeError, ZstdError)


class McapLog(MessageLog):
    """An MCAP file: its topics (from the summary, or a scan) and its decoded messages in file order."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path).expanduser()
        if not self.path.is_file():
            raise InputError(f"{self.path}: no such MCAP file")
        try:
            with self.path.open("rb") as f:
                magic = f.read(8)
        except PermissionError:
            raise permission_denied(self.path, "MCAP file") from None
        if magic != b"\x89MCAP0\r\n":
            raise InputError(f"{self.path}: not an MCAP file (no MCAP magic at the start)")
        self._topics: dict[str, TopicInfo] | None = None
        self.broken: LogCorrupt | None = None      # set by a scan that met a broken record

    def _records(self) -> Iterator[tuple[int, object]]:
        """(offset, record) of every record, chunks broken up; LogCorrupt at the first one that fails."""
        with self.path.open("rb") as f:
            reader = StreamReader(f, emit_chunks=True, record_size_limit=1 << 32)
            records = reader.records
            while True:
                offset = f.tell()
                try:
                    record = next(records)
                except StopIteration:
                    return
                except _READ_ERRORS as exc:
                    raise LogCorrupt(offset, _why(exc)) from None
                if isinstance(record, (DataEnd, Footer)):
                    return                          # the summary section follows: no messages in it
                if isinstance(record, Chunk):
                    try:
                        inner = breakup_chunk(record, validate_crc=True)
                    except _READ_ERRORS as exc:
                        raise LogCorrupt(offset, f"chunk: {_why(exc)}") from None
                    for r in inner:
                        yield offset, r
                else:
                    yield offset, record

    def messages(self, topics: tuple[str, ...]) -> Iterator[LogMessage]:
        """Decoded messages on ``topics`` in file order."""
        schemas: dict[int, Schema] = {}
        channels: dict[int, Channel] = {}
        decoders: dict[int, object] = {}
        factory = DecoderFactory()
        for offset, record in self._records():
            if isinstance(record, Schema):
                schemas[record.id] = record
            elif isinstance(record, Channel):
                channels[record.id] = record
            elif isinstance(record, Message):
                channel = channels.get(record.channel_id)
                if channel is None or channel.topic not in topics:
                    continue
                decode = decoders.get(channel.id)
                schema = schemas.get(channel.schema_id)
                if decode is None:
                    try:
                        decode = factory.decoder_for(channel.message_encoding, schema)
                    except _READ_ERRORS as exc:
                        raise InputError(f"{self.path}: cannot decode topic {channel.topic}: {_why(exc)}") from None
                    if decode is None:
                        raise InputError(f"{self.path}: topic {channel.topic} is {channel.message_encoding!r} with "
                                         f"a {schema.encoding if schema else 'missing'} schema; edgecal reads ROS 2 "
                                         "messages (cdr, ros2msg)")
                    decoders[channel.id] = decode
                try:
                    msg = decode(record.data)  # type: ignore[operator]
                except _READ_ERRORS as exc:
                    raise LogCorrupt(offset, f"message on {channel.topic}: {_why(exc)}") from None
                yield LogMessage(channel.topic, schema.name if schema else "", record.log_time, msg)

    def topics(self) -> dict[str, TopicInfo]:
        """Topics, types and counts (summary, else a scan), image topics with their first message's size
        and encoding."""
        if self._topics is None:
            self._topics = self._summary_topics() or self._scan_topics()
            images = tuple(t for t, i in self._topics.items() if i.is_image)
            seen: set[str] = set()
            try:
                for m in self.messages(images):
                    if m.topic not in seen:
                        seen.add(m.topic)
                        info = self._topics[m.topic]
                        d = describe_msg(m.msgtype, m.msg)
                        info.encoding, info.size = d["encoding"], d["size"]
                    if len(seen) == len(images):
                        break
            except LogCorrupt as exc:
                self.broken = exc
        return self._topics

    def _summary_topics(self) -> dict[str, TopicInfo] | None:
        try:
            with self.path.open("rb") as f:
                summary = make_reader(f).get_summary()
        except _READ_ERRORS:
            return None                      # no footer or summary (a cut file): scan instead
        if summary is None or summary.statistics is None:
            return None
        counts = summary.statistics.channel_message_counts
        out: dict[str, TopicInfo] = {}
        for cid, ch in summary.channels.items():
            schema = summary.schemas.get(ch.schema_id)
            info = out.setdefault(ch.topic, TopicInfo(ch.topic, schema.name if schema else "", 0))
            info.count += int(counts.get(cid, 0))
        return out

    def _scan_topics(self) -> dict[str, TopicInfo]:
        schemas: dict[int, Schema] = {}
        channels: dict[int, Channel] = {}
        out: dict[str, TopicInfo] = {}
        try:
            for _, record in self._records():
                if isinstance(record, Schema):
                    schemas[record.id] = record
                elif isinstance(record, Channel):
                    channels[record.id] = record
                    schema = schemas.get(record.schema_id)
                    out.setdefault(record.topic, TopicInfo(record.topic, schema.name if schema else "", 0))
                elif isinstance(record, Message) and record.channel_id in channels:
                    out[channels[record.channel_id].topic].count += 1
        except LogCorrupt as exc:
            self.broken = exc
        return out


def _why(exc: BaseException) -> str:
    text = str(exc) or type(exc).__name__
    if type(exc).__name__ == "EndOfFile":
        text = "the file ends inside a record"
    return text if len(text) <= 80 else text[:77] + "..."


def open_mcap(spec: SourceSpec) -> Source:
    """The ``mcap:`` source of ``spec``."""
    return open_log_source(spec, McapLog(spec.target))


__all__ = ["IMAGE_TYPES", "McapLog", "open_mcap"]
