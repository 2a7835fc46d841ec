"""USB and CSI cameras through Video4Linux2, using OpenCV's V4L2 backend (cv2.CAP_V4L2).

Why OpenCV and not linuxpy: OpenCV is already a dependency of edgecal, its V4L2 backend negotiates
the format, decodes MJPG/YUYV to BGR (or hands GREY/Y16 through raw), sets size, fps, exposure and
gain, honours a read timeout, and reports each frame's kernel buffer timestamp (CAP_PROP_POS_MSEC,
the v4l2_buffer timestamp, CLOCK_MONOTONIC for UVC and most CSI drivers). That covers what
calibration and the live loop need, with one fewer package on the robot. See docs/drivers.md.

``v4l2:/dev/videoN``. Settings: width, height, fps, pixel_format (a FOURCC: GREY, Y16, YUYV, UYVY,
MJPG, BGR3, RGB3, NV12), exposure_us (manual exposure, V4L2's 100 µs units), gain (the driver's raw
units), buffers (kernel queue length; small = low latency).
"""

from __future__ import annotations

import errno
import fcntl
import glob
import os
import re
import stat
import struct
import time
from dataclasses import dataclass
from pathlib import Path

import cv2

from edgecal.config import setting
from edgecal.drivers.base import Frame, Source
from edgecal.drivers.spec import CameraSettings, SourceSpec, buffers_setting
from edgecal.errors import DeviceAbsent, DeviceError, DeviceLost, DeviceTimeout

# FOURCCs OpenCV hands through undecoded when CAP_PROP_CONVERT_RGB is off (grey sensors).
_RAW_FORMATS = ("GREY", "Y16")


@dataclass(frozen=True)
class V4L2Settings(CameraSettings):
    """Settings of a V4L2 camera."""

    pixel_format: str | None = setting(None, doc="the FOURCC to capture",
                                       choices=("GREY", "Y16", "YUYV", "UYVY", "MJPG", "BGR3", "RGB3", "NV12"))
    gain: float | None = setting(None, doc="gain in the device's raw units (V4L2 has no standard unit)", minimum=0)
    buffers: int = buffers_setting()


def check_device_node(path: str) -> None:
    """DeviceError unless ``path`` is a character device this user may open read/write."""
    p = Path(path)
    if not p.exists():
        raise DeviceAbsent(f"v4l2:{path}: no such device (is the camera plugged in? `edgecal sources` lists the "
                          "V4L2 devices)")
    mode = p.stat().st_mode
    if not stat.S_ISCHR(mode):
        raise DeviceAbsent(f"v4l2:{path}: not a device node (expected a character device such as /dev/video0)")
    if not os.access(path, os.R_OK | os.W_OK):
        raise DeviceAbsent(f"v4l2:{path}: no permission to open the device (add the user to the "
                          f"'video' group: sudo usermod -aG video $USER, then log in again)")


# VIDIOC_QUERYCAP = _IOR('V', 0, struct v4l2_capability): driver[16] card[32] bus_info[32] version
# capabilities device_caps reserved[3] (104 bytes, linux/videodev2.h).
VIDIOC_QUERYCAP = 0x80685600
_CAPABILITY = struct.Struct("16s32s32sIII12x")
V4L2_CAP_VIDEO_CAPTURE = 0x00000001
V4L2_CAP_VIDEO_CAPTURE_MPLANE = 0x00001000
V4L2_CAP_DEVICE_CAPS = 0x80000000


def query_capabilities(path: str) -> tuple[str, bool]:
    """(card name, whether the node captures video) from VIDIOC_QUERYCAP; DeviceError if it is no V4L2 node.

    A UVC camera creates two nodes: one captures, the other carries metadata only.
    """
    try:
        fd = os.open(path, os.O_RDWR | os.O_NONBLOCK)
    except PermissionError:
        raise DeviceAbsent(f"v4l2:{path}: no permission to open the device (add the user to the 'video' group: "
                          "sudo usermod -aG video $USER, then log in again)") from None
    except OSError as exc:
        raise DeviceAbsent(f"v4l2:{path}: cannot open ({exc.strerror})") from None
    try:
        buf = bytearray(_CAPABILITY.size)
        try:
            fcntl.ioctl(fd, VIDIOC_QUERYCAP, buf)
        except OSError as exc:
            if exc.errno in (errno.ENOTTY, errno.EINVAL):
                raise DeviceAbsent(f"v4l2:{path}: not a V4L2 device (it does not answer VIDIOC_QUERYCAP)") from None
            raise DeviceAbsent(f"v4l2:{path}: VIDIOC_QUERYCAP failed ({exc.strerror})") from None
    finally:
        os.close(fd)
    _, card, _, _, caps, device_caps = _CAPABILITY.unpack(bytes(buf))
    effective = device_caps if caps & V4L2_CAP_DEVICE_CAPS else caps
    capture = bool(effective & (V4L2_CAP_VIDEO_CAPTURE | V4L2_CAP_VIDEO_CAPTURE_MPLANE))
    return card.split(b"\0", 1)[0].decode(errors="replace"), capture


def device_index(path: str) -> int:
    """N of the /dev/videoN node that ``path`` is or links to; DeviceError for any other device."""
    real = os.path.realpath(path)
    m = re.fullmatch(r"/dev/video(\d+)", real)
    if not m:
        raise DeviceAbsent(f"v4l2:{path}: not a V4L2 capture device (expected /dev/videoN or a link to one, "
                          f"got {real})")
    return int(m.group(1))


def list_devices() -> list[dict]:
    """The /dev/video* nodes with their driver-given name and whether this user may open them."""
    out = []
    for dev in sorted(glob.glob("/dev/video*"), key=lambda d: (len(d), d)):
        name_file = Path("/sys/class/video4linux") / Path(dev).name / "name"
        try:
            name = name_file.read_text().strip()
        except OSError:
            name = "?"
        try:
            card, capture = query_capabilities(dev)
            why = "" if capture else "not a capture node (metadata or output)"
            name = card or name
        except DeviceError as exc:
            capture, why = False, str(exc).split(": ", 1)[-1]
        out.append({"uri": f"v4l2:{dev}", "name": name, "usable": capture, "why": why})
    return out


class V4L2Source(Source):
    """One V4L2 capture device."""

    live = True

    def __init__(self, spec: SourceSpec) -> None:
        super().__init__(spec.uri, spec.settings)
        self.spec = spec
        self._cap: cv2.VideoCapture | None = None
        self._seq = 0
        self._last_stamp = 0
        self.exposure_us: float | None = None
        self.gain: float | None = None

    def describe(self) -> dict:
        """URI and the settings in force."""
        out = {"uri": self.uri, "driver": "v4l2", "settings": self.settings.as_dict()}
        if self._cap is not None:
            fourcc = int(self._cap.get(cv2.CAP_PROP_FOURCC))
            out.update(width=int(self._cap.get(cv2.CAP_PROP_FRAME_WIDTH)),
                       height=int(self._cap.get(cv2.CAP_PROP_FRAME_HEIGHT)), fps=self._cap.get(cv2.CAP_PROP_FPS),
                       pixel_format="".join(chr((fourcc >> (8 * i)) & 0xFF) for i in range(4)))
        return out

    def _open(self) -> None:
        """Open the device node, negotiate the format and apply exposure/gain."""
        if self._cap is not None:
            return
        path = self.spec.target
        check_device_node(path)
        card, capture = query_capabilities(path)
        if not capture:
            raise DeviceAbsent(f"{self.uri}: {card or 'the device'} has no video capture on this node (UVC cameras "
                              "have a second, metadata-only node: try the other /dev/videoN)")
        s = self.settings
        params = [cv2.CAP_PROP_READ_TIMEOUT_MSEC, int(s.timeout_s * 1000)]
        # OpenCV's V4L2 backend opens /dev/videoN by its index N (udev symlinks are resolved first).
        cap = cv2.VideoCapture(device_index(path), cv2.CAP_V4L2, params)
        if not cap.isOpened():
            cap.release()
            raise DeviceAbsent(f"{self.uri}: not a V4L2 capture device, or busy (another program has it open?)")
        self._cap = cap
        try:
            if s.pixel_format:
                cap.set(cv2.CAP_PROP_FOURCC, cv2.VideoWriter.fourcc(*s.pixel_format.ljust(4)))
                if s.pixel_format in _RAW_FORMATS:
                    cap.set(cv2.CAP_PROP_CONVERT_RGB, 0)
            if s.width:
                cap.set(cv2.CAP_PROP_FRAME_WIDTH, s.width)
            if s.height:
                cap.set(cv2.CAP_PROP_FRAME_HEIGHT, s.height)
            if s.fps:
                cap.set(cv2.CAP_PROP_FPS, s.fps)
            cap.set(cv2.CAP_PROP_BUFFERSIZE, s.buffers)
            if s.exposure_us is not None:
                cap.set(cv2.CAP_PROP_AUTO_EXPOSURE, 1)  # V4L2_EXPOSURE_MANUAL
                if not cap.set(cv2.CAP_PROP_EXPOSURE, s.exposure_us / 100.0):
                    raise DeviceError(f"{self.uri}: the device refused exposure_us={s.exposure_us:g}")
                self.exposure_us = cap.get(cv2.CAP_PROP_EXPOSURE) * 100.0
            if s.gain is not None and not cap.set(cv2.CAP_PROP_GAIN, s.gain):
                raise DeviceError(f"{self.uri}: the device refused gain={s.gain:g}")
            self._check_size()
        except BaseException:
            self.close()
            raise

    def _check_size(self) -> None:
        assert self._cap is not None
        s = self.settings
        w, h = int(self._cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(self._cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        if (s.width and w != s.width) or (s.height and h != s.height):
            raise DeviceError(f"{self.uri}: the device does not offer {s.width}x{s.height} "
                              f"(it chose {w}x{h}; `v4l2-ctl --list-formats-ext -d {self.spec.target}` lists sizes)")

    def _read(self, timeout_s: float | None) -> Frame:
        """The next frame with its kernel timestamp; DeviceTimeout after the timeout, DeviceLost on unplug."""
        assert self._cap is not None
        timeout = self.settings.timeout_s if timeout_s is None else timeout_s
        self._cap.set(cv2.CAP_PROP_READ_TIMEOUT_MSEC, int(timeout * 1000))
        t0 = time.monotonic()
        ok = self._cap.grab()
        if not ok:
            waited = time.monotonic() - t0
            if waited >= 0.9 * timeout:
                raise DeviceTimeout(f"{self.uri}: no frame within {timeout:g} s")
            raise DeviceLost(f"{self.uri}: the device stopped (unplugged?) within {timeout:g} s")
        recv = time.monotonic_ns()
        ok, image = self._cap.retrieve()
        if not ok or image is None:
            raise DeviceError(f"{self.uri}: a frame arrived but could not be decoded")
        stamp_ms = self._cap.get(cv2.CAP_PROP_POS_MSEC)
        stamp = int(round(stamp_ms * 1e6)) if stamp_ms > 0 else recv
        self._seq += 1
        return Frame(image, stamp, recv, self._seq, self.spec.camera_id, self.exposure_us, None)

    def _close(self) -> None:
        """Release the device (safe to call twice)."""
        cap, self._cap = self._cap, None
        if cap is not None:
            cap.release()
