"""GigE Vision and USB3 Vision cameras through Aravis (gi.repository Aravis 0.8).

``aravis:NAME`` opens the camera NAME: an IP address (opened directly, no network scan), an Aravis
device id as listed by ``edgecal sources``/``arv-tool-0.8``, or ``fake`` for libaravis's built-in Fake
camera. Settings: width/height (region at the sensor's top-left), fps, pixel_format (Mono8/10/12/16,
Bayer 8-bit, RGB8/BGR8: converted to uint8/uint16 grey or BGR), exposure_us, gain_db, trigger
(free, software, hardware = Line1, or the first input line offered), packet_size (GigE), buffers.

Timestamps: the device's timestamp (ns) is mapped onto CLOCK_MONOTONIC by the smallest observed
receive-minus-device offset (the frame that crossed the network fastest), relaxed by 20 ppm so that
clock drift is followed; the spacing of ``stamp_ns`` is therefore the camera's own.
"""

from __future__ import annotations

import threading
import time
import traceback
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from edgecal.config import setting
from edgecal.drivers.base import Frame, Source
from edgecal.drivers.spec import CameraSettings, SourceSpec, buffers_setting
from edgecal.errors import DeviceAbsent, DeviceError, DeviceLost, DeviceTimeout

INSTALL_HINT = ("install Debian's gir1.2-aravis-0.8 and PyGObject (pip install 'edgecal[aravis]', which needs "
                "libgirepository1.0-dev, libcairo2-dev and pkg-config to build)")

# GenICam pixel format -> (numpy dtype, OpenCV conversion to grey/BGR or None, channels in the buffer)
_FORMATS: dict[str, tuple[type, int | None, int]] = {
    "Mono8": (np.uint8, None, 1),
    "Mono10": (np.uint16, None, 1),
    "Mono12": (np.uint16, None, 1),
    "Mono16": (np.uint16, None, 1),
    "BayerRG8": (np.uint8, cv2.COLOR_BayerRGGB2BGR, 1),
    "BayerGR8": (np.uint8, cv2.COLOR_BayerGRBG2BGR, 1),
    "BayerGB8": (np.uint8, cv2.COLOR_BayerGBRG2BGR, 1),
    "BayerBG8": (np.uint8, cv2.COLOR_BayerBGGR2BGR, 1),
    "RGB8": (np.uint8, cv2.COLOR_RGB2BGR, 3),
    "BGR8": (np.uint8, None, 3),
}


@dataclass(frozen=True)
class AravisSettings(CameraSettings):
    """Settings of a GigE Vision / USB3 Vision camera."""

    pixel_format: str | None = setting(None, doc="GenICam pixel format", choices=tuple(_FORMATS))
    gain_db: float | None = setting(None, doc="analogue gain (dB)", minimum=0, maximum=100)
    trigger: str = setting("free", doc="free running, software (trigger()) or hardware (Line1)",
                           choices=("free", "software", "hardware"))
    packet_size: int | None = setting(None, doc="GigE stream packet size (bytes)", minimum=576, maximum=16384)
    buffers: int = buffers_setting()

_DRIFT_PPM = 20e-6

# USB3 Vision ABRM register 0x0000 (GenCP version): readable on every U3V device, used to ask whether it is still there.
_U3V_PROBE_REGISTER = 0x0000


def load_aravis() -> Any:
    """The gi.repository Aravis module; DeviceError saying what to install when it is missing."""
    try:
        import gi
        gi.require_version("Aravis", "0.8")
        from gi.repository import Aravis
    except (ImportError, ValueError) as exc:
        raise DeviceAbsent(f"the Aravis driver is unavailable ({exc}): {INSTALL_HINT}") from None
    return Aravis


def convert_buffer(data: bytes, width: int, height: int, pixel_format: str) -> np.ndarray:
    """A GenICam buffer's bytes as a grey (uint8/uint16) or BGR uint8 image (always a copy)."""
    dtype, code, channels = _FORMATS[pixel_format]
    arr: np.ndarray = np.frombuffer(data, dtype=dtype)
    n = width * height * channels
    if arr.size < n:
        raise DeviceError(f"buffer of {arr.size} pixels is too small for {width}x{height} {pixel_format}")
    shape = (height, width, channels) if channels > 1 else (height, width)
    img = arr[:n].reshape(shape)
    return cv2.cvtColor(img, code) if code is not None else img.copy()


class ClockMapper:
    """Maps a device clock onto CLOCK_MONOTONIC by the smallest (receive - device) offset.

    The smallest offset seen belongs to the frame that crossed the link fastest; it is an upper bound
    on the true clock offset. During the first ``warmup`` frames the offset follows every new minimum;
    after that it moves by at most ``max_slew_ns`` per frame (towards a new minimum, or upwards by the
    allowed drift), so one lucky packet or a step cannot put a jump into the stamps' spacing.
    """

    def __init__(self, warmup: int = 30, max_slew_ns: int = 20_000) -> None:
        self.offset_ns: int | None = None
        self.last_device_ns = 0
        self.count = 0
        self.warmup = warmup
        self.max_slew_ns = max_slew_ns

    def to_monotonic(self, device_ns: int, recv_ns: int) -> int:
        """The monotonic time at which the device stamped ``device_ns``.

        After the warm-up a stamp can lie up to the still-unslewed part of a new minimum after
        ``recv_ns``; smooth spacing matters more to the pose filter than that sub-millisecond bound.
        """
        sample = recv_ns - device_ns
        if self.offset_ns is None:
            self.offset_ns = sample
        else:
            relaxed = self.offset_ns + int(_DRIFT_PPM * max(0, device_ns - self.last_device_ns))
            target = min(relaxed, sample)
            if self.count < self.warmup:
                self.offset_ns = target
            else:
                self.offset_ns = max(target, self.offset_ns - self.max_slew_ns)
        self.count += 1
        self.last_device_ns = device_ns
        return device_ns + self.offset_ns


class AravisSource(Source):
    """One GigE Vision / USB3 Vision camera streaming through Aravis."""

    live = True

    def __init__(self, spec: SourceSpec) -> None:
        super().__init__(spec.uri, spec.settings)
        self.spec = spec
        self._camera: Any = None
        self._device: Any = None   # the camera's ArvDevice, polled for a lost camera (see _control_lost)
        self._stream: Any = None
        self._lost = threading.Event()
        self._failed = False
        self.release_thread: threading.Thread | None = None   # set when close() releases in the background
        self._clock = ClockMapper()
        self._dropped = 0
        self._seq = 0
        self._pixel_format = "Mono8"
        self._width = self._height = 0
        self.exposure_us: float | None = None
        self.gain_db: float | None = None
        self.last_device_ns = 0   # the raw device timestamp of the last frame (before mapping)
        self.info: dict[str, Any] = {}

    @property
    def dropped(self) -> int:
        """Buffers that arrived incomplete or were lost, as counted here and by the device's frame ids."""
        return self._dropped

    def describe(self) -> dict:
        """URI, device identity and the settings in force."""
        return {"uri": self.uri, "driver": "aravis", "device": self.info, "pixel_format": self._pixel_format,
                "width": self._width, "height": self._height, "exposure_us": self.exposure_us,
                "gain_db": self.gain_db, "settings": self.settings.as_dict()}

    def _name(self) -> str:
        name = self.spec.target
        return "Fake_1" if name.lower() == "fake" else name

    def _open(self) -> None:
        """Connect, apply the settings, allocate buffers and start acquisition."""
        if self._camera is not None:
            return
        Aravis = load_aravis()
        from gi.repository import GLib

        name = self._name()
        if not name:
            raise DeviceAbsent("aravis: needs a camera name or IP address (aravis:192.168.1.20, aravis:fake); "
                              "`edgecal sources` lists them")
        if name.startswith("Fake_"):
            Aravis.enable_interface("Fake")
        try:
            self._camera = Aravis.Camera.new(name)
        except GLib.Error as exc:
            raise DeviceAbsent(f"{self.uri}: cannot open the camera ({exc.message}); check the address/name "
                              "with `edgecal sources`, the cable and the camera's power") from None
        try:
            self._configure(Aravis, GLib)
            self._start(Aravis, GLib)
        except BaseException as exc:
            # The traceback's finished frames (_configure, _start) hold the camera in their locals (``cam``):
            # cleared first, so close() releases the last reference instead of whoever collects the exception.
            traceback.clear_frames(exc.__traceback__)
            self.close()
            raise

    def _configure(self, Aravis: Any, GLib: Any) -> None:
        cam, s = self._camera, self.settings
        self.info = {"vendor": cam.get_vendor_name(), "model": cam.get_model_name(),
                     "device_id": cam.get_device_id()}
        step = "pixel_format"
        try:
            if s.pixel_format:
                if s.pixel_format not in cam.dup_available_pixel_formats_as_strings():
                    raise DeviceError(f"{self.uri}: pixel_format {s.pixel_format} is not offered by the camera "
                                      f"(it offers {', '.join(cam.dup_available_pixel_formats_as_strings())})")
                cam.set_pixel_format_from_string(s.pixel_format)
            step = "width/height"
            if s.width or s.height:
                _, _, w0, h0 = cam.get_region()
                cam.set_region(0, 0, s.width or w0, s.height or h0)
            step = "trigger"
            if s.trigger == "free":
                cam.clear_triggers()
            elif s.trigger == "software":
                cam.set_trigger("Software")
            else:
                lines = [x for x in cam.dup_available_trigger_sources() if x.startswith("Line")]
                if not lines:
                    raise DeviceError(f"{self.uri}: trigger hardware: the camera has no trigger input line "
                                      f"(it offers {', '.join(cam.dup_available_trigger_sources()) or 'none'})")
                # Line1 is the opto-isolated input on most GigE cameras; otherwise the first line offered.
                cam.set_trigger("Line1" if "Line1" in lines else lines[0])
            step = "fps"
            if s.fps and s.trigger == "free":
                cam.set_frame_rate(s.fps)
            step = "exposure_us"
            if s.exposure_us is not None:
                if cam.is_exposure_auto_available():
                    cam.set_exposure_time_auto(Aravis.Auto.OFF)
                cam.set_exposure_time(s.exposure_us)
            step = "gain_db"
            if s.gain_db is not None:
                if cam.is_gain_auto_available():
                    cam.set_gain_auto(Aravis.Auto.OFF)
                cam.set_gain(s.gain_db)
            step = "packet_size"
            if s.packet_size and cam.is_gv_device():
                cam.gv_set_packet_size(s.packet_size)
        except GLib.Error as exc:
            raise DeviceError(f"{self.uri}: the camera refused {step} ({exc.message})") from None
        self._pixel_format = cam.get_pixel_format_as_string()
        if self._pixel_format not in _FORMATS:
            raise DeviceError(f"{self.uri}: pixel format {self._pixel_format} is not supported "
                              f"(set pixel_format to one of {', '.join(_FORMATS)})")
        _, _, self._width, self._height = cam.get_region()
        self.info["packet_size"] = int(cam.gv_get_packet_size()) if cam.is_gv_device() else None
        self._read_controls()

    def _read_controls(self) -> None:
        cam = self._camera
        self.exposure_us = float(cam.get_exposure_time()) if cam.is_exposure_time_available() else None
        self.gain_db = float(cam.get_gain()) if cam.is_gain_available() else None

    def _start(self, Aravis: Any, GLib: Any) -> None:
        cam = self._camera
        try:
            cam.set_acquisition_mode(Aravis.AcquisitionMode.CONTINUOUS)
            self._stream = cam.create_stream(None, None)
            payload = cam.get_payload()
            for _ in range(self.settings.buffers):
                self._stream.push_buffer(Aravis.Buffer.new_allocate(payload))
            # A lost camera is polled from the reading thread (_control_lost), never signalled: a handler on
            # the device's "control-lost" signal runs on Aravis's heartbeat (GigE) or libusb event (USB3) thread,
            # and the emission holds a reference to the device until the handler returns; a Python handler
            # waits there for the GIL, and if close() drops the other references meanwhile, the device is
            # finalised on that thread, which then joins itself (GLib-ERROR "Resource deadlock avoided").
            # With no handler connected GLib skips the emission entirely.
            self._device = cam.get_device()
            cam.start_acquisition()
        except GLib.Error as exc:
            raise DeviceError(f"{self.uri}: cannot start streaming ({exc.message})") from None

    def _control_lost(self, probe: bool) -> bool:
        """Whether the device says the camera is gone (False when it cannot tell); never raises.

        GigE Vision: the heartbeat thread clears the device's controller flag when the camera stops
        answering or another host has taken it over (when it would emit "control-lost"); reading the flag
        costs nothing. USB3 Vision: a register read fails at once with NOT_CONNECTED after the camera was
        unplugged; it is a bus transaction, so only done when ``probe`` (no frame in the last slice).
        """
        device, camera = self._device, self._camera
        if device is None or camera is None:
            return False
        try:
            if camera.is_gv_device():
                return not device.is_controller()
            if probe and camera.is_uv_device():
                from gi.repository import Aravis, GLib
                try:
                    device.read_register(_U3V_PROBE_REGISTER)
                except GLib.Error as exc:
                    return exc.matches(Aravis.device_error_quark(), Aravis.DeviceError.NOT_CONNECTED)
        except Exception:  # asking must not turn into an error of its own
            pass
        return False

    def set_exposure_us(self, exposure_us: float) -> float:
        """Change the exposure while streaming; returns the value the camera applied."""
        return self._set_control("exposure_us", exposure_us)

    def set_gain_db(self, gain_db: float) -> float:
        """Change the gain while streaming; returns the value the camera applied."""
        return self._set_control("gain_db", gain_db)

    def _set_control(self, what: str, value: float) -> float:
        from gi.repository import GLib
        self.require_open(f"setting {what}")
        try:
            if what == "exposure_us":
                self._camera.set_exposure_time(float(value))
            else:
                self._camera.set_gain(float(value))
        except GLib.Error as exc:
            raise DeviceError(f"{self.uri}: the camera refused {what}={value} ({exc.message})") from None
        self._read_controls()
        now = self.exposure_us if what == "exposure_us" else self.gain_db or 0.0
        assert now is not None  # the camera took an exposure time, so it has the control
        return float(now)

    def trigger(self) -> None:
        """Fire a software trigger (``trigger: software``)."""
        self.require_open("trigger()")
        self._camera.software_trigger()

    def _read(self, timeout_s: float | None) -> Frame:
        """The next complete frame; DeviceTimeout after ``timeout_s`` without one, DeviceLost when it is gone."""
        from gi.repository import Aravis
        timeout = self.settings.timeout_s if timeout_s is None else timeout_s
        deadline = time.monotonic() + timeout
        if self.settings.trigger == "software":
            self._camera.software_trigger()
        idle = False   # the last slice brought no buffer
        while True:
            if self._lost.is_set() or self._control_lost(probe=idle):
                self._lost.set()
                self._failed = True
                raise DeviceLost(f"{self.uri}: lost contact with the camera (unplugged or powered off?)")
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                self._failed = True
                raise DeviceTimeout(f"{self.uri}: no frame within {timeout:g} s (camera stopped sending, "
                                  "unplugged, or waiting for a trigger?)")
            # Wait in slices so that a lost camera is reported promptly.
            buf = self._stream.timeout_pop_buffer(int(min(remaining, 0.1) * 1e6))
            idle = buf is None
            if idle:
                continue
            recv = time.monotonic_ns()
            try:
                if buf.get_status() != Aravis.BufferStatus.SUCCESS:
                    self._dropped += 1
                    continue
                image = convert_buffer(buf.get_data(), buf.get_image_width(), buf.get_image_height(),
                                       self._pixel_format)
                device_ns = int(buf.get_timestamp())
                if device_ns == 0:  # no device timestamp: the host's arrival time (realtime) instead
                    device_ns = int(buf.get_system_timestamp()) - (time.time_ns() - time.monotonic_ns())
                stamp = self._clock.to_monotonic(device_ns, recv)
                self.last_device_ns = device_ns
                frame_id = int(buf.get_frame_id())
            finally:
                self._stream.push_buffer(buf)
            if self._seq and frame_id > self._seq + 1:
                self._dropped += frame_id - self._seq - 1
            self._seq = frame_id
            return Frame(image, stamp, recv, frame_id, self.spec.camera_id, self.exposure_us, self.gain_db)

    def _close(self) -> None:
        """Stop acquisition and drop every reference to the device, also after an error.

        A camera that has died no longer answers, and libaravis's own teardown (stop acquisition,
        release control) then waits out its GigE Vision retries, about 10 s. The teardown runs in a
        thread: close() waits for it up to a second (a healthy camera is released by then, so it can
        be reopened at once), not at all after a known failure, and leaves the rest in the background
        (``release_thread``).

        No Python code runs on Aravis's own threads (no signal handlers, no stream callback), so the
        last references are always dropped on a thread of ours: the releasing thread, which joins the
        stream's receive thread and the device's heartbeat/event thread.
        """
        if self._camera is None:
            return
        failed = self._failed or self._lost.is_set() or self._control_lost(probe=True)
        # The references live only in this list, which the releasing thread empties (stream first).
        held = [self._camera, self._device, self._stream]
        self._camera = self._device = self._stream = None
        self.release_thread = threading.Thread(target=_stop_and_release, args=(held, not failed),
                                               name=f"release {self.uri}", daemon=True)
        self.release_thread.start()
        if not failed:
            self.release_thread.join(1.0)


def _stop_and_release(objects: list[Any], stop: bool) -> None:
    """Stop acquisition (if asked) and drop the last references to ``[camera, device, stream]``.

    In this order: the stream (its finalizer joins the receive thread and releases the stream channel),
    then the device and the camera (the device's finalizer joins its heartbeat/event thread and
    releases the control privilege). Their finalizers talk to the device.
    """
    if stop:
        try:
            objects[0].stop_acquisition()
        except Exception:  # the camera may have gone in the meantime; releasing is what matters
            pass
    while objects:
        objects.pop()
