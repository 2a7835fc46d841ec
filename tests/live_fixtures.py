"""Shared by the live-loop tests: a rendered robot sequence, its rig.yaml and a config to run it."""

from __future__ import annotations

import json
import socket
import time
from pathlib import Path

import cv2
import numpy as np
import yaml

from edgecal.synth import scenes, writer


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
