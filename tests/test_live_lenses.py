"""The live loop on a rendered fisheye rig: its rig.yaml names the lens model, and the poses meet the same
accuracy targets as on the pinhole rig (1 mm, 0.1 deg on clean renders)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from live_fixtures import free_endpoint, render_robot, write_config
from scipy.spatial.transform import Rotation
from test_stream import Subscriber, run_in_thread

from edgecal.calibration.io import load_rig
from edgecal.stream import LiveLoop, load_live_config

N_FRAMES = 4


def test_live_loop_on_a_fisheye_rig_meets_the_pinhole_targets(tmp_path: Path) -> None:
    folder = tmp_path / "robot"
    truth = render_robot(folder, N_FRAMES, seed=3, lens="fisheye")
    rig = load_rig(folder / "rig.yaml").stereo
    assert rig.left.lens == "fisheye" and rig.right.lens == "fisheye"
    endpoint = free_endpoint()
    cfg = write_config(tmp_path / "live.yaml", folder, endpoint,
                       source_extra={"pace": "fast", "loop": True, "latest_only": False})
    sub = Subscriber(endpoint)
    loop = LiveLoop(load_live_config(cfg))
    th, result = run_in_thread(loop)
    try:
        # two passes: every frame searched once and tracked once
        assert sub.wait_for(lambda: len(sub.of("pose")) >= 2 * N_FRAMES), f"got {len(sub.of('pose'))} poses"
    finally:
        loop.request_stop()
        th.join(10)
        sub.close()
    assert not th.is_alive() and result == [0]
    for msg in sub.of("pose"):
        frame = truth["frames"][msg["seq"] % N_FRAMES]
        assert msg["valid"], msg["reason"]
        err_mm = 1000 * np.linalg.norm(np.array(msg["pose"]["position_m"]) - frame["t_rig_robot_m"])
        q_err = Rotation.from_quat(msg["pose"]["orientation_xyzw"]) * Rotation.from_matrix(frame["R_rig_robot"]).inv()
        assert err_mm < 1.0 and np.degrees(q_err.magnitude()) < 0.1, (err_mm, np.degrees(q_err.magnitude()))
