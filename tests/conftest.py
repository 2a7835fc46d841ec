"""Fixtures shared by several test modules; plain helpers live in the package's helper modules
(live_fixtures, driver_frames, ros_logs, unprivileged, aravis_fake, pose_fixtures)."""

from __future__ import annotations

import fcntl
from collections.abc import Iterator

import pytest

from .aravis_fake import LOCK, FakeCamera, require_aravis


@pytest.fixture
def gv_lock() -> Iterator[None]:
    require_aravis()
    with open(LOCK, "w") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        yield


@pytest.fixture
def fake_camera(gv_lock: None) -> Iterator[FakeCamera]:
    cam = FakeCamera()
    try:
        yield cam
    finally:
        cam.kill()
