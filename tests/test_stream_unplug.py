"""A camera that unplugs mid-run (the Aravis GigE fake camera killed and restarted): the loop keeps
publishing status while it reopens the camera with back-off, then publishes poses again."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import yaml

from edgecal.drivers.base import Source, StereoSource
from edgecal.errors import DeviceLost
from edgecal.publish.subscriber import MessageCollector
from edgecal.stream import LiveLoop, load_live_config
from edgecal.stream.loop import default_source_factory

from .aravis_fake import FakeCamera
from .live_fixtures import free_endpoint, render_robot, write_config, write_rig_yaml


def small_rig(path: Path) -> Path:
    """A 320x240 stereo rig (the fake cameras' size); its numbers only have to be a valid calibration."""
    K = [[300.0, 0, 160.0], [0, 300.0, 120.0], [0, 0, 1]]
    cam = {"K": K, "dist": [0, 0, 0, 0, 0], "image_size": [320, 240]}
    return write_rig_yaml({"left": cam, "right": cam, "R_right_left": np.eye(3).tolist(),
                           "T_right_left_mm": [-75.0, 0, 0]}, path)


def test_camera_unplug_and_return(gv_lock: None, tmp_path: Path) -> None:
    endpoint = free_endpoint()
    cam = {"width": 320, "height": 240, "fps": 30, "timeout_s": 0.5}
    cfg = tmp_path / "live.yaml"
    cfg.write_text(yaml.safe_dump({
        "source": {"stereo": {"left": {"uri": "aravis:127.0.0.1", **cam}, "right": {"uri": "aravis:fake", **cam},
                              "max_skew_ms": 40, "timeout_s": 0.5}},
        "rig": str(small_rig(tmp_path / "rig.yaml")),
        "target": "targets/robot-3boards.yaml",
        "publish": {"endpoint": endpoint},
        "loop": {"status_period_s": 0.2, "camera_lost_after_s": 0.5, "reconnect_min_s": 0.2, "reconnect_max_s": 0.5},
    }))
    fake = FakeCamera()
    sub = MessageCollector(endpoint)
    loop = LiveLoop(load_live_config(cfg))
    th = threading.Thread(target=loop.run)
    th.start()
    try:
        assert sub.wait_for(lambda: len(sub.of("pose")) >= 3, 30)
        # No board in the fake camera's test pattern: a normal, invalid pose, not an error.
        assert all(not m["valid"] for m in sub.of("pose"))
        fake.kill()
        assert sub.wait_for(lambda: any(m["state"] == "camera-lost" for m in sub.of("status")), 10)
        n_status = len(sub.of("status"))
        n_pose = len(sub.of("pose"))
        assert sub.wait_for(lambda: len(sub.of("status")) >= n_status + 3, 5)   # status keeps coming
        fake = FakeCamera()
        assert sub.wait_for(lambda: sub.of("status")[-1]["state"] == "running"
                            and sub.of("status")[-1]["reconnects"] >= 1, 30)
        assert sub.wait_for(lambda: len(sub.of("pose")) >= n_pose + 3, 10)
    finally:
        loop.request_stop()
        th.join(10)
        fake.kill()
        sub.close()
    assert not th.is_alive()
    lost = [m for m in sub.of("status") if m["state"] == "camera-lost"]
    assert lost and all(m["message"] for m in lost)
    assert loop.stats.errors == 0


class _UnplugsOnce(StereoSource):
    """A replayed stereo camera that reports itself gone after its first few pairs, once: what a driver does
    when the device disappears (the DeviceLost of the Aravis/V4L2/DepthAI drivers), at the device boundary."""

    opened = 0

    def __init__(self, inner: Source, frames_before: int) -> None:
        super().__init__(inner.uri)
        self.inner = inner
        self.frames_before = frames_before

    def _open(self) -> None:
        type(self).opened += 1
        self.inner.open()

    def _read(self, timeout_s):
        if type(self).opened == 1 and self.frames_before == 0:
            raise DeviceLost(f"{self.uri}: lost contact with the camera (unplugged or powered off?)")
        self.frames_before -= 1
        return self.inner.read(timeout_s)

    def _close(self) -> None:
        self.inner.close()


def test_a_lost_camera_is_reopened_at_once_not_after_camera_lost_after_s(tmp_path: Path) -> None:
    # camera_lost_after_s is for a camera that is only silent (timeouts); a DeviceLost says it is gone:
    # the loop closes and reopens it on the back-off at once (before the split it waited the full minute).
    folder = tmp_path / "robot"
    folder.mkdir()
    render_robot(folder, 2)
    endpoint = free_endpoint()
    cfg = write_config(tmp_path / "live.yaml", folder, endpoint,
                       source_extra={"pace": "fast", "loop": True, "latest_only": False},
                       loop={"camera_lost_after_s": 60, "reconnect_min_s": 1.0, "status_period_s": 0.2})
    _UnplugsOnce.opened = 0
    sub = MessageCollector(endpoint)
    loop = LiveLoop(load_live_config(cfg), source_factory=lambda spec: _UnplugsOnce(default_source_factory(spec), 3))
    th = threading.Thread(target=loop.run)
    th.start()
    try:
        assert sub.wait_for(lambda: any(m["state"] == "camera-lost" for m in sub.of("status")), 30)
        lost = next(m for m in sub.of("status") if m["state"] == "camera-lost")
        assert "lost contact with the camera" in lost["message"]
        assert sub.wait_for(lambda: sub.of("status")[-1]["state"] == "running"
                            and sub.of("status")[-1]["reconnects"] >= 1, 10)
    finally:
        loop.request_stop()
        th.join(10)
        sub.close()
    assert not th.is_alive() and _UnplugsOnce.opened == 2 and loop.stats.errors == 0
