"""Luxonis OAK stereo cameras through the DepthAI v3 API (``depthai:`` or ``depthai:MXID``).

A StereoSource: the left (CAM_B) and right (CAM_C) mono sensors, grouped on the device by a Sync node
so that each pair was exposed together; ``stamp_ns`` is the device capture time translated by DepthAI
to the host's steady clock (CLOCK_MONOTONIC). The device's factory calibration is read with
:func:`factory_calibration`, an initial guess for edgecal's own.

``depthai`` is imported only here, when such a source is opened. Device search is bounded by
DepthAI's own DEPTHAI_SEARCH_TIMEOUT (ms); DEPTHAI_PROTOCOL=usb keeps it off the network.
Settings: width, height (default 640x400), fps (default 30), exposure_us + iso (manual exposure),
max_skew_ms (the Sync node's threshold), timeout_s.
"""

from __future__ import annotations

import datetime
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from edgecal.camera import CameraModel, StereoRig
from edgecal.config import setting
from edgecal.drivers.base import Frame, StereoFrame, StereoSource
from edgecal.drivers.spec import CameraSettings, SourceSpec, skew_setting
from edgecal.errors import DeviceAbsent, DeviceError, DeviceLost, DeviceTimeout

DEFAULT_SIZE = (640, 400)
DEFAULT_FPS = 30.0


@dataclass(frozen=True)
class DepthaiSettings(CameraSettings):
    """Settings of an OAK stereo camera (width/height default to DEFAULT_SIZE)."""

    iso: int | None = setting(None, doc="sensor sensitivity (manual exposure needs exposure_us too)", minimum=100,
                              maximum=6400)
    max_skew_ms: float = skew_setting()


def load_depthai() -> Any:
    """The depthai module; DeviceError saying what to install when it is missing."""
    try:
        import depthai
    except ImportError as exc:
        raise DeviceAbsent(f"the DepthAI driver is unavailable ({exc}): pip install 'depthai>=3'") from None
    return depthai


def _ns(td: datetime.timedelta) -> int:
    """A timedelta as integer nanoseconds without going through a float."""
    return (td.days * 86_400 + td.seconds) * 1_000_000_000 + td.microseconds * 1000


def _lens(dai: Any, calib: Any, socket: Any, coeffs: np.ndarray) -> tuple[str, np.ndarray]:
    """edgecal's lens model and parameters of one DepthAI camera (its Perspective or Fisheye model)."""
    try:
        model = calib.getDistortionModel(socket)
    except RuntimeError:
        model = dai.CameraModel.Perspective
    if model == dai.CameraModel.Fisheye:
        return "fisheye", coeffs[:4]
    if model != dai.CameraModel.Perspective:
        raise DeviceError(f"the device's {socket} lens model {model} has no edgecal equivalent "
                          "(radtan, rational, fisheye)")
    # 14 coefficients k1 k2 p1 p2 k3 k4 k5 k6 s1..s4 tx ty: OpenCV's rational model when k4..k6 are used
    if np.any(coeffs[8:] != 0):
        raise DeviceError(f"the device's {socket} calibration uses thin-prism/tilt terms edgecal does not model")
    return ("rational", coeffs[:8]) if np.any(coeffs[5:8] != 0) else ("radtan", coeffs[:5])


def factory_calibration(calib: Any, width: int, height: int) -> StereoRig:
    """Convert a depthai.CalibrationHandler to edgecal's StereoRig at ``width`` x ``height``.

    DepthAI rescales the intrinsics to the requested size; its extrinsics are in centimetres and map
    points from the source camera (left, CAM_B) into the destination camera (right, CAM_C).
    """
    dai = load_depthai()
    left, right = dai.CameraBoardSocket.CAM_B, dai.CameraBoardSocket.CAM_C
    try:
        k_l = np.array(calib.getCameraIntrinsics(left, width, height), dtype=np.float64)
        k_r = np.array(calib.getCameraIntrinsics(right, width, height), dtype=np.float64)
        d_l = np.array(calib.getDistortionCoefficients(left), dtype=np.float64)
        d_r = np.array(calib.getDistortionCoefficients(right), dtype=np.float64)
        m = np.array(calib.getCameraExtrinsics(left, right), dtype=np.float64)
    except RuntimeError as exc:
        raise DeviceError(f"the device's factory calibration is incomplete ({exc})") from None
    cams = []
    for k, d, socket in ((k_l, d_l, left), (k_r, d_r, right)):
        lens, params = _lens(dai, calib, socket, d)
        cams.append(CameraModel.from_opencv(k, params, (width, height), lens))
    return StereoRig(cams[0], cams[1], m[:3, :3], m[:3, 3] / 100.0)


class OakStereoSource(StereoSource):
    """An OAK device's left/right mono pair, synchronised on the device."""

    live = True

    def __init__(self, spec: SourceSpec) -> None:
        super().__init__(spec.uri, spec.settings)
        self.spec = spec
        self._device: Any = None
        self._pipeline: Any = None
        self._queue: Any = None
        self.device_info: dict[str, Any] = {}
        self.size = (spec.settings.width or DEFAULT_SIZE[0], spec.settings.height or DEFAULT_SIZE[1])

    def describe(self) -> dict:
        """URI, device identity and settings."""
        return {"uri": self.uri, "driver": "depthai", "device": self.device_info, "width": self.size[0],
                "height": self.size[1], "settings": self.settings.as_dict()}

    def _open(self) -> None:
        """Find the device (bounded by DEPTHAI_SEARCH_TIMEOUT), build the pipeline and start it."""
        if self._device is not None:
            return
        dai = load_depthai()
        mxid = self.spec.target
        try:
            self._device = dai.Device(dai.DeviceInfo(mxid)) if mxid else dai.Device()
        except RuntimeError as exc:
            which = f"with id {mxid}" if mxid else "at all"
            raise DeviceAbsent(f"{self.uri}: no DepthAI device found {which} ({exc}); check the USB cable and "
                              "power, and that the udev rules let this user open it") from None
        try:
            self.device_info = {"mxid": self._device.getDeviceId(), "name": self._device.getDeviceName()}
            self._build(dai)
        except BaseException:
            self.close()
            raise

    def _build(self, dai: Any) -> None:
        s = self.settings
        fps = s.fps or DEFAULT_FPS
        p = dai.Pipeline(self._device)
        sync = p.create(dai.node.Sync)
        sync.setSyncThreshold(datetime.timedelta(microseconds=int(s.max_skew_ms * 1000)))
        for name, socket in (("left", dai.CameraBoardSocket.CAM_B), ("right", dai.CameraBoardSocket.CAM_C)):
            cam = p.create(dai.node.Camera).build(socket)
            if s.exposure_us is not None:
                cam.initialControl.setManualExposure(int(s.exposure_us), int(s.iso or 400))
            out = cam.requestOutput(self.size, type=dai.ImgFrame.Type.GRAY8, fps=fps)
            out.link(sync.inputs[name])
        self._queue = sync.out.createOutputQueue(maxSize=4, blocking=False)
        p.start()
        self._pipeline = p

    def calibration(self) -> StereoRig:
        """The device's factory stereo calibration at the streamed size."""
        self.require_open("calibration()")
        return factory_calibration(self._device.readCalibration(), *self.size)

    def _frame(self, img: Any, recv: int, side: str) -> Frame:
        exposure = img.getExposureTime()
        return Frame(img.getFrame(), _ns(img.getTimestamp()), recv, int(img.getSequenceNum()),
                     f"{self.spec.camera_id}#{side}", _ns(exposure) / 1000.0 if exposure else None, None)

    def _read(self, timeout_s: float | None) -> StereoFrame:
        """The next synchronised pair; DeviceTimeout after the timeout, DeviceLost when the device is lost."""
        timeout = self.settings.timeout_s if timeout_s is None else timeout_s
        try:
            group = self._queue.get(datetime.timedelta(seconds=timeout))
        except RuntimeError as exc:
            raise DeviceLost(f"{self.uri}: the device stopped ({exc}); unplugged or out of power?") from None
        if group is None:
            raise DeviceTimeout(f"{self.uri}: no synchronised pair within {timeout:g} s")
        recv = time.monotonic_ns()
        return StereoFrame(self._frame(group["left"], recv, "left"), self._frame(group["right"], recv, "right"))

    def _close(self) -> None:
        """Stop the pipeline and close the device (safe after errors)."""
        pipeline, device = self._pipeline, self._device
        self._pipeline = self._device = self._queue = None
        try:
            if pipeline is not None:
                pipeline.stop()
        finally:
            if device is not None:
                device.close()
