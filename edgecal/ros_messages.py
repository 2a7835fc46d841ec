"""ROS 2 messages built from edgecal's values, and their CDR bytes and schema text.

The one place that builds each ROS message edgecal writes (MCAP recordings, the pose log, the Foxglove
view): ``sensor_msgs/msg/Image`` and ``CompressedImage`` from an image, ``PoseWithCovarianceStamped`` and
``tf2_msgs/msg/TFMessage`` from a Pose. Types, serialisation (CDR, little-endian) and the ros2msg schema
text come from ``rosbags``' ROS 2 Humble type store, so no ROS installation is needed. Pure functions.

Frames: the pose is T_frame_child (it maps child-frame points into ``frame_id``, the rig = left camera),
which is what a ROS transform with ``header.frame_id = frame_id`` and ``child_frame_id = child`` means.
The 6x6 covariance is row-major in (x, y, z, rot x, rot y, rot z), metres and radians, as ROS's.
"""

from __future__ import annotations

import functools
from typing import Any

import cv2
import numpy as np
from rosbags.typesys import Stores, get_typestore

from edgecal.drivers.ros_images import COMPRESSED_TYPE, IMAGE_TYPE, raw_fields
from edgecal.errors import InputError
from edgecal.pose.types import Pose

POSE_TYPE = "geometry_msgs/msg/PoseWithCovarianceStamped"
TF_TYPE = "tf2_msgs/msg/TFMessage"
TYPESTORE = get_typestore(Stores.ROS2_HUMBLE)
_T = TYPESTORE.types
JPEG_QUALITY = 90          # default CompressedImage JPEG quality (OpenCV's scale 0-100)


@functools.cache
def schema_text(msgtype: str) -> str:
    """The ros2msg definition of ``msgtype`` with its dependencies (the text an MCAP schema record holds)."""
    return TYPESTORE.generate_msgdef(msgtype, ros_version=2)[0]


def cdr(msg: Any) -> bytes:
    """The CDR bytes of a message built here."""
    return bytes(TYPESTORE.serialize_cdr(msg, msg.__msgtype__))


def header(stamp_ns: int, frame_id: str) -> Any:
    """std_msgs/msg/Header with ``stamp_ns`` split into sec and nanosec."""
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    return _T["std_msgs/msg/Header"](stamp=_T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec),
                                     frame_id=frame_id)


def image_message(image: np.ndarray, stamp_ns: int, frame_id: str) -> Any:
    """sensor_msgs/msg/Image holding ``image`` unchanged (mono8, mono16, bgr8 or bgr16)."""
    encoding, h, w, step, data = raw_fields(image)
    return _T[IMAGE_TYPE](header=header(stamp_ns, frame_id), height=h, width=w, encoding=encoding,
                          is_bigendian=0, step=step, data=np.frombuffer(data, np.uint8))


def compressed_image_message(image: np.ndarray, stamp_ns: int, frame_id: str, fmt: str = "jpeg",
                             quality: int = JPEG_QUALITY) -> Any:
    """sensor_msgs/msg/CompressedImage of ``image`` as ``fmt`` ("jpeg": 8-bit only, or "png": lossless)."""
    if fmt == "jpeg":
        if image.dtype != np.uint8:
            raise InputError(f"cannot write a {image.dtype} image as JPEG (8-bit only; use png or raw)")
        ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    elif fmt == "png":
        ok, buf = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, 1])
    else:
        raise InputError(f"unknown image compression {fmt!r} (jpeg or png)")
    if not ok:
        raise InputError(f"OpenCV could not encode a {image.dtype} {image.shape} image as {fmt}")
    return _T[COMPRESSED_TYPE](header=header(stamp_ns, frame_id), format=fmt, data=buf.ravel())


def _pose_fields(pose: Pose) -> Any:
    t = [float(v) for v in pose.t_m]
    x, y, z, w = (float(v) for v in pose.quaternion_xyzw)
    return _T["geometry_msgs/msg/Pose"](position=_T["geometry_msgs/msg/Point"](x=t[0], y=t[1], z=t[2]),
                                        orientation=_T["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w))


def has_value(pose: Pose) -> bool:
    """True when the pose holds numbers (an invalid pose may still have been computed)."""
    return bool(np.all(np.isfinite(pose.t_m)) and np.all(np.isfinite(pose.quaternion_xyzw)))


def pose_message(pose: Pose, stamp_ns: int, frame_id: str) -> Any:
    """geometry_msgs/msg/PoseWithCovarianceStamped: the child frame's pose in ``frame_id`` with its covariance
    (non-finite covariance entries become -1, ROS's "unknown")."""
    cov = np.asarray(pose.covariance, np.float64).reshape(36)
    cov = np.where(np.isfinite(cov), cov, -1.0)
    return _T[POSE_TYPE](header=header(stamp_ns, frame_id),
                         pose=_T["geometry_msgs/msg/PoseWithCovariance"](pose=_pose_fields(pose), covariance=cov))


def transform_message(pose: Pose, stamp_ns: int, frame_id: str, child_frame_id: str) -> Any:
    """tf2_msgs/msg/TFMessage with the one transform frame_id <- child_frame_id."""
    t = [float(v) for v in pose.t_m]
    x, y, z, w = (float(v) for v in pose.quaternion_xyzw)
    tf = _T["geometry_msgs/msg/TransformStamped"](
        header=header(stamp_ns, frame_id), child_frame_id=child_frame_id,
        transform=_T["geometry_msgs/msg/Transform"](
            translation=_T["geometry_msgs/msg/Vector3"](x=t[0], y=t[1], z=t[2]),
            rotation=_T["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w)))
    return _T[TF_TYPE](transforms=[tf])
