"""Recording to an MCAP file: each frame as a ROS 2 ``sensor_msgs/msg/Image`` (or ``CompressedImage``).

``edgecal record SOURCE --out FILE.mcap`` (or ``record(src, "FILE.mcap")``) writes this instead of a
PNG folder, so a recording opens in Foxglove and replays in ROS (``ros2 bag play FILE.mcap``) and in
edgecal (``mcap:FILE.mcap?topic=/camera/image_raw`` or ``?left=/left/image_raw&right=/right/image_raw``).

Topics: ``/camera/image_raw`` for a mono source, ``/left/image_raw`` and ``/right/image_raw`` for a
stereo one (``header.frame_id`` camera / left / right). ``header.stamp`` and the MCAP log time are the
frame's ``stamp_ns`` (so a replay through ``mcap:`` gives the same stamps back), the publish time is
the wall clock when it was written; the message sequence is the frame's ``seq``. Raw images are
lossless (mono8, mono16, bgr8, bgr16), as are PNG ones; JPEG is 8-bit only. The source's description
is stored as the file's ``edgecal`` metadata record.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

from edgecal.drivers.base import Frame, StereoFrame
from edgecal.drivers.recording import recording_layout
from edgecal.errors import InputError
from edgecal.mcap_writer import McapLogWriter
from edgecal.ros_messages import compressed_image_message, image_message

MONO_TOPIC = "/camera/image_raw"
LEFT_TOPIC = "/left/image_raw"
RIGHT_TOPIC = "/right/image_raw"
IMAGE_FORMATS = ("raw", "png", "jpeg")


class McapRecorder:
    """Writes frames (or stereo pairs) into one MCAP file; the same add()/close() as the PNG Recorder."""

    def __init__(self, out: str | Path, source: dict[str, Any], force: bool = False, image_format: str = "raw"
                 ) -> None:
        if image_format not in IMAGE_FORMATS:
            raise InputError(f"image format {image_format!r}: expected one of {', '.join(IMAGE_FORMATS)}")
        self.image_format = image_format
        self.layout: str | None = None
        self.frames = 0
        self.writer = McapLogWriter(out, force=force, flush_s=1.0,
                                    metadata={"source": json.dumps(source), "format": "edgecal-recording-mcap",
                                              "started_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())})
        self.out = self.writer.path

    def _write(self, topic: str, frame: Frame, frame_id: str) -> None:
        if self.image_format == "raw":
            msg = image_message(frame.image, frame.stamp_ns, frame_id)
        else:
            msg = compressed_image_message(frame.image, frame.stamp_ns, frame_id, self.image_format)
        self.writer.write(topic, msg, frame.stamp_ns, time.time_ns(), sequence=int(frame.seq) & 0xFFFFFFFF)

    def add(self, item: Frame | StereoFrame) -> None:
        """Append one frame or stereo pair (a recording holds one kind only)."""
        self.layout = recording_layout(self.layout, item, self.out)
        if isinstance(item, StereoFrame):
            self._write(LEFT_TOPIC, item.left, "left")
            self._write(RIGHT_TOPIC, item.right, "right")
        else:
            self._write(MONO_TOPIC, item, "camera")
        self.frames += 1

    def close(self) -> None:
        """Finish the file (summary and index)."""
        self.writer.close()
