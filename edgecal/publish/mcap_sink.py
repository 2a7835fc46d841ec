"""``publish.record: FILE.mcap``: the pose stream as an MCAP log of ROS 2 messages.

Topics:

* ``/edgecal/pose``: ``geometry_msgs/msg/PoseWithCovarianceStamped`` of every valid pose (header
  ``frame_id`` = publish.frame_id);
* ``/tf``: ``tf2_msgs/msg/TFMessage`` with the same transform frame_id <- child_frame_id;
* ``/edgecal/pose_json``: every pose message as JSON, valid or not (the quality figures and the reason:
  a ROS pose message has no field for them);
* ``/edgecal/status``: the status messages as JSON.

Header stamps and log times follow ``publish.stamp``. The writing (serialisation, compression, the
disk) happens in a thread of its own behind a bounded queue: the loop only enqueues, and a queue that
is full (a stalled disk) drops messages and counts them. Chunks reach the file at least every
``flush_s``, so a kill loses at most that; the file rotates at ``max_mb`` to NAME.1.mcap, ...; a restart
continues with the next free number instead of overwriting.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from typing import Any

from edgecal.mcap_writer import McapLogWriter
from edgecal.publish.sink_settings import OutputSettings, RecordSettings
from edgecal.publish.sinks import FrameOutput, Sink, ros_stamp_ns
from edgecal.ros_messages import has_value, pose_message, transform_message

log = logging.getLogger("edgecal.publish")

POSE_TOPIC = "/edgecal/pose"
TF_TOPIC = "/tf"
POSE_JSON_TOPIC = "/edgecal/pose_json"
STATUS_TOPIC = "/edgecal/status"
_STOP = object()


class McapSink(Sink):
    """Poses, transforms and status into a rotating MCAP file, written by a background thread."""

    name = "mcap"

    def __init__(self, settings: RecordSettings, outputs: OutputSettings) -> None:
        self.settings = settings
        self.outputs = outputs
        self.writer = McapLogWriter(settings.path, flush_s=settings.flush_s,
                                    max_bytes=int(settings.max_mb * (1 << 20)), continue_numbering=True,
                                    metadata={"frame_id": outputs.frame_id, "child_frame_id": outputs.child_frame_id,
                                              "stamp": outputs.stamp})
        self._queue: queue.Queue = queue.Queue(maxsize=settings.queue)
        self._dropped = 0
        self.write_errors = 0
        self._thread = threading.Thread(target=self._run, name="mcap-sink", daemon=True)
        self._thread.start()
        log.info("recording poses to %s", self.writer.path)

    @property
    def dropped(self) -> int:
        """Messages dropped because the writer thread fell behind."""
        return self._dropped

    def _put(self, item: tuple) -> None:
        try:
            self._queue.put_nowait(item)
        except queue.Full:
            self._dropped += 1

    def frame(self, out: FrameOutput) -> None:
        """Enqueue the pose (the ROS messages are built in the writer thread)."""
        self._put(("pose", out.pose, out.message, ros_stamp_ns(out, self.outputs.stamp)))

    def status(self, message: dict[str, Any]) -> None:
        """Enqueue a status message, stamped per publish.stamp."""
        stamp = time.time_ns() if self.outputs.stamp == "realtime" else int(message.get("stamp_ns", 0))
        self._put(("status", message, stamp))

    def _write(self, item: tuple) -> None:
        w = self.writer
        if item[0] == "pose":
            _, pose, message, stamp = item
            if pose.valid and has_value(pose):
                w.write(POSE_TOPIC, pose_message(pose, stamp, self.outputs.frame_id), stamp)
                w.write(TF_TOPIC, transform_message(pose, stamp, self.outputs.frame_id, self.outputs.child_frame_id),
                        stamp)
            w.write_json(POSE_JSON_TOPIC, "edgecal.pose", message, stamp)
        else:
            _, message, stamp = item
            w.write_json(STATUS_TOPIC, "edgecal.status", message, stamp)

    def _run(self) -> None:
        while True:
            try:
                item = self._queue.get(timeout=self.settings.flush_s)
            except queue.Empty:
                item = None
            try:
                if item is _STOP:
                    return
                if item is not None:
                    self._write(item)
                elif self.writer.messages:
                    self.writer.flush()          # an idle loop still gets its last messages out
            except Exception as exc:  # noqa: BLE001 - a write error (disk full) must not end the thread
                self.write_errors += 1
                if self.write_errors == 1 or self.write_errors % 1000 == 0:
                    log.error("writing %s failed (%d times): %r", self.writer.path, self.write_errors, exc)

    def close(self) -> None:
        """Write what is queued, finish the file (summary and index) and stop the thread."""
        if self._thread.is_alive():
            self._queue.put(_STOP)
            self._thread.join(10.0)
        self.writer.close()
