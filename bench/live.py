#!/usr/bin/env python3
"""Live-loop benchmark: a rendered robot sequence replayed through the real loop and a real subscriber.

    .venv/bin/python bench/live.py [--frames 60] [--seconds 20] [--out out/bench/live] [--json FILE]

The sequence (1280x800, 30 fps, the robot carrying configs/targets/robot-3boards.yaml at about 1 m,
clean renders) is rendered once into --out and reused. The rig file holds the renderer's true cameras,
so the numbers are the loop's, not a calibration's. Two runs, each through `LiveLoop` in this process
with a ZeroMQ SUB socket on localhost:

* real time: replay paced at 30 fps, latest-frame-wins (as a camera would deliver): capture->publish
  latency median/p99, achieved fps, dropped frames, CPU use;
* as fast as possible: replay not paced, every frame processed in order: sustained fps, CPU use.

For both: pose error against ground truth (position mm, rotation deg; median, p95, max) and the
covariance's consistency with the error (mean NEES, 6 for a consistent 6-D estimate; per-axis ratio of
RMS error to the reported sigma). The OpenCV reference (findChessboardCornersSB, once per board size,
on both images) is timed on the same frames, single thread, for the detection ratio.
"""

from __future__ import annotations

import os

if __name__ == "__main__":
    for _var in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[_var] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
import resource  # noqa: E402
import sys  # noqa: E402
import threading  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402
import yaml  # noqa: E402
import zmq  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

import edgecal  # noqa: E402
from edgecal.stream import LiveLoop, load_live_config  # noqa: E402

THRESHOLDS = {"fps": 30.0, "p99_ms": 33.0, "position_mm": 1.0, "rotation_deg": 0.1}


def ensure_sequence(folder: Path, n_frames: int, seed: int = 7) -> dict:
    """Render the robot sequence (and its true rig.yaml) unless it is already there with enough frames."""
    truth_file = folder / "truth.json"
    if truth_file.is_file():
        truth = json.loads(truth_file.read_text())
        if len(truth["frames"]) >= n_frames and (folder / "rig.yaml").is_file():
            return truth
    from edgecal.synth import scenes, writer
    t0 = time.perf_counter()
    rig = scenes.robot_rig(seed, (1280, 800))
    frames = scenes.robot_sequence(seed, n_frames, size=(1280, 800), photometric="clean")
    writer.write_robot_sequence(folder, frames, rig, scenes.robot_target(), 30.0, force=True)
    truth = json.loads(truth_file.read_text())
    write_rig(truth["rig"], folder / "rig.yaml")
    print(f"rendered {n_frames} stereo frames into {folder} ({time.perf_counter() - t0:.0f} s)")
    return truth


def write_rig(rig: dict, path: Path) -> None:
    """rig.yaml with the renderer's true cameras (T in metres)."""
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("image_size", np.array(rig["left"]["image_size"], dtype=np.int32).reshape(1, 2))
    for side in ("left", "right"):
        fs.write(f"camera_matrix_{side}", np.array(rig[side]["K"], dtype=np.float64))
        fs.write(f"dist_coeffs_{side}", np.array(rig[side]["dist"], dtype=np.float64).reshape(1, -1))
    fs.write("R", np.array(rig["R_right_left"], dtype=np.float64))
    fs.write("T", np.array(rig["T_right_left_mm"], dtype=np.float64).reshape(3, 1) / 1000.0)
    fs.release()


class Collector:
    """A real ZeroMQ subscriber in its own thread."""

    def __init__(self, endpoint: str) -> None:
        self.ctx = zmq.Context()
        self.sock = self.ctx.socket(zmq.SUB)
        self.sock.setsockopt(zmq.SUBSCRIBE, b"")
        self.sock.setsockopt(zmq.LINGER, 0)
        self.sock.connect(endpoint)
        self.messages: list[dict] = []
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while not self.stop.is_set():
            if self.sock.poll(50):
                self.messages.append(json.loads(self.sock.recv_multipart()[1]))

    def close(self) -> list[dict]:
        time.sleep(0.2)
        self.stop.set()
        self.thread.join()
        self.sock.close()
        self.ctx.term()
        return self.messages


def run_loop(folder: Path, out: Path, realtime: bool, seconds: float, endpoint: str) -> dict:
    """One run of the live loop; returns the subscriber's messages and the run's wall and CPU time."""
    cfg = out / ("live-realtime.yaml" if realtime else "live-fast.yaml")
    source = {"driver": "replay", "path": str(folder), "pace": "recorded" if realtime else "fast",
              "loop": realtime, "timeout_s": 1.0}
    cfg.write_text(yaml.safe_dump({
        "source": source, "rig": str(folder / "rig.yaml"), "target": "targets/robot-3boards.yaml",
        "publish": {"endpoint": endpoint},
        "loop": {"latest_frame_wins": realtime, "stop_at_end": True, "status_period_s": 1.0},
    }))
    sub = Collector(endpoint)
    loop = LiveLoop(load_live_config(cfg))
    loop.warm_up()                       # JIT before the clock starts (run() does it again, cached)
    time.sleep(0.3)                      # let the subscription reach the publisher
    r0, t0 = resource.getrusage(resource.RUSAGE_SELF), time.monotonic()
    if realtime:
        timer = threading.Timer(seconds, loop.request_stop)
        timer.start()
    loop.run()
    wall = time.monotonic() - t0
    r1 = resource.getrusage(resource.RUSAGE_SELF)
    msgs = sub.close()
    cpu = (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)
    return {"messages": msgs, "wall_s": wall, "cpu_s": cpu, "stats": loop.stats}


def pose_errors(messages: list[dict], truth: dict) -> dict:
    """Errors of the valid poses against the truth, and the covariance's consistency."""
    frames = truth["frames"]
    n = len(frames)
    pos, rot, nees, errs, sig = [], [], [], [], []
    poses = [m for m in messages if m["type"] == "pose"]
    for m in poses:
        if not m["valid"]:
            continue
        fr = frames[m["seq"] % n]
        dt = np.array(m["pose"]["position_m"]) - np.array(fr["t_rig_robot_m"])
        R_est = Rotation.from_quat(m["pose"]["orientation_xyzw"]).as_matrix()
        dth = Rotation.from_matrix(R_est @ np.array(fr["R_rig_robot"]).T).as_rotvec()
        e = np.concatenate([dt, dth])
        C = np.array(m["covariance"]).reshape(6, 6)
        pos.append(1000 * np.linalg.norm(dt))
        rot.append(np.degrees(np.linalg.norm(dth)))
        nees.append(float(e @ np.linalg.solve(C, e)))
        errs.append(e)
        sig.append(np.sqrt(np.diag(C)))
    out = {"poses": len(poses), "valid": len(pos),
           "invalid_reasons": sorted({m["reason"] for m in poses if not m["valid"]})[:5]}
    if pos:
        ratio = np.sqrt(np.mean(np.square(errs), axis=0)) / np.sqrt(np.mean(np.square(sig), axis=0))
        out.update({
            "position_mm": {"median": float(np.median(pos)), "p95": float(np.percentile(pos, 95)),
                            "max": float(np.max(pos))},
            "rotation_deg": {"median": float(np.median(rot)), "p95": float(np.percentile(rot, 95)),
                             "max": float(np.max(rot))},
            "reported_sigma_mm": float(np.median([1000 * np.linalg.norm(s[:3]) for s in sig])),
            "nees_mean": float(np.mean(nees)), "nees_median": float(np.median(nees)),
            "rms_error_over_sigma": [round(float(v), 2) for v in ratio],
        })
    return out


def latency(messages: list[dict]) -> dict:
    lat = np.array([m["latency_ns"] for m in messages if m["type"] == "pose"], dtype=float) / 1e6
    return {"median_ms": float(np.median(lat)), "p99_ms": float(np.percentile(lat, 99)), "n": int(lat.size)} \
        if lat.size else {}


def detection_times(folder: Path, truth: dict, n: int) -> dict:
    """edgecal.detect vs OpenCV findChessboardCornersSB on the same stereo frames, single thread, ms per frame."""
    from edgecal.config import packaged_config_path
    target = edgecal.load_target(packaged_config_path("targets/robot-3boards.yaml"))
    sizes = sorted({(b.cols, b.rows) for b in target.boards})
    ours, ref = [], []
    cv2.setNumThreads(1)
    frames = truth["frames"][:n]
    for fr in frames:
        images = [cv2.imread(str(folder / fr[s]), cv2.IMREAD_GRAYSCALE) for s in ("left", "right")]
        t0 = time.perf_counter()
        for im in images:
            edgecal.detect(im, target)
        ours.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        for im in images:
            for size in sizes:
                cv2.findChessboardCornersSB(im, size, flags=cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY)
        ref.append(time.perf_counter() - t0)
    return {"frames": len(frames), "edgecal_ms": 1000 * float(np.median(ours)),
            "opencv_sb_ms": 1000 * float(np.median(ref)), "opencv_over_edgecal": float(np.median(ref) / np.median(ours))}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=60, help="frames in the rendered sequence (default 60)")
    ap.add_argument("--seconds", type=float, default=20.0, help="length of the real-time run (default 20)")
    ap.add_argument("--reference-frames", type=int, default=10, help="frames timed for the OpenCV reference")
    ap.add_argument("--out", default="out/bench/live", help="where the sequence and configs go")
    ap.add_argument("--json", default=None, help="write the results here as JSON")
    ap.add_argument("--endpoint", default="tcp://127.0.0.1:5591")
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    folder = out / "robot"
    truth = ensure_sequence(folder, args.frames)
    results: dict = {"frames": len(truth["frames"]), "size": "1280x800", "cores": os.cpu_count(),
                     "load_average_before": os.getloadavg()[0]}

    rt = run_loop(folder, out, True, args.seconds, args.endpoint)
    poses_rt = [m for m in rt["messages"] if m["type"] == "pose"]
    results["realtime"] = {
        "fps": len(poses_rt) / rt["wall_s"], "cpu_percent_of_one_core": 100 * rt["cpu_s"] / rt["wall_s"],
        "cpu_ms_per_frame": 1000 * rt["cpu_s"] / max(rt["stats"].frames, 1),
        "latency": latency(rt["messages"]), "dropped_frames": rt["stats"].dropped_frames,
        "detection_failures": rt["stats"].detection_failures, "errors": pose_errors(rt["messages"], truth)}

    fast = run_loop(folder, out, False, 0, args.endpoint)
    poses_fast = [m for m in fast["messages"] if m["type"] == "pose"]
    results["fast"] = {
        "fps": fast["stats"].frames / fast["wall_s"], "frames": fast["stats"].frames,
        "received": len(poses_fast), "cpu_percent_of_one_core": 100 * fast["cpu_s"] / fast["wall_s"],
        "cpu_ms_per_frame": 1000 * fast["cpu_s"] / max(fast["stats"].frames, 1),
        "latency": latency(fast["messages"]), "errors": pose_errors(fast["messages"], truth)}
    results["detection"] = detection_times(folder, truth, args.reference_frames)

    results["load_average_after"] = os.getloadavg()[0]
    r, f, d = results["realtime"], results["fast"], results["detection"]
    e = f["errors"]
    print(f"\nlive loop on {results['frames']} rendered 1280x800 stereo frames, {results['cores']} cores "
          f"(NUMBA_NUM_THREADS=1; left/right detection in two threads); load average "
          f"{results['load_average_before']:.1f} before, {results['load_average_after']:.1f} after")
    print(f"real time (30 fps replay, latest-frame-wins): {r['fps']:.1f} fps processed, latency median "
          f"{r['latency'].get('median_ms', float('nan')):.1f} ms p99 {r['latency'].get('p99_ms', float('nan')):.1f} ms, "
          f"{r['dropped_frames']} frames dropped, CPU {r['cpu_percent_of_one_core']:.0f}% of one core "
          f"({r['cpu_ms_per_frame']:.0f} CPU ms per frame)")
    print(f"as fast as possible: {f['fps']:.1f} fps sustained over {f['frames']} frames, "
          f"CPU {f['cpu_percent_of_one_core']:.0f}% of one core ({f['cpu_ms_per_frame']:.0f} CPU ms per frame; "
          f"{2000 / f['cpu_ms_per_frame']:.1f} fps if it had both cores to itself)")
    if "position_mm" in e:
        print(f"pose error ({e['valid']}/{e['poses']} valid): position median {e['position_mm']['median']:.3f} mm "
              f"p95 {e['position_mm']['p95']:.3f} max {e['position_mm']['max']:.3f}; rotation median "
              f"{e['rotation_deg']['median']:.4f} deg p95 {e['rotation_deg']['p95']:.4f} max "
              f"{e['rotation_deg']['max']:.4f}")
        print(f"covariance: mean NEES {e['nees_mean']:.1f} (6 = consistent), median {e['nees_median']:.1f}; "
              f"RMS error / reported sigma per axis [x y z rx ry rz] {e['rms_error_over_sigma']}")
    print(f"detection per stereo frame, single thread: edgecal {d['edgecal_ms']:.0f} ms, OpenCV SB "
          f"{d['opencv_sb_ms']:.0f} ms (OpenCV/edgecal {d['opencv_over_edgecal']:.2f})")
    print("targets: " + ", ".join([
        f"30 fps {'met' if f['fps'] >= THRESHOLDS['fps'] else 'NOT met'}",
        f"p99 < 33 ms {'met' if r['latency'].get('p99_ms', 1e9) < THRESHOLDS['p99_ms'] else 'NOT met'}",
        f"position < 1 mm {'met' if e.get('position_mm', {}).get('max', 1e9) < 1 else 'NOT met'} (max)",
        f"rotation < 0.1 deg {'met' if e.get('rotation_deg', {}).get('max', 1e9) < 0.1 else 'NOT met'} (max)"]))
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
