"""``edgecal demo --out out/demo``: the whole pipeline on data edgecal renders itself.

1. render the calibration box seen by the robot's stereo rig and detect its boards in both images;
2. calibrate the rig from that one pair (as ``edgecal calibrate`` does -> rig.yaml) and compare with the truth;
3. render a short sequence of the robot moving in front of the same rig (as ``edgecal render robot`` does);
4. run the live loop on its replay with a ZeroMQ subscriber attached, and compare every published
   pose with the ground truth.

Afterwards ``edgecal run --config configs/robot.yaml`` streams the same replay (looping) and
``edgecal listen`` prints it.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import yaml
from scipy.spatial.transform import Rotation

from edgecal.commands.argtypes import positive_int
from edgecal.errors import EdgecalError, InputError
from edgecal.fileio import check_outputs, make_folders, png_bytes, write_atomic

ENDPOINT = "tcp://127.0.0.1:5561"     # not the default 5560: a running `edgecal run` must not clash


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register ``edgecal demo``."""
    p = subparsers.add_parser("demo", help="render, detect, calibrate and stream pose from a replay (the README demo)",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default="out/demo", help="output folder (default out/demo)")
    p.add_argument("--frames", type=positive_int, default=30, help="frames of the robot sequence (default 30 = 1 s)")
    p.add_argument("--seed", type=int, default=1, help="random seed of the scenes")
    p.add_argument("--force", action="store_true", help="replace the results of an earlier demo in --out")
    return p


def render_box_pair(seed: int, out: Path) -> dict:
    """The calibration box seen by the robot rig of ``seed`` (the rig the robot sequence uses); writes
    box/left.png, box/right.png and returns the rig's truth.

    The box sits 0.26 m in front of the rig, seen from the octant where its three boards face the cameras.
    """
    from edgecal.geometry import look_at
    from edgecal.synth import scenes
    from edgecal.synth.camera import stereo_right_pose
    from edgecal.synth.panels import panels_from_target
    from edgecal.synth.view import render_view

    rig = scenes.robot_rig(seed, (1280, 800))
    box = scenes.box_target()
    panels = panels_from_target(box)
    centre = np.full(3, 50.0)
    direction = -np.array([0.85, 0.75, 0.95]) / np.linalg.norm([0.85, 0.75, 0.95])
    eye = centre + 260.0 * direction
    R_left, _ = look_at(eye, centre, up=np.array([0.0, 0.0, -1.0]))
    t_left = -R_left @ (eye - R_left[0] * np.linalg.norm(rig.T_right_left_mm) / 2.0)
    R_right, t_right = stereo_right_pose(R_left, t_left, rig.R_right_left, rig.T_right_left_mm)
    for side, cam, R, t in (("left", rig.left, R_left, t_left), ("right", rig.right, R_right, t_right)):
        view = render_view(cam, panels, R, t, background=0.45, rng=seed, target_frame="box", target_name=box.name,
                           camera_name=side)
        write_atomic(out / "box" / f"{side}.png", png_bytes(view.image))
    return rig.as_json()


def detect_box(out: Path) -> list[str]:
    """Detect the box's boards in both images; one summary line per image."""
    from edgecal.config import packaged_config_path
    from edgecal.detection.detector import detect
    from edgecal.images import load_grey
    from edgecal.targets import load_target

    target = load_target(packaged_config_path("targets/box-100mm.yaml"))
    lines = []
    for side in ("left", "right"):
        dets = detect(load_grey(out / "box" / f"{side}.png"), target)
        boards = ", ".join(f"{d.board} {len(d.corners)}" for d in dets) or "none"
        lines.append(f"  {side}: {len(dets)} boards ({boards} corners)")
    return lines


def calibrate(out: Path, truth: dict) -> list[str]:
    """Calibrate from the box pair as ``edgecal calibrate --report`` does (rig.yaml, camera_info, corners, report;
    its output in calibrate.txt); compare focal, baseline and rotation with the truth."""
    from edgecal.calibration.from_images import calibrate_images, calibration_problems, provenance
    from edgecal.calibration.io import load_rig, write_calibration
    from edgecal.calibration.report import format_summary, write_report
    from edgecal.calibration.settings import load_calibration_settings
    from edgecal.calibration.views import corners_path, corners_text, name_views
    from edgecal.config import packaged_config_path
    from edgecal.targets import load_target

    target = load_target(packaged_config_path("targets/box-100mm.yaml"))
    settings = load_calibration_settings(None)
    views = name_views([(out / "box" / "left.png", out / "box" / "right.png")])
    cal, corners, size = calibrate_images(target, views, settings)
    problems = calibration_problems(cal, target, views, settings)
    corners_out = corners_path(out / "rig.yaml")
    prov = provenance(target, views, cal, settings, None, corners_out)
    write_report(cal, views, out / "calibration", True, problems=problems, bounds=settings.acceptance, provenance=prov)
    log = [format_summary(cal)]
    if not problems:
        also = {corners_out: corners_text(views, corners, size, target).encode("utf-8")}
        log += [f"wrote {p}" for p in write_calibration(cal, out / "rig.yaml", True, provenance=prov, also=also)]
    write_atomic(out / "calibrate.txt", ("\n".join(log) + "\n").encode("utf-8"))
    if problems:
        raise EdgecalError(f"demo: calibration refused ({'; '.join(problems)}); details in {out / 'calibrate.txt'}")
    rig = load_rig(out / "rig.yaml")
    lines = []
    for i, side in enumerate(("left", "right")):
        f_est = rig.cameras[i].camera_matrix[0, 0]
        f_true = truth[side]["K"][0][0]
        lines.append(f"  {side} focal {f_est:.1f} px (true {f_true:.1f}, error {100 * (f_est / f_true - 1):+.2f} %)")
    T_true = np.array(truth["T_right_left_mm"])
    assert rig.stereo is not None  # the demo calibrates a stereo pair
    T_est = rig.stereo.t_right_left_m * 1000
    dR = Rotation.from_matrix(rig.stereo.R_right_left @ np.array(truth["R_right_left"]).T).magnitude()
    lines.append(f"  baseline {np.linalg.norm(T_est):.2f} mm (true {np.linalg.norm(T_true):.2f}), T error "
                 f"{np.linalg.norm(T_est - T_true):.2f} mm, rotation error {np.degrees(dR):.3f} deg")
    return lines


def render_robot(out: Path, seed: int, frames: int) -> None:
    """The robot moving in front of the rig, with the true pose of every frame (as ``edgecal render robot``)."""
    from edgecal.synth import scenes, writer

    size = (1280, 800)
    rig = scenes.robot_rig(seed, size)
    sequence = scenes.robot_sequence(seed, frames, size=size, photometric="clean")
    writer.write_robot_sequence(out / "robot", sequence, rig, scenes.robot_target(), 30.0, True)


def stream(out: Path) -> tuple[list[dict], float]:
    """Run the live loop once over the replay (every frame, in order) with a subscriber; its pose messages."""
    from edgecal.publish.subscriber import MessageCollector
    from edgecal.stream import LiveLoop, load_live_config

    cfg = out / "live.yaml"
    write_atomic(cfg, yaml.safe_dump({
        "source": {"driver": "replay", "path": str(out / "robot"), "pace": "fast", "preload": True,
                   "latest_only": False},
        "rig": str(out / "rig.yaml"), "target": "targets/robot-3boards.yaml",
        "publish": {"endpoint": ENDPOINT},
        "loop": {"stop_at_end": True},
    }, sort_keys=False).encode("utf-8"))
    loop = LiveLoop(load_live_config(cfg))
    sub = MessageCollector(ENDPOINT, ("pose",))
    t0 = time.monotonic()
    try:
        loop.run()
    finally:
        elapsed = time.monotonic() - t0
        messages = sub.close(drain_s=0.3)
    return messages, loop.stats.frames / max(elapsed, 1e-9)


def pose_summary(messages: list[dict], truth_file: Path) -> list[str]:
    """Pose errors of the published poses against the rendered truth."""
    frames = json.loads(truth_file.read_text())["frames"]
    pos, rot = [], []
    valid = [m for m in messages if m["valid"]]
    for m in valid:
        fr = frames[m["seq"] % len(frames)]
        pos.append(1000 * np.linalg.norm(np.array(m["pose"]["position_m"]) - fr["t_rig_robot_m"]))
        dq = Rotation.from_quat(m["pose"]["orientation_xyzw"]) * Rotation.from_matrix(fr["R_rig_robot"]).inv()
        rot.append(np.degrees(dq.magnitude()))
    tracked = sum(m["quality"].get("detection") == "tracked" for m in messages)
    lines = [f"  {len(valid)} of {len(messages)} published poses valid; {tracked} frames tracked, "
             f"{len(messages) - tracked} searched in full"]
    reasons = sorted({m["reason"] for m in messages if not m["valid"]})
    if reasons:
        lines.append(f"  invalid because: {'; '.join(reasons[:3])}")
    if pos:
        lat = np.array([m["latency_ns"] for m in messages]) / 1e6
        lines.append(f"  position error median {np.median(pos):.2f} mm, max {np.max(pos):.2f} mm; rotation error "
                     f"median {np.median(rot):.3f} deg, max {np.max(rot):.3f} deg")
        lines.append(f"  capture->publish latency median {np.median(lat):.0f} ms")
    return lines


def run(args: argparse.Namespace) -> int:
    """Render, detect, calibrate, render the robot, stream, summarise."""
    out = Path(args.out)
    if (out / "rig.yaml").exists() and not args.force:
        raise InputError(f"{out}: holds an earlier demo (rig.yaml); use --force to replace it or another --out")
    check_outputs([out / "rig.yaml"], force=True, create_folders=True)
    make_folders(out)
    t0 = time.monotonic()
    print(f"1. calibration box rendered for the robot's stereo rig -> {out / 'box'}", flush=True)
    truth = render_box_pair(args.seed, out)
    for line in detect_box(out):
        print(line, flush=True)
    print(f"2. calibrated from that one pair -> {out / 'rig.yaml'}", flush=True)
    for line in calibrate(out, truth):
        print(line, flush=True)
    print(f"3. robot sequence: {args.frames} stereo frames 1280x800 -> {out / 'robot'}", flush=True)
    render_robot(out, args.seed, args.frames)
    print("4. live loop on its replay (every frame), subscriber on " + ENDPOINT + "; the pose errors include "
          "the calibration's own error above", flush=True)
    messages, fps = stream(out)
    print(f"  {len(messages)} poses received, {fps:.1f} stereo frames/s processed", flush=True)
    for line in pose_summary(messages, out / "robot" / "truth.json"):
        print(line, flush=True)
    print(f"done in {time.monotonic() - t0:.0f} s. Stream it live: edgecal run --config configs/robot.yaml "
          f"& edgecal listen")
    return 0
