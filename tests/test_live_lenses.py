"""The live loop on a rendered fisheye rig: its rig.yaml names the lens model, and the poses meet the same
accuracy targets as on the pinhole rig (1 mm, 0.1 deg on clean renders)."""

from __future__ import annotations

from pathlib import Path

from edgecal.calibration.io import load_rig

from .live_fixtures import free_endpoint, pose_errors, render_robot, run_loop_until, write_config

N_FRAMES = 4


def test_live_loop_on_a_fisheye_rig_meets_the_pinhole_targets(tmp_path: Path) -> None:
    folder = tmp_path / "robot"
    truth = render_robot(folder, N_FRAMES, seed=3, lens="fisheye")
    rig = load_rig(folder / "rig.yaml").stereo
    assert rig.left.lens == "fisheye" and rig.right.lens == "fisheye"
    endpoint = free_endpoint()
    cfg = write_config(tmp_path / "live.yaml", folder, endpoint,
                       source_extra={"pace": "fast", "loop": True, "latest_only": False})
    # two passes: every frame searched once and tracked once
    sub = run_loop_until(cfg, endpoint, lambda s: len(s.of("pose")) >= 2 * N_FRAMES)
    for msg in sub.of("pose"):
        assert msg["valid"], msg["reason"]
        err_mm, err_deg = pose_errors(msg, truth)
        assert err_mm < 1.0 and err_deg < 0.1, (err_mm, err_deg)
