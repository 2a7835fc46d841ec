"""ROS image messages to and from the arrays every edgecal source delivers.

Pure functions shared by the ``mcap:`` and ``rosbag:`` sources and by the MCAP writers: a decoded
``sensor_msgs/msg/Image`` or ``sensor_msgs/msg/CompressedImage`` (any object with the message's fields:
mcap-ros2-support's and rosbags' decoded messages both qualify) in, a uint8/uint16 grey (H, W) or BGR
(H, W, 3) array out, as the other drivers give (RGB, BGRA and RGBA are turned into BGR; Bayer mosaics
are demosaiced to BGR). Nothing here reads files.
"""

from __future__ import annotations

import sys
from typing import Any

import cv2
import numpy as np

from edgecal.errors import InputError, quote

IMAGE_TYPE = "sensor_msgs/msg/Image"
COMPRESSED_TYPE = "sensor_msgs/msg/CompressedImage"
IMAGE_TYPES = (IMAGE_TYPE, COMPRESSED_TYPE)

# encoding -> (dtype, channels, cv2 conversion to grey/BGR or None to keep as it is)
RAW_ENCODINGS: dict[str, tuple[type, int, int | None]] = {
    "mono8": (np.uint8, 1, None),
    "8UC1": (np.uint8, 1, None),
    "mono16": (np.uint16, 1, None),
    "16UC1": (np.uint16, 1, None),
    "bgr8": (np.uint8, 3, None),
    "8UC3": (np.uint8, 3, None),
    "rgb8": (np.uint8, 3, cv2.COLOR_RGB2BGR),
    "bgra8": (np.uint8, 4, cv2.COLOR_BGRA2BGR),
    "rgba8": (np.uint8, 4, cv2.COLOR_RGBA2BGR),
    "bgr16": (np.uint16, 3, None),
    "rgb16": (np.uint16, 3, cv2.COLOR_RGB2BGR),
    # ROS names a mosaic by its top-left 2x2 block; OpenCV 5's explicit RGGB/BGGR/... codes mean the same
    # (the older two-letter codes BayerRG/BayerBG are shifted by one pixel and would swap red and blue).
    "bayer_rggb8": (np.uint8, 1, cv2.COLOR_BayerRGGB2BGR),
    "bayer_bggr8": (np.uint8, 1, cv2.COLOR_BayerBGGR2BGR),
    "bayer_gbrg8": (np.uint8, 1, cv2.COLOR_BayerGBRG2BGR),
    "bayer_grbg8": (np.uint8, 1, cv2.COLOR_BayerGRBG2BGR),
    "bayer_rggb16": (np.uint16, 1, cv2.COLOR_BayerRGGB2BGR),
    "bayer_bggr16": (np.uint16, 1, cv2.COLOR_BayerBGGR2BGR),
    "bayer_gbrg16": (np.uint16, 1, cv2.COLOR_BayerGBRG2BGR),
    "bayer_grbg16": (np.uint16, 1, cv2.COLOR_BayerGRBG2BGR),
    # packed 4:2:2 (uyvy / yuyv byte orders)
    "yuv422": (np.uint8, 2, cv2.COLOR_YUV2BGR_UYVY),
    "uyvy": (np.uint8, 2, cv2.COLOR_YUV2BGR_UYVY),
    "yuv422_yuy2": (np.uint8, 2, cv2.COLOR_YUV2BGR_YUY2),
    "yuyv": (np.uint8, 2, cv2.COLOR_YUV2BGR_YUY2),
}
COMPRESSED_FORMATS = ("jpeg", "png")


def stamp_ns(msg: Any) -> int:
    """The message header's stamp in nanoseconds (builtin_interfaces/Time: sec, nanosec)."""
    stamp = msg.header.stamp
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def compressed_format(fmt: str) -> str | None:
    """'jpeg' or 'png' for a CompressedImage ``format`` field ("jpeg", "bgr8; jpeg compressed bgr8",
    "png", "mono16; png compressed", ...), None for anything else (e.g. compressedDepth, qoi)."""
    text = fmt.lower()
    if "compresseddepth" in text:
        return None
    if "jpeg" in text or "jpg" in text:
        return "jpeg"
    if "png" in text:
        return "png"
    return None


def image_from_raw(msg: Any, where: str) -> np.ndarray:
    """The pixels of a ``sensor_msgs/msg/Image`` as grey or BGR (uint8/uint16); InputError naming ``where``
    for an unsupported encoding or a data size that does not match height x step."""
    encoding = str(msg.encoding)
    spec = RAW_ENCODINGS.get(encoding) or RAW_ENCODINGS.get(encoding.lower())
    if spec is None:
        raise InputError(f"{where}: unsupported image encoding {quote(encoding)} "
                         f"(supported: {', '.join(RAW_ENCODINGS)})")
    dtype, channels, conversion = spec
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    itemsize = np.dtype(dtype).itemsize
    row = w * channels * itemsize if channels != 2 else w * 2
    data = msg.data
    buf = np.frombuffer(data, np.uint8) if not isinstance(data, np.ndarray) else data.view(np.uint8).ravel()
    if h <= 0 or w <= 0 or step < row or buf.size < h * step:
        raise InputError(f"{where}: {encoding} image {w}x{h} with step {step} needs {h * max(step, row)} bytes, "
                         f"the message holds {buf.size}")
    rows = buf[:h * step].reshape(h, step)[:, :row]          # drop any row padding
    pixels: np.ndarray
    if channels == 2:                                          # 4:2:2: two bytes per pixel
        pixels = np.ascontiguousarray(rows).reshape(h, w, 2)
    else:
        pixels = np.ascontiguousarray(rows).view(dtype).reshape((h, w) if channels == 1 else (h, w, channels))
        big = bool(msg.is_bigendian)
        if itemsize > 1 and big != (sys.byteorder == "big"):
            pixels = pixels.byteswap()
    if conversion is not None:
        pixels = cv2.cvtColor(pixels, conversion)
    return pixels


def image_from_compressed(msg: Any, where: str) -> np.ndarray:
    """The decoded pixels of a ``sensor_msgs/msg/CompressedImage`` (JPEG or PNG) as grey or BGR."""
    kind = compressed_format(str(msg.format))
    if kind is None:
        raise InputError(f"{where}: unsupported compressed image format {quote(str(msg.format))} "
                         f"(supported: {', '.join(COMPRESSED_FORMATS)})")
    data = msg.data
    buf = np.frombuffer(data, np.uint8) if not isinstance(data, np.ndarray) else data.view(np.uint8).ravel()
    image = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED) if buf.size else None
    if image is None:
        raise InputError(f"{where}: the {kind} data ({buf.size} bytes) does not decode")
    if image.ndim == 3 and image.shape[2] == 4:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
    return image


def image_from_msg(msgtype: str, msg: Any, where: str) -> np.ndarray:
    """Pixels of an Image or CompressedImage message (``msgtype`` is its ROS 2 type name)."""
    if msgtype == COMPRESSED_TYPE:
        return image_from_compressed(msg, where)
    return image_from_raw(msg, where)


def describe_msg(msgtype: str, msg: Any) -> dict[str, Any]:
    """Size and encoding of one image message, without decoding the pixels where it can be avoided."""
    if msgtype == COMPRESSED_TYPE:
        out: dict[str, Any] = {"encoding": str(msg.format)}
        try:
            image = image_from_compressed(msg, "")
            out["size"] = f"{image.shape[1]}x{image.shape[0]}"
        except InputError:
            out["size"] = "?"
        return out
    return {"encoding": str(msg.encoding), "size": f"{int(msg.width)}x{int(msg.height)}"}


def raw_fields(image: np.ndarray) -> tuple[str, int, int, int, bytes]:
    """(encoding, height, width, step, data) of a sensor_msgs/msg/Image holding ``image`` unchanged:
    grey uint8 -> mono8, grey uint16 -> mono16, BGR uint8 -> bgr8, BGR uint16 -> bgr16 (little-endian)."""
    if image.dtype not in (np.uint8, np.uint16) or image.ndim not in (2, 3) or \
            (image.ndim == 3 and image.shape[2] != 3):
        raise InputError(f"cannot write a {image.dtype} image of shape {image.shape} as a ROS Image "
                         "(grey or BGR, uint8 or uint16)")
    deep = image.dtype == np.uint16
    encoding = ("mono16" if deep else "mono8") if image.ndim == 2 else ("bgr16" if deep else "bgr8")
    data = np.ascontiguousarray(image.astype("<u2", copy=False) if deep else image)
    h, w = image.shape[:2]
    return encoding, h, w, data.strides[0], data.tobytes()
