"""IEEE-1394 (FireWire, IIDC) cameras through libdc1394 (ctypes against Debian's libdc1394.so.25).

``dc1394:GUID`` opens the camera with that 64-bit GUID (hexadecimal); ``dc1394:`` the first one found.
Settings: width/height (a fixed IIDC mode of that size and pixel_format if the camera has one, else a
Format_7 region), fps, pixel_format (Mono8, Mono16, RGB8, YUV422, Raw8), exposure_us (the shutter's
absolute control), gain (raw register units), trigger (free, hardware = external trigger mode 0 on
source 0), iso_speed (400, 800 ...), buffers (DMA ring size).

Timestamps: libdc1394 stamps each frame with the wall-clock time (µs) at which the kernel filled the
ring buffer; it is mapped onto CLOCK_MONOTONIC with the current wall-minus-monotonic offset.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import select
import time
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from edgecal.config import setting
from edgecal.drivers.base import Frame, Source
from edgecal.drivers.spec import CameraSettings, SourceSpec, buffers_setting
from edgecal.errors import DeviceAbsent, DeviceError, DeviceTimeout

LIBRARY_NAMES = ("libdc1394.so.25", "libdc1394.so.22", "libdc1394.so")

# Enumerations from dc1394/types.h, video.h, capture.h, control.h (libdc1394 2.x ABI).
COLOR_MONO8, COLOR_YUV422, COLOR_RGB8, COLOR_MONO16, COLOR_RAW8 = 352, 354, 356, 357, 361
CODINGS = {"Mono8": COLOR_MONO8, "Mono16": COLOR_MONO16, "RGB8": COLOR_RGB8, "YUV422": COLOR_YUV422,
           "Raw8": COLOR_RAW8}


@dataclass(frozen=True)
class DC1394Settings(CameraSettings):
    """Settings of an IEEE-1394 (IIDC) camera."""

    pixel_format: str | None = setting(None, doc="IIDC colour coding", choices=tuple(CODINGS))
    gain: float | None = setting(None, doc="gain in raw register units", minimum=0)
    trigger: str = setting("free", doc="free running, or hardware (external trigger mode 0)",
                           choices=("free", "hardware"))
    iso_speed: int | None = setting(None, doc="bus speed (Mb/s)", minimum=100, maximum=3200)
    buffers: int = buffers_setting()
VIDEO_MODE_FORMAT7_0 = 88
FRAMERATE_FIRST = 32            # DC1394_FRAMERATE_1_875, then doubling up to 240 fps
FRAMERATES = [1.875 * 2 ** i for i in range(8)]
CAPTURE_POLICY_POLL = 673
FEATURE_SHUTTER, FEATURE_GAIN, FEATURE_FRAME_RATE = 423, 424, 431
FEATURE_MODE_MANUAL = 736
SWITCH_OFF, SWITCH_ON = 0, 1
TRIGGER_MODE_0, TRIGGER_SOURCE_0 = 384, 576
CAPTURE_FLAGS_DEFAULT = 0x04
OPERATION_MODE_1394B = 481
ISO_SPEEDS = {100: 0, 200: 1, 400: 2, 800: 3, 1600: 4, 3200: 5}


class CameraId(ctypes.Structure):
    """dc1394camera_id_t"""

    _fields_ = [("unit", ctypes.c_uint16), ("guid", ctypes.c_uint64)]


class CameraList(ctypes.Structure):
    """dc1394camera_list_t"""

    _fields_ = [("num", ctypes.c_uint32), ("ids", ctypes.POINTER(CameraId))]


class VideoFrame(ctypes.Structure):
    """dc1394video_frame_t (120 bytes on 64-bit Linux; checked against the C header)."""

    _fields_ = [("image", ctypes.POINTER(ctypes.c_ubyte)), ("size", ctypes.c_uint32 * 2),
                ("position", ctypes.c_uint32 * 2), ("color_coding", ctypes.c_int), ("color_filter", ctypes.c_int),
                ("yuv_byte_order", ctypes.c_uint32), ("data_depth", ctypes.c_uint32), ("stride", ctypes.c_uint32),
                ("video_mode", ctypes.c_int), ("total_bytes", ctypes.c_uint64), ("image_bytes", ctypes.c_uint32),
                ("padding_bytes", ctypes.c_uint32), ("packet_size", ctypes.c_uint32),
                ("packets_per_frame", ctypes.c_uint32), ("timestamp", ctypes.c_uint64),
                ("frames_behind", ctypes.c_uint32), ("camera", ctypes.c_void_p), ("id", ctypes.c_uint32),
                ("allocated_image_bytes", ctypes.c_uint64), ("little_endian", ctypes.c_int),
                ("data_in_padding", ctypes.c_int)]


class VideoModes(ctypes.Structure):
    """dc1394video_modes_t"""

    _fields_ = [("num", ctypes.c_uint32), ("modes", ctypes.c_int * 32)]


class Framerates(ctypes.Structure):
    """dc1394framerates_t"""

    _fields_ = [("num", ctypes.c_uint32), ("framerates", ctypes.c_int * 8)]


_lib: Any = None


def load_library() -> Any:
    """The libdc1394 shared library with prototypes; DeviceError saying what to install when absent."""
    global _lib
    if _lib is not None:
        return _lib
    names = list(LIBRARY_NAMES)
    found = ctypes.util.find_library("dc1394")
    if found:
        names.insert(0, found)
    lib = None
    for name in names:
        try:
            lib = ctypes.CDLL(name)
            break
        except OSError:
            continue
    if lib is None:
        raise DeviceAbsent("the IEEE-1394 driver is unavailable: libdc1394 is not installed "
                          "(Debian/Ubuntu: apt-get install libdc1394-25)")
    # one-letter type names keep the prototype table below readable
    P, V, U32, I = ctypes.c_void_p, ctypes.c_void_p, ctypes.c_uint32, ctypes.c_int  # noqa: E741
    protos = {
        "dc1394_new": (P, []), "dc1394_free": (None, [P]),
        "dc1394_camera_enumerate": (I, [P, ctypes.POINTER(ctypes.POINTER(CameraList))]),
        "dc1394_camera_free_list": (None, [ctypes.POINTER(CameraList)]),
        "dc1394_camera_new": (P, [P, ctypes.c_uint64]), "dc1394_camera_free": (None, [V]),
        "dc1394_error_get_string": (ctypes.c_char_p, [I]),
        "dc1394_video_get_supported_modes": (I, [V, ctypes.POINTER(VideoModes)]),
        "dc1394_video_get_supported_framerates": (I, [V, I, ctypes.POINTER(Framerates)]),
        "dc1394_get_image_size_from_video_mode": (I, [V, I, ctypes.POINTER(U32), ctypes.POINTER(U32)]),
        "dc1394_get_color_coding_from_video_mode": (I, [V, I, ctypes.POINTER(I)]),
        "dc1394_video_set_mode": (I, [V, I]), "dc1394_video_set_framerate": (I, [V, I]),
        "dc1394_video_set_operation_mode": (I, [V, I]), "dc1394_video_set_iso_speed": (I, [V, I]),
        "dc1394_format7_set_roi": (I, [V, I, I, I, I, I, I, I]),
        "dc1394_feature_set_mode": (I, [V, I, I]),
        "dc1394_feature_set_absolute_control": (I, [V, I, I]),
        "dc1394_feature_set_absolute_value": (I, [V, I, ctypes.c_float]),
        "dc1394_feature_get_absolute_value": (I, [V, I, ctypes.POINTER(ctypes.c_float)]),
        "dc1394_feature_set_value": (I, [V, I, U32]),
        "dc1394_external_trigger_set_mode": (I, [V, I]), "dc1394_external_trigger_set_source": (I, [V, I]),
        "dc1394_external_trigger_set_power": (I, [V, I]),
        "dc1394_capture_setup": (I, [V, U32, U32]), "dc1394_capture_stop": (I, [V]),
        "dc1394_capture_get_fileno": (I, [V]),
        "dc1394_capture_dequeue": (I, [V, I, ctypes.POINTER(ctypes.POINTER(VideoFrame))]),
        "dc1394_capture_enqueue": (I, [V, ctypes.POINTER(VideoFrame)]),
        "dc1394_video_set_transmission": (I, [V, I]),
    }
    for name, (res, args) in protos.items():
        fn = getattr(lib, name)
        fn.restype, fn.argtypes = res, args
    _lib = lib
    return lib


def list_cameras() -> list[int]:
    """GUIDs of the IIDC cameras on every FireWire bus (an empty list when there is no bus or camera)."""
    lib = load_library()
    ctx = lib.dc1394_new()
    if not ctx:
        raise DeviceAbsent("libdc1394 could not start (no FireWire support in this kernel?)")
    try:
        lst = ctypes.POINTER(CameraList)()
        err = lib.dc1394_camera_enumerate(ctx, ctypes.byref(lst))
        if err != 0:
            raise DeviceAbsent(f"IEEE-1394: cannot enumerate cameras ({lib.dc1394_error_get_string(err).decode()})")
        try:
            return [int(lst.contents.ids[i].guid) for i in range(lst.contents.num)]
        finally:
            lib.dc1394_camera_free_list(lst)
    finally:
        lib.dc1394_free(ctx)


def nearest_framerate(fps: float, offered: list[int]) -> int:
    """The offered IIDC framerate enum closest to ``fps`` (in log terms)."""
    return min(offered, key=lambda e: abs(np.log(FRAMERATES[e - FRAMERATE_FIRST] / fps)))


def convert_frame(data: np.ndarray, width: int, height: int, coding: int, stride: int,
                  little_endian: bool) -> np.ndarray:
    """Raw IIDC bytes as grey uint8/uint16 or BGR uint8 (always a copy)."""
    rows = data[: stride * height].reshape(height, stride)
    if coding in (COLOR_MONO8, COLOR_RAW8):
        return rows[:, :width].copy()
    if coding == COLOR_MONO16:
        # IIDC sends 16-bit pixels big-endian unless the camera says otherwise.
        dt = np.dtype("<u2" if little_endian else ">u2")
        return rows[:, : 2 * width].copy().view(dt).astype(np.uint16)
    if coding == COLOR_RGB8:
        return cv2.cvtColor(rows[:, : 3 * width].reshape(height, width, 3), cv2.COLOR_RGB2BGR)
    if coding == COLOR_YUV422:  # IIDC's 4:2:2 byte order is UYVY
        return cv2.cvtColor(rows[:, : 2 * width].reshape(height, width, 2), cv2.COLOR_YUV2BGR_UYVY)
    raise DeviceError(f"IEEE-1394: colour coding {coding} is not supported (use pixel_format Mono8/Mono16/"
                      "RGB8/YUV422/Raw8)")


class DC1394Source(Source):
    """One IIDC camera on a FireWire bus."""

    live = True

    def __init__(self, spec: SourceSpec) -> None:
        super().__init__(spec.uri, spec.settings)
        self.spec = spec
        self._lib: Any = None
        self._ctx: Any = None
        self._cam: Any = None
        self._capturing = False
        self._seq = 0
        self._dropped = 0
        self.guid = 0
        self.exposure_us: float | None = None

    @property
    def dropped(self) -> int:
        """Frames the ring buffer overran (reported by libdc1394's frames_behind)."""
        return self._dropped

    def describe(self) -> dict:
        """URI, GUID and settings."""
        return {"uri": self.uri, "driver": "dc1394", "guid": f"{self.guid:016x}", "settings": self.settings.as_dict()}

    def _check(self, err: int, what: str) -> None:
        if err != 0:
            msg = self._lib.dc1394_error_get_string(err).decode()
            raise DeviceError(f"{self.uri}: {what} failed ({msg})")

    def _open(self) -> None:
        """Find the camera on the bus, apply the settings and start the isochronous transfer."""
        if self._cam is not None:
            return
        self._lib = lib = load_library()
        guids = list_cameras()
        want = int(self.spec.target, 16) if self.spec.target else None
        if want is None and not guids:
            raise DeviceAbsent(f"{self.uri}: no IEEE-1394 camera found (is the FireWire card present, the camera "
                              "plugged in and powered, and /dev/fw* readable?)")
        if want is not None and want not in guids:
            found = ", ".join(f"{g:016x}" for g in guids) or "none"
            raise DeviceAbsent(f"{self.uri}: no IEEE-1394 camera with GUID {want:016x} (found: {found})")
        self.guid = want if want is not None else guids[0]
        self._ctx = lib.dc1394_new()
        self._cam = lib.dc1394_camera_new(self._ctx, ctypes.c_uint64(self.guid))
        if not self._cam:
            self.close()
            raise DeviceAbsent(f"{self.uri}: cannot open camera {self.guid:016x} (in use by another program?)")
        try:
            self._configure()
            self._check(lib.dc1394_capture_setup(self._cam, self.settings.buffers, CAPTURE_FLAGS_DEFAULT),
                        "capture setup (ISO bandwidth/channel)")
            self._capturing = True
            self._check(lib.dc1394_video_set_transmission(self._cam, SWITCH_ON), "starting transmission")
        except BaseException:
            self.close()
            raise

    def _configure(self) -> None:
        lib, cam, s = self._lib, self._cam, self.settings
        if s.iso_speed:
            if s.iso_speed > 400:
                self._check(lib.dc1394_video_set_operation_mode(cam, OPERATION_MODE_1394B), "1394B mode")
            self._check(lib.dc1394_video_set_iso_speed(cam, ISO_SPEEDS[s.iso_speed]), "iso_speed")
        modes = VideoModes()
        self._check(lib.dc1394_video_get_supported_modes(cam, ctypes.byref(modes)), "reading video modes")
        coding = CODINGS[s.pixel_format] if s.pixel_format else None
        chosen = None
        for m in modes.modes[: modes.num]:
            if m >= VIDEO_MODE_FORMAT7_0:
                continue
            w, h, c = ctypes.c_uint32(), ctypes.c_uint32(), ctypes.c_int()
            if lib.dc1394_get_image_size_from_video_mode(cam, m, ctypes.byref(w), ctypes.byref(h)) != 0:
                continue
            lib.dc1394_get_color_coding_from_video_mode(cam, m, ctypes.byref(c))
            if ((s.width is None or w.value == s.width) and (s.height is None or h.value == s.height)
                    and (coding is None or c.value == coding)):
                chosen = m
        if chosen is not None and (s.width or s.height or coding):
            self._check(lib.dc1394_video_set_mode(cam, chosen), "video mode")
            if s.fps:
                rates = Framerates()
                self._check(lib.dc1394_video_get_supported_framerates(cam, chosen, ctypes.byref(rates)), "framerates")
                offered = list(rates.framerates[: rates.num])
                if offered:
                    self._check(lib.dc1394_video_set_framerate(cam, nearest_framerate(s.fps, offered)), "fps")
        elif s.width or s.height or coding:
            if VIDEO_MODE_FORMAT7_0 not in list(modes.modes[: modes.num]):
                raise DeviceError(f"{self.uri}: the camera has no mode of {s.width}x{s.height} {s.pixel_format} "
                                  "and no Format_7 to make one")
            self._check(lib.dc1394_video_set_mode(cam, VIDEO_MODE_FORMAT7_0), "Format_7 mode")
            self._check(lib.dc1394_format7_set_roi(cam, VIDEO_MODE_FORMAT7_0, coding or COLOR_MONO8, -2, 0, 0,
                                                   s.width or -2, s.height or -2), "width/height (Format_7 ROI)")
            if s.fps:
                self._set_absolute(FEATURE_FRAME_RATE, s.fps, "fps")
        if s.exposure_us is not None:
            self._set_absolute(FEATURE_SHUTTER, s.exposure_us * 1e-6, "exposure_us")
            v = ctypes.c_float()
            if lib.dc1394_feature_get_absolute_value(cam, FEATURE_SHUTTER, ctypes.byref(v)) == 0:
                self.exposure_us = float(v.value) * 1e6
        if s.gain is not None:
            self._check(lib.dc1394_feature_set_mode(cam, FEATURE_GAIN, FEATURE_MODE_MANUAL), "gain mode")
            self._check(lib.dc1394_feature_set_value(cam, FEATURE_GAIN, int(s.gain)), "gain")
        if s.trigger == "hardware":
            self._check(lib.dc1394_external_trigger_set_mode(cam, TRIGGER_MODE_0), "trigger mode")
            self._check(lib.dc1394_external_trigger_set_source(cam, TRIGGER_SOURCE_0), "trigger source")
            self._check(lib.dc1394_external_trigger_set_power(cam, SWITCH_ON), "trigger")

    def _set_absolute(self, feature: int, value: float, what: str) -> None:
        lib, cam = self._lib, self._cam
        self._check(lib.dc1394_feature_set_mode(cam, feature, FEATURE_MODE_MANUAL), f"{what} manual mode")
        self._check(lib.dc1394_feature_set_absolute_control(cam, feature, SWITCH_ON), f"{what} absolute control")
        self._check(lib.dc1394_feature_set_absolute_value(cam, feature, ctypes.c_float(value)), what)

    def _read(self, timeout_s: float | None) -> Frame:
        """The next frame; DeviceTimeout when none arrives within the timeout (camera unplugged or stalled)."""
        lib = self._lib
        timeout = self.settings.timeout_s if timeout_s is None else timeout_s
        fd = lib.dc1394_capture_get_fileno(self._cam)
        ready, _, _ = select.select([fd], [], [], timeout)
        if not ready:
            raise DeviceTimeout(f"{self.uri}: no frame within {timeout:g} s (camera unplugged, or waiting for a "
                              "trigger?)")
        frame_p = ctypes.POINTER(VideoFrame)()
        self._check(lib.dc1394_capture_dequeue(self._cam, CAPTURE_POLICY_POLL, ctypes.byref(frame_p)),
                    "capturing a frame")
        if not frame_p:
            raise DeviceError(f"{self.uri}: the bus signalled a frame but none could be dequeued")
        recv = time.monotonic_ns()
        f = frame_p.contents
        try:
            n = int(f.image_bytes) or int(f.stride) * int(f.size[1])
            data = np.ctypeslib.as_array(f.image, shape=(n,))
            image = convert_frame(data, int(f.size[0]), int(f.size[1]), int(f.color_coding), int(f.stride),
                                  bool(f.little_endian))
            stamp = int(f.timestamp) * 1000 - (time.time_ns() - time.monotonic_ns())
            self._dropped += int(f.frames_behind)
        finally:
            lib.dc1394_capture_enqueue(self._cam, frame_p)
        self._seq += 1
        return Frame(image, stamp, recv, self._seq, self.spec.camera_id, self.exposure_us, None)

    def _close(self) -> None:
        """Stop transmission and capture, free the camera and the context (safe after errors)."""
        lib = self._lib
        if lib is None:
            return
        if self._cam:
            if self._capturing:
                lib.dc1394_video_set_transmission(self._cam, SWITCH_OFF)
                lib.dc1394_capture_stop(self._cam)
            lib.dc1394_camera_free(self._cam)
        if self._ctx:
            lib.dc1394_free(self._ctx)
        self._cam = self._ctx = None
        self._capturing = False
