"""Image topics of a robot log (an MCAP file or a ROS bag) as a Source.

The ``mcap:`` and ``rosbag:`` drivers differ only in how they read the file; both hand this module a
:class:`MessageLog` - the log's topics, and its messages in file order - and get back a mono Source
(``topic=``) or a StereoSource (``left=`` + ``right=``, the two topics paired by header stamp within
``max_skew_ms`` by the same TimestampPairer as ``stereo:``).

``stamp_ns`` is the message header's stamp (the log time when a driver left the header stamp at
zero); ``seq`` counts the topic's messages from 0. ``pace``, ``loop`` and the stamp shift of later
loop passes are as for ``replay:``. A log that ends in the middle of a record (a recorder killed, a
copy cut short) or holds a corrupt record gives its frames up to there, then one InputError naming
the byte offset; the next read ends the pass (or, with ``loop``, starts the next one).
"""

from __future__ import annotations

import abc
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from edgecal.config import setting
from edgecal.drivers.base import Frame, Source, StereoFrame, StereoSource
from edgecal.drivers.replay import DEFAULT_FPS, Pacer
from edgecal.drivers.ros_images import IMAGE_TYPES, image_from_msg, stamp_ns
from edgecal.drivers.spec import SourceSettings, SourceSpec, pace_setting, skew_setting
from edgecal.drivers.stereo import TimestampPairer
from edgecal.errors import InputError, quote


@dataclass(frozen=True)
class RobotLogSettings(SourceSettings):
    """Settings of an image topic (or a left and a right one) of an MCAP file or a ROS bag."""

    topic: str | None = setting(None, doc="the image topic of a mono source")
    left: str | None = setting(None, doc="the left image topic of a stereo source")
    right: str | None = setting(None, doc="the right image topic of a stereo source")
    pace: str = pace_setting()
    loop: bool = setting(False, doc="start again at the end")
    max_skew_ms: float = skew_setting()


class LogCorrupt(Exception):
    """The log cannot be read past ``offset`` (a truncated or corrupt record); ``detail`` says what broke."""

    def __init__(self, offset: int | None, detail: str) -> None:
        super().__init__(detail)
        self.offset = offset
        self.detail = detail


@dataclass(frozen=True)
class LogMessage:
    """One decoded message of a log."""

    topic: str
    msgtype: str            # ROS 2 type name, e.g. sensor_msgs/msg/Image
    log_time_ns: int        # when the recorder logged it
    msg: Any                # the decoded message (fields as attributes)


@dataclass
class TopicInfo:
    """What a log holds on one topic."""

    topic: str
    msgtype: str
    count: int
    encoding: str = ""      # first message's encoding (Image) or format (CompressedImage)
    size: str = ""          # first message's WIDTHxHEIGHT

    @property
    def is_image(self) -> bool:
        """True for sensor_msgs Image and CompressedImage topics."""
        return self.msgtype in IMAGE_TYPES


class MessageLog(abc.ABC):
    """A robot log file read through its own library: the topics, and the messages in file order."""

    path: Path

    @abc.abstractmethod
    def topics(self) -> dict[str, TopicInfo]:
        """Every topic with its type and message count (image topics also with size and encoding)."""

    @abc.abstractmethod
    def messages(self, topics: tuple[str, ...]) -> Iterator[LogMessage]:
        """The decoded messages on ``topics`` in file order; raises LogCorrupt where the file breaks."""


def image_topic_list(infos: dict[str, TopicInfo]) -> str:
    """The image topics as 'topic (type, N messages)', for error messages."""
    images = [i for i in infos.values() if i.is_image]
    if not images:
        return "the log holds no sensor_msgs Image or CompressedImage topic"
    return "image topics: " + ", ".join(f"{i.topic} ({i.msgtype.rsplit('/', 1)[-1]}, {i.count})" for i in images)


def check_topics(log: MessageLog, wanted: tuple[str, ...]) -> dict[str, TopicInfo]:
    """The log's topics; InputError when one of ``wanted`` is absent or holds no images (listing those that do)."""
    infos = log.topics()
    for topic in wanted:
        info = infos.get(topic)
        if info is None:
            raise InputError(f"{log.path}: no topic {quote(topic)}; {image_topic_list(infos)}")
        if not info.is_image:
            raise InputError(f"{log.path}: topic {topic} holds {info.msgtype}, not images; {image_topic_list(infos)}")
    return infos


class _Reader:
    """Walks the log's messages on the wanted topics, pass after pass, turning breaks into one InputError."""

    def __init__(self, log: MessageLog, topics: tuple[str, ...], loop: bool) -> None:
        self.log = log
        self.topics = topics
        self.loop = loop
        self.passes = 0
        self.delivered = 0                 # messages delivered in this pass
        self._it: Iterator[LogMessage] | None = None
        self._ended = False

    def next(self) -> LogMessage | None:
        """The next message; None at the end (of the last pass); InputError at a break in the file."""
        while True:
            if self._ended:
                return None
            if self._it is None:
                self._it = self.log.messages(self.topics)
            try:
                return next(self._it)
            except StopIteration:
                broken = None
            except LogCorrupt as exc:
                broken = exc
            self._it = None
            empty = self.delivered == 0
            n = self.delivered
            if not self.loop or empty:
                self._ended = True
            else:
                self.passes += 1
                self.delivered = 0
            if broken is not None:
                where = f"at byte {broken.offset}" if broken.offset is not None else "part-way"
                raise InputError(f"{self.log.path}: truncated or corrupt {where} ({broken.detail}); "
                                 f"the {n} messages before it were read")
            if self._ended:
                return None


class _Timeline:
    """Stamps, seq and pacing over loop passes: later passes are shifted by the first pass's length."""

    def __init__(self, fast: bool) -> None:
        self.pacer = Pacer(fast)
        self.first_ns: int | None = None
        self.last_ns = 0
        self.count = 0                     # frames in the first pass
        self.span_ns = 0                   # length of one pass, known once the first has ended

    def note(self, stamp: int, passes: int) -> None:
        """Record a first-pass stamp (the span of a pass is measured from them)."""
        if passes == 0:
            if self.first_ns is None:
                self.first_ns = stamp
            self.last_ns = max(self.last_ns, stamp)
            self.count += 1

    def shift(self, passes: int) -> int:
        """Nanoseconds added to the stamps of pass ``passes``."""
        if passes == 0 or self.first_ns is None:
            return 0
        if not self.span_ns:
            period = (self.last_ns - self.first_ns) // max(self.count - 1, 1) if self.count > 1 \
                else int(1e9 / DEFAULT_FPS)
            self.span_ns = self.last_ns - self.first_ns + period
        return passes * self.span_ns


def _frame(m: LogMessage, seq: int, camera_id: str, where: str, shift: int) -> Frame:
    image = image_from_msg(m.msgtype, m.msg, where)
    stamp = stamp_ns(m.msg) or m.log_time_ns
    return Frame(image, stamp + shift, time.monotonic_ns(), seq, camera_id)


class LogImageSource(Source):
    """One image topic of a log as a mono Source."""

    def __init__(self, spec: SourceSpec, log: MessageLog) -> None:
        super().__init__(spec.uri, spec.settings)
        self.spec = spec
        self.log = log
        self.topic = str(spec.settings.topic)
        self.camera_id = spec.settings.camera_id or self.topic
        self._reader: _Reader | None = None
        self._timeline = _Timeline(spec.settings.pace == "fast")
        self._seq = 0

    def describe(self) -> dict:
        """The URI, the driver, the topic and the settings."""
        return {"uri": self.uri, "driver": self.spec.driver, "topic": self.topic,
                "settings": self.spec.settings.as_dict()}

    def _open(self) -> None:
        """Check the topic exists and holds images; start at the first message."""
        check_topics(self.log, (self.topic,))
        self._reader = _Reader(self.log, (self.topic,), self.spec.settings.loop)
        self._seq = 0

    def _read(self, timeout_s: float | None) -> Frame | None:
        """The next image (paced per ``pace``), None at the end; InputError for an undecodable message."""
        assert self._reader is not None
        m = self._reader.next()
        if m is None:
            return None
        passes = self._reader.passes
        seq = self._seq
        self._seq += 1
        self._reader.delivered += 1
        frame = _frame(m, seq, self.camera_id, f"{self.log.path} {m.topic} #{self._reader.delivered - 1}",
                       self._timeline.shift(passes))
        self._timeline.note(frame.stamp_ns, passes)
        self._timeline.pacer.wait(frame.stamp_ns)
        frame.recv_ns = time.monotonic_ns()          # delivered now, after the pacing wait
        return frame

    def _close(self) -> None:
        """Forget the position (the file is opened per pass by the log)."""
        self._reader = None


class LogStereoSource(StereoSource):
    """Two image topics of a log as a StereoSource, paired by header stamp within ``max_skew_ms``."""

    def __init__(self, spec: SourceSpec, log: MessageLog) -> None:
        super().__init__(spec.uri, spec.settings)
        self.spec = spec
        self.log = log
        self.left_topic = str(spec.settings.left)
        self.right_topic = str(spec.settings.right)
        cid = spec.settings.camera_id
        self.left_id = f"{cid}#left" if cid else self.left_topic
        self.right_id = f"{cid}#right" if cid else self.right_topic
        self.pairer = TimestampPairer(int(spec.settings.max_skew_ms * 1e6))
        self._reader: _Reader | None = None
        self._timeline = _Timeline(spec.settings.pace == "fast")
        self._seq = {self.left_topic: 0, self.right_topic: 0}

    @property
    def dropped(self) -> int:
        """Frames without a partner within max_skew_ms."""
        return self.pairer.dropped

    def describe(self) -> dict:
        """The URI, the driver, both topics and the settings."""
        return {"uri": self.uri, "driver": self.spec.driver, "left": self.left_topic, "right": self.right_topic,
                "settings": self.spec.settings.as_dict()}

    def _open(self) -> None:
        """Check both topics exist and hold images; start at the first message."""
        if self.left_topic == self.right_topic:
            raise InputError(f"{self.uri}: left and right are the same topic {self.left_topic}")
        check_topics(self.log, (self.left_topic, self.right_topic))
        self._reader = _Reader(self.log, (self.left_topic, self.right_topic), self.spec.settings.loop)
        self.pairer.left.clear()
        self.pairer.right.clear()
        self._seq = {self.left_topic: 0, self.right_topic: 0}

    def _read(self, timeout_s: float | None) -> StereoFrame | None:
        """The next pair (paced per ``pace``), None at the end; InputError for an undecodable message."""
        assert self._reader is not None
        while True:
            pair = self.pairer.pop_pair()
            if pair is not None:
                break
            passes = self._reader.passes
            try:
                m = self._reader.next()
            except InputError:
                self.pairer.left.clear()       # a break ends the pass: no pairing across it
                self.pairer.right.clear()
                raise
            if m is None:
                return None
            if self._reader.passes != passes:   # (only after a clean end: the pass restarted)
                self.pairer.left.clear()
                self.pairer.right.clear()
            self._reader.delivered += 1
            seq = self._seq[m.topic]
            self._seq[m.topic] = seq + 1
            left = m.topic == self.left_topic
            frame = _frame(m, seq, self.left_id if left else self.right_id,
                           f"{self.log.path} {m.topic} #{seq}", self._timeline.shift(self._reader.passes))
            (self.pairer.push_left if left else self.pairer.push_right)(frame)
        self._timeline.note(pair.stamp_ns, self._reader.passes)
        self._timeline.pacer.wait(pair.stamp_ns)
        pair.left.recv_ns = pair.right.recv_ns = time.monotonic_ns()
        return pair

    def _close(self) -> None:
        """Forget the position and any unpaired frames."""
        self._reader = None
        self.pairer.left.clear()
        self.pairer.right.clear()


def open_log_source(spec: SourceSpec, log: MessageLog) -> Source:
    """A mono source for ``topic=``, a stereo source for ``left=`` + ``right=`` (the spec has checked which)."""
    if spec.settings.topic:
        return LogImageSource(spec, log)
    return LogStereoSource(spec, log)
