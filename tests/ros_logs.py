"""Test helpers: robot logs written with the ROS libraries themselves (mcap-ros2-support, rosbags).

Independent of edgecal's own writers on purpose: a reader bug must not be hidden by the same bug in
the writer. Message definitions come from rosbags' ROS 2 Humble type store.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from mcap_ros2.writer import Writer as Ros2McapWriter
from rosbags.typesys import Stores, get_typestore

TYPESTORE = get_typestore(Stores.ROS2_HUMBLE)
IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
STRING = "std_msgs/msg/String"


def msgdef(msgtype: str) -> str:
    """The ros2msg text (with its dependencies) of a ROS 2 type."""
    return TYPESTORE.generate_msgdef(msgtype, ros_version=2)[0]


@dataclass
class LogImage:
    """One image message to write: topic, stamp, pixels and how to encode them."""

    topic: str
    stamp_ns: int
    image: np.ndarray
    encoding: str = "mono8"      # an Image encoding, or "jpeg"/"png" for a CompressedImage
    pad: int = 0                 # extra bytes at the end of each row (Image.step > width * bpp)
    bigendian: bool = False


def _header(stamp_ns: int, frame_id: str) -> dict[str, Any]:
    return {"stamp": {"sec": stamp_ns // 1_000_000_000, "nanosec": stamp_ns % 1_000_000_000}, "frame_id": frame_id}


def image_fields(item: LogImage) -> tuple[str, dict[str, Any]]:
    """(msgtype, message as a dict) of ``item``."""
    if item.encoding in ("jpeg", "png"):
        ok, buf = cv2.imencode("." + ("jpg" if item.encoding == "jpeg" else "png"), item.image)
        assert ok
        return COMPRESSED, {"header": _header(item.stamp_ns, "cam"), "format": item.encoding,
                            "data": buf.tobytes()}
    img = item.image
    if item.bigendian and img.dtype.itemsize > 1:
        img = img.astype(img.dtype.newbyteorder(">"))
    rows = np.ascontiguousarray(img).view(np.uint8).reshape(img.shape[0], -1)
    if item.pad:
        rows = np.hstack([rows, np.full((rows.shape[0], item.pad), 0xAB, np.uint8)])
    return IMAGE, {"header": _header(item.stamp_ns, "cam"), "height": img.shape[0], "width": img.shape[1],
                   "encoding": item.encoding, "is_bigendian": int(item.bigendian), "step": rows.shape[1],
                   "data": rows.tobytes()}


def write_mcap(path: Path, items: list[LogImage], extra_topics: dict[str, int] | None = None,
               chunk_size: int = 1 << 20) -> Path:
    """An MCAP file (ros2 profile, zstd chunks) of ``items`` in order; ``extra_topics`` adds std_msgs/String
    topics with that many messages (a topic that is not images)."""
    schemas: dict[str, Any] = {}
    with open(path, "wb") as f:
        w = Ros2McapWriter(f, chunk_size=chunk_size)
        for name in (IMAGE, COMPRESSED, STRING):
            schemas[name] = w.register_msgdef(name, msgdef(name))
        for topic, n in (extra_topics or {}).items():
            for i in range(n):
                w.write_message(topic, schemas[STRING], {"data": f"hello {i}"}, log_time=i)
        for i, item in enumerate(items):
            msgtype, msg = image_fields(item)
            w.write_message(item.topic, schemas[msgtype], msg, log_time=item.stamp_ns + 1000, sequence=i)
        w.finish()
    return path


def _typed(msgtype: str, msg: dict[str, Any]) -> Any:
    """``msg`` as rosbags' message class (nested dicts become the nested classes)."""
    T = TYPESTORE.types
    h = msg["header"]
    header = T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](**h["stamp"]), frame_id=h["frame_id"])
    data = np.frombuffer(msg["data"], np.uint8)
    if msgtype == COMPRESSED:
        return T[COMPRESSED](header=header, format=msg["format"], data=data)
    return T[IMAGE](header=header, height=msg["height"], width=msg["width"], encoding=msg["encoding"],
                    is_bigendian=msg["is_bigendian"], step=msg["step"], data=data)


def write_rosbag(path: Path, items: list[LogImage], kind: str) -> Path:
    """A ROS 1 bag (``kind`` "ros1", path ending in .bag) or a ROS 2 bag folder ("sqlite3" or "mcap")."""
    if kind == "ros1":
        from rosbags.rosbag1 import Writer
        conns: dict[str, Any] = {}
        with Writer(path) as w:
            for item in items:
                msgtype, msg = image_fields(item)
                if item.topic not in conns:
                    conns[item.topic] = w.add_connection(item.topic, msgtype, typestore=TYPESTORE)
                w.write(conns[item.topic], item.stamp_ns + 1000,
                        TYPESTORE.serialize_ros1(_typed(msgtype, msg), msgtype))
        return path
    from rosbags.rosbag2 import StoragePlugin
    from rosbags.rosbag2 import Writer as Writer2
    plugin = StoragePlugin.MCAP if kind == "mcap" else StoragePlugin.SQLITE3
    conns = {}
    with Writer2(path, version=9, storage_plugin=plugin) as w:
        for item in items:
            msgtype, msg = image_fields(item)
            if item.topic not in conns:
                conns[item.topic] = w.add_connection(item.topic, msgtype, typestore=TYPESTORE)
            w.write(conns[item.topic], item.stamp_ns + 1000, TYPESTORE.serialize_cdr(_typed(msgtype, msg), msgtype))
    return path


def gradient(i: int, shape: tuple[int, ...] = (24, 32), dtype: type = np.uint8) -> np.ndarray:
    """A distinct test image per index (grey or 3-channel, uint8 or uint16)."""
    h, w = shape[:2]
    y, x = np.mgrid[0:h, 0:w]
    top = 60000 if dtype == np.uint16 else 250
    base = ((x * 7 + y * 3 + i * 11) % top).astype(dtype)
    if len(shape) == 2:
        return base
    return np.dstack([(base + k * 40) % top for k in range(shape[2])]).astype(dtype)
