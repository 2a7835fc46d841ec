"""``publish.foxglove: {port: 8765}``: a live Foxglove WebSocket server (``foxglove-sdk``).

Open ``ws://HOST:PORT`` in Foxglove (app.foxglove.dev or the desktop app: "Open connection", Foxglove
WebSocket). Topics, with Foxglove's own message types:

* ``/edgecal/left/image``, ``/edgecal/right/image``: ``foxglove.CompressedImage``, each camera's image
  downscaled to at most ``image_width`` and JPEG-compressed, at most ``image_hz`` per camera;
* ``/edgecal/left/corners``, ``/edgecal/right/corners``: ``foxglove.ImageAnnotations``, the corners the
  pose was fitted to (one colour per board, its name at its first corner), for the same images;
* ``/tf``: ``foxglove.FrameTransforms``, the pose as the transform frame_id <- child_frame_id (valid poses);
* ``/edgecal/pose``: ``foxglove.PoseInFrame`` of the same pose, for plots;
* ``/edgecal/status``: the status messages (JSON).

It never slows the loop: the pose, transform and status are handed to the SDK (which sends from its own
threads and drops the oldest message for a client that falls behind, ``message_backlog_size``); images
are scaled and compressed in a thread of this sink from a one-frame mailbox, so a frame that arrives
while the previous one is still being compressed replaces it (counted in ``dropped``), and nothing is
encoded while no client subscribes. The server binds to localhost unless ``allow_remote``.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any

import cv2
import foxglove
import numpy as np
from foxglove.channels import (
    CompressedImageChannel,
    FrameTransformsChannel,
    ImageAnnotationsChannel,
    PoseInFrameChannel,
)
from foxglove.messages import (
    Color,
    CompressedImage,
    FrameTransform,
    FrameTransforms,
    ImageAnnotations,
    Point2,
    PointsAnnotation,
    PointsAnnotationType,
    Pose,
    PoseInFrame,
    Quaternion,
    TextAnnotation,
    Timestamp,
    Vector3,
)

from edgecal.errors import PublishError
from edgecal.publish.sink_settings import FoxgloveSettings, OutputSettings
from edgecal.publish.sinks import FrameOutput, Sink, ros_stamp_ns
from edgecal.ros_messages import has_value

log = logging.getLogger("edgecal.publish")

BACKLOG = 32                  # messages buffered per client before the oldest is dropped (SDK default 1024)
CORNER_DIAMETER_PX = 4.0
# One colour per board, in the order of the target's boards (cycled beyond six).
BOARD_COLOURS = ((0.1, 0.9, 0.2), (1.0, 0.6, 0.0), (0.2, 0.6, 1.0), (1.0, 0.2, 0.6), (0.9, 0.9, 0.1), (0.6, 0.3, 1.0))
SIDES = ("left", "right")


def _timestamp(ns: int) -> Timestamp:
    sec, nsec = divmod(int(ns), 1_000_000_000)
    return Timestamp(sec, nsec)


def preview_jpeg(image: np.ndarray, max_width: int, quality: int) -> tuple[bytes, float]:
    """(JPEG bytes, scale) of ``image`` downscaled to at most ``max_width`` (uint16 shown as its top 8 bits)."""
    if image.dtype == np.uint16:
        image = (image >> 8).astype(np.uint8)
    h, w = image.shape[:2]
    scale = min(1.0, max_width / w)
    if scale < 1.0:
        image = cv2.resize(image, (max(1, round(w * scale)), max(1, round(h * scale))), interpolation=cv2.INTER_AREA)
    ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise ValueError(f"JPEG encoding of a {image.shape} image failed")
    return buf.tobytes(), scale


def corner_annotations(detections: list, scale: float, stamp: Timestamp) -> ImageAnnotations:
    """The detected corners as Foxglove image annotations on an image scaled by ``scale``.

    OpenCV puts integer coordinates at pixel centres, Foxglove at the top-left corner of the first
    pixel: hence the half pixel before scaling.
    """
    points, texts = [], []
    for k, det in enumerate(detections):
        r, g, b = BOARD_COLOURS[k % len(BOARD_COLOURS)]
        colour = Color(r=r, g=g, b=b, a=1.0)
        xy = (np.asarray(det.corners, np.float64) + 0.5) * scale
        points.append(PointsAnnotation(timestamp=stamp, type=PointsAnnotationType.Points,
                                       points=[Point2(x=float(x), y=float(y)) for x, y in xy],
                                       outline_color=colour, fill_color=colour, thickness=CORNER_DIAMETER_PX))
        if len(xy):
            texts.append(TextAnnotation(timestamp=stamp, position=Point2(x=float(xy[0, 0]), y=float(xy[0, 1])),
                                        text=str(det.board), font_size=14.0, text_color=colour,
                                        background_color=Color(r=0, g=0, b=0, a=0.6)))
    return ImageAnnotations(points=points, texts=texts)


class FoxgloveSink(Sink):
    """A Foxglove WebSocket server showing the cameras, the corners, the pose and the status."""

    name = "foxglove"

    def __init__(self, settings: FoxgloveSettings, outputs: OutputSettings) -> None:
        self.settings = settings
        self.outputs = outputs
        self._ctx = foxglove.Context()
        try:
            server = foxglove.start_server(name="edgecal", host=settings.host, port=settings.port,
                                           context=self._ctx, message_backlog_size=BACKLOG)
        except Exception as exc:  # noqa: BLE001 - the SDK raises its own (Rust) error types for a bind failure
            raise PublishError(f"cannot serve Foxglove on {settings.host}:{settings.port} ({exc}); "
                              "is another edgecal running? (publish.foxglove.port)") from None
        self.server: foxglove.WebSocketServer | None = server
        self.port = int(server.port)
        self._images = {s: CompressedImageChannel(f"/edgecal/{s}/image", context=self._ctx) for s in SIDES}
        self._corners = {s: ImageAnnotationsChannel(f"/edgecal/{s}/corners", context=self._ctx) for s in SIDES}
        self._tf = FrameTransformsChannel("/tf", context=self._ctx)
        self._pose = PoseInFrameChannel("/edgecal/pose", context=self._ctx)
        self._status = foxglove.Channel("/edgecal/status", message_encoding="json", context=self._ctx)
        self._period_ns = int(1e9 / settings.image_hz) if settings.image_hz > 0 else None
        self._next_image_ns = 0
        self._mailbox: FrameOutput | None = None
        self._dropped = 0
        self.images_sent = 0
        self._wake = threading.Condition()
        self._stopping = False
        self._thread = threading.Thread(target=self._run, name="foxglove-images", daemon=True)
        self._thread.start()
        log.info("Foxglove server on ws://%s:%d", settings.host, self.port)

    @property
    def dropped(self) -> int:
        """Image frames replaced in the mailbox before they were compressed."""
        return self._dropped

    def frame(self, out: FrameOutput) -> None:
        """Send the pose and transform; hand the images to the compression thread at most image_hz."""
        stamp_ns = ros_stamp_ns(out, self.outputs.stamp)
        pose = out.pose
        if pose.valid and has_value(pose):
            t = [float(v) for v in pose.t_m]
            x, y, z, w = (float(v) for v in pose.quaternion_xyzw)
            ts = _timestamp(stamp_ns)
            self._tf.log(FrameTransforms(transforms=[FrameTransform(
                timestamp=ts, parent_frame_id=self.outputs.frame_id, child_frame_id=self.outputs.child_frame_id,
                translation=Vector3(x=t[0], y=t[1], z=t[2]), rotation=Quaternion(x=x, y=y, z=z, w=w))]),
                log_time=stamp_ns)
            self._pose.log(PoseInFrame(timestamp=ts, frame_id=self.outputs.frame_id,
                                       pose=Pose(position=Vector3(x=t[0], y=t[1], z=t[2]),
                                                 orientation=Quaternion(x=x, y=y, z=z, w=w))), log_time=stamp_ns)
        if self._period_ns is None:
            return
        now = time.monotonic_ns()
        if now < self._next_image_ns or not (any(c.has_sinks() for c in self._images.values())
                                             or any(c.has_sinks() for c in self._corners.values())):
            return
        self._next_image_ns = now + self._period_ns
        with self._wake:
            if self._mailbox is not None:
                self._dropped += 1
            self._mailbox = out
            self._wake.notify()

    def status(self, message: dict[str, Any]) -> None:
        """Send a status message (JSON)."""
        self._status.log(message, log_time=int(message.get("stamp_ns", 0)) or None)

    def _send_images(self, out: FrameOutput) -> None:
        stamp_ns = ros_stamp_ns(out, self.outputs.stamp)
        ts = _timestamp(stamp_ns)
        for side, frame, dets in zip(SIDES, (out.frame.left, out.frame.right), out.detections):
            if not isinstance(frame.image, np.ndarray) or frame.image.ndim not in (2, 3):
                continue                       # a corrupt frame: nothing to show
            data, scale = preview_jpeg(frame.image, self.settings.image_width, self.settings.jpeg_quality)
            # The rig frame is the left camera's; the right camera gets a frame of its own name.
            frame_id = self.outputs.frame_id if side == "left" else f"{self.outputs.frame_id}_right"
            self._images[side].log(CompressedImage(timestamp=ts, frame_id=frame_id, data=data, format="jpeg"),
                                   log_time=stamp_ns)
            self._corners[side].log(corner_annotations(dets, scale, ts), log_time=stamp_ns)
        self.images_sent += 1

    def _run(self) -> None:
        while True:
            with self._wake:
                while self._mailbox is None and not self._stopping:
                    self._wake.wait()
                if self._stopping:
                    return
                out, self._mailbox = self._mailbox, None
            assert out is not None  # woken with a frame in the mailbox
            try:
                self._send_images(out)
            except Exception as exc:  # noqa: BLE001 - a frame that fails to encode must not end the thread
                self.failures += 1
                if self.failures == 1 or self.failures % 1000 == 0:
                    log.error("Foxglove image preview failed (%d times): %r", self.failures, exc)

    def close(self) -> None:
        """Stop the compression thread and the server; safe to call twice."""
        with self._wake:
            self._stopping = True
            self._wake.notify()
        self._thread.join(5.0)
        if self.server is not None:
            server, self.server = self.server, None
            server.stop()
