"""V4L2, IEEE-1394 and DepthAI up to the device boundary: no such camera can exist on a test machine.

Each test runs the real driver code (the OpenCV V4L2 backend, libdc1394 through ctypes, depthai) and
checks that an absent device is a clear DeviceAbsent (a DeviceError), quickly, and that close() is safe afterwards.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np
import pytest

from edgecal.drivers import open_source
from edgecal.errors import DeviceAbsent


def _expect_device_error(uri: str, pattern: str, limit_s: float = 3.0) -> None:
    src = open_source(uri)
    t0 = time.monotonic()
    with pytest.raises(DeviceAbsent, match=pattern):
        with src:
            pass
    assert time.monotonic() - t0 < limit_s
    src.close()  # safe to call again after the failed open


# --- V4L2 -----------------------------------------------------------------------------------------

def test_v4l2_absent_device(tmp_path: Path) -> None:
    missing = next(f"/dev/video{i}" for i in range(60, 100) if not os.path.exists(f"/dev/video{i}"))
    _expect_device_error(f"v4l2:{missing}", r"no such device .*edgecal sources")
    link = tmp_path / "by-id-camera"
    link.symlink_to(missing)                     # a udev by-id link whose camera is unplugged
    _expect_device_error(f"v4l2:{link}", "no such device")


def test_v4l2_rejects_what_is_not_a_capture_device(tmp_path: Path) -> None:
    # A character device that does not answer VIDIOC_QUERYCAP (the real ioctl is sent).
    _expect_device_error("v4l2:/dev/null", r"v4l2:/dev/null: not a V4L2 device \(it does not answer VIDIOC_QUERYCAP\)")
    f = tmp_path / "video0"
    f.write_bytes(b"")
    _expect_device_error(f"v4l2:{f}", "not a device node")


def test_v4l2_device_listing_and_capability_struct() -> None:
    from edgecal.drivers.v4l2 import _CAPABILITY, list_devices
    assert _CAPABILITY.size == 104          # sizeof(struct v4l2_capability)
    devices = list_devices()
    assert all(d["uri"].startswith("v4l2:/dev/video") and "usable" in d for d in devices)


# --- IEEE-1394 ------------------------------------------------------------------------------------

def test_dc1394_library_and_struct_layout() -> None:
    import ctypes

    from edgecal.drivers import dc1394
    dc1394.load_library()
    # Sizes/offsets of the C structs on 64-bit Linux (dc1394/video.h, camera.h, types.h of libdc1394 2.2).
    assert ctypes.sizeof(dc1394.VideoFrame) == 120
    assert (dc1394.VideoFrame.timestamp.offset, dc1394.VideoFrame.camera.offset) == (72, 88)
    assert ctypes.sizeof(dc1394.CameraId) == 16 and ctypes.sizeof(dc1394.VideoModes) == 132
    assert dc1394.list_cameras() == []   # the bus is enumerated for real: no camera here


def test_dc1394_absent_camera_errors() -> None:
    _expect_device_error("dc1394:", r"no IEEE-1394 camera found")
    _expect_device_error("dc1394:00b09d0100a1b2c3", r"no IEEE-1394 camera with GUID 00b09d0100a1b2c3 \(found: none\)")


def test_dc1394_frame_conversion() -> None:
    from edgecal.drivers import dc1394
    # Mono16 arrives big-endian with a padded stride; YUV422 as UYVY; RGB8 becomes BGR.
    vals = np.arange(6, dtype=">u2").reshape(2, 3)
    padded = np.zeros((2, 8), np.uint8)
    padded[:, :6] = vals.view(np.uint8).reshape(2, 6)
    out = dc1394.convert_frame(padded.ravel(), 3, 2, dc1394.COLOR_MONO16, 8, False)
    assert out.dtype == np.uint16 and out.tolist() == [[0, 1, 2], [3, 4, 5]]
    rgb = np.array([[[10, 20, 30], [40, 50, 60]]], np.uint8)
    bgr = dc1394.convert_frame(rgb.ravel(), 2, 1, dc1394.COLOR_RGB8, 6, False)
    assert bgr[0, 0].tolist() == [30, 20, 10]
    grey = np.full((2, 4), 128, np.uint8)   # U=128, Y=128, V=128, Y=128: mid grey
    yuv = dc1394.convert_frame(grey.ravel(), 2, 2, dc1394.COLOR_YUV422, 4, False)
    assert yuv.shape == (2, 2, 3) and abs(int(yuv[0, 0, 1]) - 128) <= 2
    assert dc1394.FRAMERATES[dc1394.nearest_framerate(25, [34, 35, 36]) - 32] == 30.0


# --- DepthAI --------------------------------------------------------------------------------------

@pytest.fixture
def depthai_env(monkeypatch: pytest.MonkeyPatch) -> None:
    # No telemetry, a short search, USB only (no network discovery) - set before depthai is imported.
    monkeypatch.setenv("DEPTHAI_TELEMETRY", "0")
    monkeypatch.setenv("DEPTHAI_SEARCH_TIMEOUT", "300")
    monkeypatch.setenv("DEPTHAI_PROTOCOL", "usb")
    monkeypatch.setenv("DEPTHAI_LEVEL", "off")


def test_depthai_absent_device(depthai_env: None) -> None:
    _expect_device_error("depthai:", r"depthai:: no DepthAI device found at all .*USB cable", limit_s=5.0)
    _expect_device_error("depthai:1844301011B5C01200", r"no DepthAI device found with id 1844301011B5C01200",
                         limit_s=5.0)


def test_depthai_factory_calibration_conversion(depthai_env: None) -> None:
    import depthai as dai

    from edgecal.drivers.oak import factory_calibration
    calib = dai.CalibrationHandler()
    k = [[800.0, 0.0, 640.0], [0.0, 800.0, 400.0], [0.0, 0.0, 1.0]]
    size = dai.Size2f(1280, 800)
    for socket in (dai.CameraBoardSocket.CAM_B, dai.CameraBoardSocket.CAM_C):
        calib.setCameraIntrinsics(socket, k, size)
        calib.setDistortionCoefficients(socket, [0.1, -0.2, 0.001, 0.002, 0.03] + [0.0] * 9)
    r = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
    calib.setCameraExtrinsics(dai.CameraBoardSocket.CAM_B, dai.CameraBoardSocket.CAM_C, r, [-7.5, 0.0, 0.0])
    rig = factory_calibration(calib, 640, 400)
    assert rig.image_size == (640, 400) and rig.left.lens == "radtan"
    assert rig.left.fx == pytest.approx(400.0) and rig.left.cx == pytest.approx(320, abs=1)
    assert rig.right.dist_coeffs.tolist() == pytest.approx([0.1, -0.2, 0.001, 0.002, 0.03])
    assert rig.t_right_left_m.tolist() == pytest.approx([-0.075, 0.0, 0.0])   # centimetres -> metres, left -> right
    assert np.allclose(rig.R_right_left, np.eye(3))
