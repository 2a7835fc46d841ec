"""`edgecal run` as a daemon, in a subprocess: sd_notify, SIGHUP reload, SIGTERM, bad config."""

from __future__ import annotations

import re
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from edgecal.publish.subscriber import MessageCollector

from .live_fixtures import (
    NotifySocket,
    end_daemon,
    free_endpoint,
    render_robot,
    start_daemon,
    wait_until,
    write_config,
)

N_FRAMES = 3


@pytest.fixture(scope="module")
def sequence(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("robot")
    render_robot(folder, N_FRAMES, seed=5)
    return folder


def test_notify_reload_and_sigterm(sequence: Path, tmp_path: Path) -> None:
    endpoint = free_endpoint()
    cfg = write_config(tmp_path / "live.yaml", sequence, endpoint, source_extra={"loop": True})
    good = yaml.safe_load(cfg.read_text())
    notify = NotifySocket(tmp_path / "notify.sock")
    try:
        _run_daemon(cfg, good, notify, endpoint, tmp_path)
    finally:
        notify.close()


def _run_daemon(cfg: Path, good: dict, notify: NotifySocket, endpoint: str, tmp_path: Path) -> None:
    sub = MessageCollector(endpoint)
    log = tmp_path / "run.log"
    proc = start_daemon(cfg, notify, log)
    try:
        assert notify.wait_for("READY=1", 90), log.read_text()
        assert notify.wait_for("WATCHDOG=1", 5)
        assert sub.wait_for(lambda: len(sub.of("pose")) >= 2, 20)
        assert all(m["valid"] for m in sub.of("pose")), sub.of("pose")[0]["reason"]

        # SIGHUP with a broken config: logged, reported on the status, the old config keeps running.
        cfg.write_text(yaml.safe_dump({**good, "pose": {"max_rms_px": "small"}}))
        proc.send_signal(signal.SIGHUP)
        assert sub.wait_for(lambda: any("reload failed" in (m.get("message") or "") for m in sub.of("status")), 10)
        n = len(sub.of("pose"))
        assert sub.wait_for(lambda: len(sub.of("pose")) >= n + 2, 10)
        assert proc.poll() is None
        assert all(m["valid"] for m in sub.of("pose")[n:])

        # SIGHUP with a good config that tightens a bound: takes effect, the camera is not reopened.
        cfg.write_text(yaml.safe_dump({**good, "pose": {"max_rms_px": 1e-6}}))
        proc.send_signal(signal.SIGHUP)
        assert sub.wait_for(lambda: any("max_rms_px" in m["reason"] for m in sub.of("pose")), 10), log.read_text()
        assert sub.wait_for(lambda: len(sub.of("status")) > 0 and sub.of("status")[-1]["message"] == "", 5)
        assert sub.of("status")[-1]["reconnects"] == 0 and sub.of("status")[-1]["reload_failures"] == 1

        # SIGTERM: a clean exit within a second, socket closed.
        t0 = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        code = proc.wait(10)
        elapsed = time.monotonic() - t0
    finally:
        end_daemon(proc, sub)
    text = log.read_text()
    assert code == 0, text
    assert elapsed < 1.0, f"SIGTERM took {elapsed:.2f} s"
    assert notify.wait_for("STOPPING=1", 1)
    assert "reload failed, keeping the running config" in text and "field 'pose.max_rms_px'" in text
    # A frame still in flight after the grace period (a loaded machine) is abandoned: also a clean stop.
    assert re.search(r"stopped (\(aborted in frame\) )?after", text) and "Traceback" not in text
    # The port is free again: a new publisher can bind it.
    from edgecal.publish import PosePublisher
    PosePublisher(endpoint).close()


def test_bad_config_fails_before_opening_any_device(sequence: Path, tmp_path: Path) -> None:
    """A wrong field: one line naming it, exit 2; the absent camera is never touched (that would be exit 3)."""
    cfg = write_config(tmp_path / "live.yaml", sequence, free_endpoint())
    doc = yaml.safe_load(cfg.read_text())
    doc["source"] = {"stereo": {"left": {"uri": "v4l2:/dev/video-edgecal-absent"},
                                "right": {"uri": "v4l2:/dev/video-edgecal-absent2"}}}
    doc["pose"] = {"min_corners": 2}
    cfg.write_text(yaml.safe_dump(doc))
    res = subprocess.run([sys.executable, "-m", "edgecal", "run", "--config", str(cfg)], capture_output=True,
                         text=True, timeout=60)
    assert res.returncode == 2
    assert res.stderr.strip().count("\n") == 0
    assert "field 'pose.min_corners' must be at least 3" in res.stderr

def test_missing_config_file(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    from edgecal.cli import main
    assert main(["run", "--config", str(tmp_path / "none.yaml")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "config file not found" in err[0]


def test_notify_never_blocks_on_a_full_socket(tmp_path: Path) -> None:
    from edgecal.stream.notify import SystemdNotifier
    server = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    server.bind(str(tmp_path / "n.sock"))            # bound, never read: its queue fills up
    notifier = SystemdNotifier(str(tmp_path / "n.sock"))
    t0 = time.monotonic()
    results = [notifier.watchdog() for _ in range(5000)]
    assert time.monotonic() - t0 < 5.0
    assert results[0] and not all(results)
    notifier.close()
    server.close()
    assert not SystemdNotifier("").enabled and SystemdNotifier("").ready() is False


def test_ready_while_the_camera_is_absent_at_boot(sequence: Path, tmp_path: Path) -> None:
    """Both cameras unplugged at start: READY=1 still comes once the loop runs (systemd would otherwise kill
    and restart the unit forever), the status says camera-lost, the watchdog is fed, SIGTERM ends it cleanly."""
    endpoint = free_endpoint()
    cfg = write_config(tmp_path / "live.yaml", sequence, endpoint,
                       loop={"camera_lost_after_s": 0.5, "reconnect_min_s": 0.2, "reconnect_max_s": 0.5})
    doc = yaml.safe_load(cfg.read_text())
    doc["source"] = {"stereo": {"left": {"uri": "v4l2:/dev/video-edgecal-absent0"},
                                "right": {"uri": "v4l2:/dev/video-edgecal-absent1"}}}
    cfg.write_text(yaml.safe_dump(doc))
    notify = NotifySocket(tmp_path / "notify.sock")
    sub = MessageCollector(endpoint)
    log = tmp_path / "run.log"
    proc = start_daemon(cfg, notify, log)
    try:
        assert notify.wait_for("READY=1", 90), log.read_text()
        ready = next(m for m in notify.received if "READY=1" in m.splitlines())
        assert "STATUS=camera-lost" in ready
        assert sub.wait_for(lambda: any(m["state"] == "camera-lost" for m in sub.of("status")), 10)
        assert "no such device" in sub.of("status")[-1]["message"]
        n = sum("WATCHDOG=1" in m for m in notify.received)
        assert wait_until(lambda: sum("WATCHDOG=1" in m for m in notify.received) > n + 1, 5)
        assert proc.poll() is None
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(10) == 0
    finally:
        end_daemon(proc, sub, notify)
    assert "Traceback" not in log.read_text()
