"""The Aravis fake GigE Vision camera (arv-fake-gv-camera-0.8 on 127.0.0.1) for the tests that need a camera.

One fake camera can own the GigE Vision port at a time: the ``gv_lock`` fixture (conftest.py) holds a file
lock shared with bench/sources.py while a test's camera runs.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import time
from pathlib import Path

import pytest

from edgecal.errors import DeviceError

FAKE = "arv-fake-gv-camera-0.8"
LOCK = Path("/tmp/edgecal-arv-fake-gv.lock")


def require_aravis() -> None:
    problem = None
    if shutil.which(FAKE) is None:
        problem = f"{FAKE} is not installed (Debian package aravis-tools)"
    else:
        try:
            from edgecal.drivers.aravis import load_aravis
            load_aravis()
        except DeviceError as exc:
            problem = str(exc)
    if problem:
        if os.environ.get("CI"):
            pytest.fail(f"Aravis tests must run in CI: {problem}")
        pytest.skip(problem)


def _die_with_parent() -> None:
    """In the child: receive SIGKILL when the test process dies (no orphaned camera holding the port)."""
    import ctypes
    import signal
    ctypes.CDLL(None).prctl(1, int(signal.SIGKILL))  # PR_SET_PDEATHSIG


class FakeCamera:
    """A running arv-fake-gv-camera-0.8 process on 127.0.0.1."""

    def __init__(self) -> None:
        self.proc = subprocess.Popen([FAKE, "-i", "127.0.0.1", "-s", "EDGECAL"], stdout=subprocess.DEVNULL,
                                     stderr=subprocess.PIPE, preexec_fn=_die_with_parent)
        from edgecal.drivers.aravis import load_aravis
        Aravis = load_aravis()
        deadline = time.monotonic() + 5.0
        while True:
            if self.proc.poll() is not None:
                raise RuntimeError(f"{FAKE} exited: {self.proc.stderr.read().decode(errors='replace')}")
            try:
                Aravis.Camera.new("127.0.0.1")  # the GVCP port answers: the camera is up
                return
            except Exception:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.05)

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(5)
