"""systemd/edgecal.service passes `systemd-analyze verify` without a single message.

`systemd-analyze verify` exits 0 even when it reports unknown keys or bad values, so any output at
all is a failure. The only change made before verifying is ExecStart's path to the installed
`edgecal` script (verify checks that the command exists).
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

UNIT = Path(__file__).resolve().parents[1] / "systemd" / "edgecal.service"
INSTALLED = "/opt/edgecal/.venv/bin/edgecal"


def verify(text: str, folder: Path) -> str:
    """Everything `systemd-analyze verify` prints about a unit with this text."""
    if shutil.which("systemd-analyze") is None:
        pytest.fail("systemd-analyze is missing: install the Debian package 'systemd' (make test does)")
    unit = folder / "edgecal.service"
    unit.write_text(text)
    res = subprocess.run(["systemd-analyze", "verify", str(unit)], capture_output=True, text=True, timeout=60)
    return (res.stdout + res.stderr).strip()


def local_unit_text() -> str:
    script = Path(sys.executable).parent / "edgecal"
    text = UNIT.read_text()
    assert INSTALLED in text
    return text.replace(INSTALLED, str(script))


def test_unit_verifies_cleanly(tmp_path: Path) -> None:
    assert verify(local_unit_text(), tmp_path) == ""


def test_verify_output_catches_mistakes(tmp_path: Path) -> None:
    """The check above can fail: a typo in a key is reported (while the exit code stays 0)."""
    broken = local_unit_text().replace("WatchdogSec=10", "WatchdogSecs=10")
    assert "WatchdogSecs" in verify(broken, tmp_path)


def test_unit_has_what_the_daemon_needs() -> None:
    text = UNIT.read_text()
    for line in ("Type=notify", "WatchdogSec=", "Restart=on-failure", "SupplementaryGroups=video",
                 "DeviceAllow=char-video4linux rw", "ExecReload=/bin/kill -HUP $MAINPID", "StandardOutput=journal"):
        assert line in text, line
    assert "PrivateDevices=yes" not in text        # it would hide the cameras
