#!/usr/bin/env python3
"""Soak test of the live loop: many replayed frames with a subscriber attached; memory, threads and
file handles must stay flat.

    .venv/bin/python bench/soak.py [--frames 100000] [--size 1280x800] [--pace recorded] [--reload-every 5000]

A rendered robot sequence (--sequence frames, preloaded and looped, through the latest-frame-wins
reader; paced at its 30 fps by default, as a camera delivers) goes through the real loop in this
process; a ZeroMQ subscriber reads every message. Each wrap of the loop makes the robot jump back, so
the loop also loses and re-acquires the track once per pass (a full search). Every --sample frames it
records the resident memory, the process's threads and open file descriptors. At the end it prints the
first and last samples, the RSS slope (kB per 1000 frames over the second half, after warm-up) and
PASS/FAIL against: RSS growth < 20 MB over the second half, threads and fds back to their starting
counts, no errors. --reload-every also reloads the config (SIGHUP's path) that often. 100,000 frames at
30 fps take 56 minutes.
"""

from __future__ import annotations

import os

if __name__ == "__main__":
    for _var in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[_var] = "1"

import argparse  # noqa: E402
import sys  # noqa: E402
import threading  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import yaml  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from live import write_rig  # noqa: E402

from edgecal.publish.subscriber import MessageCollector  # noqa: E402
from edgecal.runtime import tune_allocator  # noqa: E402
from edgecal.stream import LiveLoop, load_live_config  # noqa: E402


class MessageCounter:
    """Counts the messages a subscriber receives and how many are valid poses, keeping nothing else (it shares
    this process's memory with the loop, so it must not grow itself)."""

    def __init__(self) -> None:
        self.received = 0
        self.valid = 0

    def __call__(self, msg: dict) -> None:
        self.received += 1
        self.valid += bool(msg.get("valid"))


def rss_kb() -> int:
    """Resident set size of this process."""
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") // 1024


def thread_names() -> list[str]:
    """Kernel names of this process's threads (Python's and native ones)."""
    out = []
    for tid in os.listdir("/proc/self/task"):
        try:
            out.append(open(f"/proc/self/task/{tid}/comm").read().strip())
        except OSError:
            pass
    return sorted(out)


def counts() -> tuple[int, int]:
    """(threads, open file descriptors) of this process."""
    return len(os.listdir("/proc/self/task")), len(os.listdir("/proc/self/fd"))


def ensure_sequence(folder: Path, size: tuple[int, int], n: int) -> None:
    if (folder / "truth.json").is_file() and (folder / "rig.yaml").is_file():
        return
    import json

    from edgecal.synth import scenes, writer
    rig = scenes.robot_rig(11, size)
    writer.write_robot_sequence(folder, scenes.robot_sequence(11, n, size=size), rig, scenes.robot_target(), 30.0,
                                force=True)
    write_rig(json.loads((folder / "truth.json").read_text())["rig"], folder / "rig.yaml")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=100_000)
    ap.add_argument("--size", default="1280x800", help="WIDTHxHEIGHT of the rendered sequence")
    ap.add_argument("--sequence", type=int, default=60, help="frames in the rendered (looped) sequence")
    ap.add_argument("--pace", default="recorded", choices=("recorded", "fast"),
                    help="recorded: 30 fps as a camera; fast: as fast as the replay hands frames out")
    ap.add_argument("--sample", type=int, default=500, help="frames between samples")
    ap.add_argument("--reload-every", type=int, default=5000, help="reload the config every N frames (0 = never)")
    ap.add_argument("--out", default="out/bench/soak")
    ap.add_argument("--endpoint", default="tcp://127.0.0.1:5592")
    args = ap.parse_args()
    w, h = (int(v) for v in args.size.lower().split("x"))
    out = Path(args.out)
    folder = out / f"robot-{w}x{h}-{args.sequence}"
    ensure_sequence(folder, (w, h), args.sequence)
    cfg = out / "soak.yaml"
    cfg.write_text(yaml.safe_dump({
        "source": {"driver": "replay", "path": str(folder), "pace": args.pace, "loop": True, "preload": True},
        "rig": str(folder / "rig.yaml"), "target": "targets/robot-3boards.yaml",
        "publish": {"endpoint": args.endpoint}, "loop": {"status_period_s": 1.0},
    }))
    # A short run first: native libraries start helper threads lazily on first use (one stays for the
    # process's life); the leak check compares the big run against the state after this one.
    pre = LiveLoop(load_live_config(cfg))
    timer = threading.Timer(3.0, pre.request_stop)
    timer.start()
    pre.run()
    timer.cancel()
    timer.join()
    base_threads, base_fds = counts()
    counter = MessageCounter()
    sub = MessageCollector(args.endpoint, on_message=counter)
    loop = LiveLoop(load_live_config(cfg))
    samples: list[tuple[int, float, int, int, int]] = []

    clock: dict[str, float] = {}

    def watch() -> None:
        next_sample, next_reload = 0, args.reload_every or -1
        while not loop.stats.frames:          # opening (the preload) is not the loop's rate
            time.sleep(0.01)
        t0 = clock["first_frame"] = time.monotonic()
        while loop.stats.frames < args.frames:
            n = loop.stats.frames
            if n >= next_sample:
                th, fds = counts()
                samples.append((n, time.monotonic() - t0, rss_kb(), th, fds))
                print(f"{n:7d} frames {samples[-1][1]:7.0f} s  RSS {samples[-1][2] / 1024:7.1f} MB  threads {th}  "
                      f"fds {fds}  received {counter.received}", flush=True)
                next_sample += args.sample
            if next_reload > 0 and n >= next_reload:
                loop.request_reload()
                next_reload += args.reload_every
            time.sleep(0.05)
        clock["last_frame"] = time.monotonic()
        loop.request_stop()

    watcher = threading.Thread(target=watch, daemon=True)
    watcher.start()
    loop.run()
    watcher.join()
    sub.close(drain_s=0.2)
    received = counter.received
    end_threads, end_fds = counts()
    extra = [t.name for t in threading.enumerate() if t is not threading.main_thread()]
    half = [s for s in samples if s[0] >= args.frames // 2] or samples[-2:]
    x = np.array([s[0] for s in half], float)
    y = np.array([s[2] for s in half], float)
    slope = float(np.polyfit(x, y, 1)[0] * 1000) if len(half) >= 2 and np.ptp(x) > 0 else 0.0
    growth_mb = (half[-1][2] - half[0][2]) / 1024
    fps = (loop.stats.frames - 1) / max(clock["last_frame"] - clock["first_frame"], 1e-9)
    print(f"\n{loop.stats.frames} frames at {fps:.1f} fps ({w}x{h}), {received} messages received, "
          f"{loop.stats.tracked_frames} tracked, {loop.stats.dropped_frames} dropped, "
          f"{loop.stats.poses_valid} valid poses, {loop.stats.reconnects} reconnects, {loop.stats.errors} errors, "
          f"{loop.stats.reload_failures} failed reloads")
    print(f"RSS {samples[0][2] / 1024:.1f} MB at start, {samples[-1][2] / 1024:.1f} MB at the end; second half "
          f"growth {growth_mb:+.1f} MB, slope {slope:+.2f} kB per 1000 frames")
    print(f"threads {base_threads} before (after a 3-s warm-up run), "
          f"{max(s[3] for s in samples)} at most while running, {end_threads} after; "
          f"fds {base_fds} before, {max(s[4] for s in samples)} at most, {end_fds} after"
          + (f"; Python threads left: {', '.join(extra)}" if extra else ""))
    ok = growth_mb < 20 and end_threads <= base_threads and end_fds <= base_fds and loop.stats.errors == 0
    print("PASS" if ok else "FAIL")
    return 0 if ok else 1


if __name__ == "__main__":
    tune_allocator()  # as every edgecal command does (importing edgecal does not)
    sys.exit(main())
