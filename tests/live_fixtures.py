"""Shared by the live-loop and daemon tests: a rendered robot sequence, its rig.yaml and a config to run it, the
loop run against a subscriber (edgecal.publish.subscriber), the notify socket, the daemon process, and inputs a
reload must survive."""

from __future__ import annotations

import copy
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import yaml
from scipy.spatial.transform import Rotation

from edgecal.publish.subscriber import MessageCollector
from edgecal.stream import LiveLoop, load_live_config
from edgecal.synth import scenes, writer

# A YAML "billion laughs" of 378 bytes: nine levels of nine aliases in one value, whose repr is 3 GB.
ALIAS_BOMB = "[&a [lol, lol, lol, lol, lol, lol, lol, lol, lol], " + ", ".join(
    f"&{c} [{', '.join(['*' + p] * 9)}]" for p, c in zip("abcdefgh", "bcdefghi")) + "]"


def wait_until(condition, timeout_s: float) -> bool:
    """Poll ``condition()`` every 20 ms until it is true (True) or ``timeout_s`` passes (False)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.02)
    return False


def free_endpoint() -> str:
    """A tcp endpoint on a free localhost port."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp://127.0.0.1:{s.getsockname()[1]}"


def write_rig_yaml(truth_rig: dict, path: Path) -> Path:
    """rig.yaml (cv2.FileStorage, T in metres) holding the renderer's true cameras."""
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("image_size", np.array(truth_rig["left"]["image_size"], dtype=np.int32).reshape(1, 2))
    for side in ("left", "right"):
        fs.write(f"distortion_model_{side}", str(truth_rig[side].get("lens", "radtan")))
        fs.write(f"camera_matrix_{side}", np.array(truth_rig[side]["K"], dtype=np.float64))
        fs.write(f"dist_coeffs_{side}", np.array(truth_rig[side]["dist"], dtype=np.float64).reshape(1, -1))
    fs.write("R", np.array(truth_rig["R_right_left"], dtype=np.float64))
    fs.write("T", np.array(truth_rig["T_right_left_mm"], dtype=np.float64).reshape(3, 1) / 1000.0)
    fs.release()
    return path


def render_robot(folder: Path, n_frames: int, seed: int = 3, lens: str = "radtan") -> dict:
    """Render ``n_frames`` of the robot sequence into ``folder`` (left/, right/, truth.json); return the truth.

    ``lens``: the rig's lens model (scenes.robot_rig)."""
    rig = scenes.robot_rig(seed, (1280, 800), lens=lens)
    frames = scenes.robot_sequence(seed, n_frames, size=(1280, 800), photometric="clean", lens=lens)
    writer.write_robot_sequence(folder, frames, rig, scenes.robot_target(), 30.0)
    truth = json.loads((folder / "truth.json").read_text())
    write_rig_yaml(truth["rig"], folder / "rig.yaml")
    return truth


def write_config(path: Path, sequence: Path, endpoint: str, *, source_extra: dict | None = None,
                 loop: dict | None = None, pose: dict | None = None) -> Path:
    """A live config replaying ``sequence`` and publishing on ``endpoint``."""
    doc = {
        "source": {"driver": "replay", "path": str(sequence), **(source_extra or {})},
        "rig": str(sequence / "rig.yaml"),
        "target": "targets/robot-3boards.yaml",
        "publish": {"endpoint": endpoint},
        "loop": {"status_period_s": 0.25, **(loop or {})},
    }
    if pose:
        doc["pose"] = pose
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def run_in_thread(loop: LiveLoop) -> tuple[threading.Thread, list]:
    """Run ``loop`` in a thread; the list receives its exit code."""
    result: list = []
    th = threading.Thread(target=lambda: result.append(loop.run()))
    th.start()
    return th, result


def run_loop_until(config: Path, endpoint: str, done: Callable[[MessageCollector], bool]) -> MessageCollector:
    """Run the LiveLoop of ``config`` in a thread, a subscriber on ``endpoint``, until ``done(subscriber)``
    (AssertionError after 20 s), then stop it: it must end with 0. The closed subscriber holds the messages."""
    sub = MessageCollector(endpoint)
    loop = LiveLoop(load_live_config(config))
    th, result = run_in_thread(loop)
    try:
        assert sub.wait_for(lambda: done(sub)), f"got {len(sub.of('pose'))} poses, {len(sub.of('status'))} status"
    finally:
        loop.request_stop()
        th.join(10)
        sub.close()
    assert not th.is_alive() and result == [0]
    return sub


def pose_errors(msg: dict, truth: dict) -> tuple[float, float]:
    """A pose message's position error (mm) and rotation error (deg) against the rendered truth of its frame."""
    frame = truth["frames"][msg["seq"] % len(truth["frames"])]
    err_mm = 1000 * np.linalg.norm(np.array(msg["pose"]["position_m"]) - frame["t_rig_robot_m"])
    q_err = Rotation.from_quat(msg["pose"]["orientation_xyzw"]) * Rotation.from_matrix(frame["R_rig_robot"]).inv()
    return float(err_mm), float(np.degrees(q_err.magnitude()))


class NotifySocket:
    """The receiving end of $NOTIFY_SOCKET, read continuously as systemd does."""

    def __init__(self, path: Path) -> None:
        self.path = str(path)
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(self.path)
        self.sock.settimeout(0.05)
        self.received: list[str] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                self.received.append(self.sock.recv(4096).decode())
            except TimeoutError:
                pass

    def wait_for(self, line: str, timeout_s: float) -> bool:
        return wait_until(lambda: any(line in m.splitlines() for m in list(self.received)), timeout_s)

    def close(self) -> None:
        self._stop.set()
        self._thread.join()
        self.sock.close()


def start_daemon(config: Path, notify: NotifySocket, log: Path) -> subprocess.Popen:
    """`edgecal run --config CONFIG` in a subprocess notifying ``notify``, its output in ``log``."""
    env = {**os.environ, "NOTIFY_SOCKET": notify.path, "NUMBA_NUM_THREADS": "1"}
    return subprocess.Popen([sys.executable, "-m", "edgecal", "run", "--config", str(config)], env=env,
                            stdout=log.open("wb"), stderr=subprocess.STDOUT)


def stop_daemon(proc: subprocess.Popen, timeout_s: float = 10.0) -> int | None:
    """SIGTERM the daemon and wait for it (killed if it does not end in ``timeout_s``); its exit code."""
    proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(timeout_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
    return proc.returncode


def end_daemon(proc: subprocess.Popen, *listeners: MessageCollector | NotifySocket) -> None:
    """A test's teardown: kill the daemon if the test left it running, then close its listeners."""
    if proc.poll() is None:
        proc.kill()
        proc.wait()
    for listener in listeners:
        listener.close()


def bad_rigs(truth_rig: dict, good_rig: Path, folder: Path) -> dict[str, Path]:
    """Files that are not a usable rig, by what is wrong with them."""
    rigs = {"text file": folder / "notes.txt", "no nodes": folder / "empty-rig.yaml",
            "bad node": folder / "bad-node-rig.yaml"}
    rigs["text file"].write_text("this is not a calibration\n")
    rigs["no nodes"].write_text("%YAML:1.0\n---\nfoo: 1\n")
    good = good_rig.read_text()
    rigs["bad node"].write_text(good.replace("camera_matrix_left: !!opencv-matrix",
                                             "camera_matrix_left: abc\nx: !!opencv-matrix"))
    for name, fx in (("nan focal", float("nan")), ("zero focal", 0.0)):
        rig = copy.deepcopy(truth_rig)
        rig["left"]["K"][0][0] = fx
        rigs[name] = write_rig_yaml(rig, folder / f"{name.replace(' ', '-')}-rig.yaml")
    for name, scale in (("baseline in mm", 1000.0), ("absurd baseline", 1e300)):
        rig = copy.deepcopy(truth_rig)
        rig["T_right_left_mm"] = [scale * float(v) for v in rig["T_right_left_mm"]]
        rigs[name] = write_rig_yaml(rig, folder / f"{name.replace(' ', '-')}-rig.yaml")
    return rigs
