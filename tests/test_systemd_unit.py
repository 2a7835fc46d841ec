"""systemd/edgecal.service passes `systemd-analyze verify` without a single message.

`systemd-analyze verify` exits 0 even when it reports unknown keys or bad values, so any output at
all is a failure. The only change made before verifying is ExecStart's path to the installed
`edgecal` script (verify checks that the command exists).
"""

from __future__ import annotations

import errno
import os
import re
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


# The exposure `systemd-analyze security --offline=yes` gives the shipped unit (README, "Running as a service").
MAX_EXPOSURE = 2.0


def test_security_exposure_is_at_most_2(tmp_path: Path) -> None:
    if shutil.which("systemd-analyze") is None:
        pytest.fail("systemd-analyze is missing: install the Debian package 'systemd' (make test does)")
    unit = tmp_path / "edgecal.service"
    unit.write_text(local_unit_text())
    res = subprocess.run(["systemd-analyze", "security", "--offline=yes", str(unit)], capture_output=True, text=True,
                         timeout=60, check=False)
    if "--offline" in res.stderr and res.returncode != 0:
        pytest.skip(f"this systemd-analyze has no --offline ({res.stderr.strip()[:80]})")
    found = re.search(r"Overall exposure level for edgecal\.service: (\d+\.\d+)", res.stdout)
    assert found, res.stdout[-2000:] + res.stderr
    assert float(found.group(1)) <= MAX_EXPOSURE, res.stdout


def test_unit_settings_of_a_long_running_service() -> None:
    text = UNIT.read_text()
    for line in ("RestartPreventExitStatus=2", "LimitNOFILE=", "SystemCallFilter=@system-service",
                 "ProtectHome=yes", "ProtectProc=invisible", "ProcSubset=pid", "PrivateMounts=yes"):
        assert line in text, line


def system_service_syscalls() -> list[str]:
    """The system calls of systemd's @system-service group, its nested groups expanded."""
    res = subprocess.run(["systemd-analyze", "syscall-filter"], capture_output=True, text=True, timeout=60,
                         check=True)
    groups: dict[str, list[str]] = {}
    current: list[str] = []
    for line in res.stdout.splitlines():
        if line.startswith("@"):
            current = groups.setdefault(line.strip(), [])
        elif line.startswith("    ") and not line.strip().startswith("#") and line.strip():
            current.append(line.strip())

    def expand(name: str) -> set[str]:
        out: set[str] = set()
        for item in groups.get(name, []):
            out |= expand(item) if item.startswith("@") else {item}
        return out

    return sorted(expand("@system-service"))


def test_daemon_runs_under_the_system_call_allow_list(tmp_path: Path) -> None:
    """SystemCallFilter=@system-service with EPERM for the rest, applied with libseccomp as systemd does: the
    daemon warms up numba, replays, detects, publishes poses and notifies; SIGTERM ends it with exit 0."""
    seccomp = pytest.importorskip("pyseccomp")
    import signal

    from edgecal.publish.subscriber import MessageCollector

    from .live_fixtures import NotifySocket, end_daemon, free_endpoint, render_robot, write_config

    allowed = system_service_syscalls()
    assert "mprotect" in allowed and "ioctl" in allowed and len(allowed) > 300

    def apply_filter() -> None:
        f = seccomp.SyscallFilter(seccomp.ERRNO(errno.EPERM))
        for name in allowed:
            try:
                f.add_rule(seccomp.ALLOW, name)
            except Exception:  # noqa: BLE001 - a name this libseccomp does not know: systemd skips it too
                pass
        f.load()

    # The filter is in force: chroot (root may call it, it is outside @system-service) is refused.
    probe = subprocess.run([sys.executable, "-c", "import os; os.chroot('/')"], capture_output=True, text=True,
                           timeout=60, check=False, preexec_fn=apply_filter)
    assert probe.returncode != 0 and "Operation not permitted" in probe.stderr, probe.stderr

    folder = tmp_path / "robot"
    folder.mkdir()
    render_robot(folder, 3, seed=5)
    endpoint = free_endpoint()
    cfg = write_config(tmp_path / "live.yaml", folder, endpoint, source_extra={"loop": True, "preload": True})
    notify = NotifySocket(tmp_path / "notify.sock")
    sub = MessageCollector(endpoint)
    log = tmp_path / "run.log"
    env = {**os.environ, "NOTIFY_SOCKET": notify.path, "NUMBA_NUM_THREADS": "1",
           "NUMBA_CACHE_DIR": str(tmp_path / "numba-cache")}      # a cold cache: numba compiles under the filter
    proc = subprocess.Popen([sys.executable, "-m", "edgecal", "run", "--config", str(cfg)], env=env,
                            stdout=log.open("wb"), stderr=subprocess.STDOUT, preexec_fn=apply_filter)
    try:
        assert notify.wait_for("READY=1", 300), log.read_text()[-3000:]
        assert sub.wait_for(lambda: len(sub.of("pose")) >= 3, 30), log.read_text()[-3000:]
        assert all(m["valid"] for m in sub.of("pose")), sub.of("pose")[0]["reason"]
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(20) == 0, log.read_text()[-3000:]
    finally:
        end_daemon(proc, sub, notify)
    text = log.read_text()
    assert "Traceback" not in text and "Operation not permitted" not in text, text[-3000:]
