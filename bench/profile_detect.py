#!/usr/bin/env python3
"""Where edgecal's detector spends its time: milliseconds per stage, per image set and size, single thread.

    .venv/bin/python bench/profile_detect.py [--sets planar_640,negatives_640,robot_hard] [--repeat 3] [--clock cpu]

Each stage function of the pipeline (edgecal.detection.*) is wrapped in a timer for the run; a stage's time
is *exclusive*: a stage called inside another one (completion probes and refines its predictions) is
counted for itself, not for its caller, so the rows add up to the total. Per set it prints the median
total ms per image, the mean ms per image of every stage, and how many candidates, accepted points and
boards each image had. Sets: 640x480 and 1280x800 renders with one board (``planar_640``, ``planar_1280``),
renders without a board (``negatives_640``, ``negatives_1280``), frames of bench/live.py's hard robot
sequence (``robot_hard``, 1280x800, three boards), and ../shared's synthetic sets and the real photographs of
one board (``real_opencv_stereo_9x6``, 640x480, ...) when present.
"""

from __future__ import annotations

import os

if __name__ == "__main__":
    for _var in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[_var] = "1"

import argparse  # noqa: E402
import functools  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from collections import defaultdict  # noqa: E402
from collections.abc import Callable  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

import edgecal  # noqa: E402
from edgecal.runtime import tune_allocator  # noqa: E402
from edgecal.targets import Target, planar_target  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("EDGECAL_DATA", REPO.parent / "shared" / "data"))

#: (module, function name, stage): every call site of a stage function, by the module that calls it.
STAGES = (
    ("edgecal.detection.detector", "as_grey", "convert"),
    ("edgecal.detection.detector", "estimate_noise_sigma", "noise"),
    ("edgecal.detection.detector", "half_resolution_noise_sigma", "noise"),
    ("edgecal.detection.levels", "estimate_noise_sigma", "noise"),
    ("edgecal.detection.levels", "smooth_image", "smooth"),
    ("edgecal.detection.levels", "gradients", "gradients"),
    ("edgecal.detection.levels", "gradients_near", "gradients"),
    ("edgecal.detection.detector", "min_eigen_candidates", "candidates"),
    ("edgecal.detection.detector", "snap_to_saddle", "snap"),
    ("edgecal.detection.detector", "dedupe_in_order", "dedupe"),
    ("edgecal.detection.detector", "chess_thresholds", "chess"),
    ("edgecal.detection.detector", "chess_filter", "chess"),
    ("edgecal.detection.detector", "ring_prefilter_radii", "prefilter"),
    ("edgecal.detection.detector", "probe_candidates", "probe"),
    ("edgecal.detection.detector", "probe_accepts", "probe"),
    ("edgecal.detection.detector", "refine_corners", "subpixel"),
    ("edgecal.detection.detector", "nearest_spacing", "spacing"),
    ("edgecal.detection.detector", "group_grids", "grouping"),
    ("edgecal.detection.detector", "trim_false_edges", "completion"),
    ("edgecal.detection.detector", "complete_grid", "completion"),
    ("edgecal.detection.completion", "probe_candidates", "probe"),
    ("edgecal.detection.completion", "refine_corners", "subpixel"),
    ("edgecal.detection.detector", "assign_ids", "ids+checks"),
    ("edgecal.detection.detector", "grid_is_regular", "ids+checks"),
    ("edgecal.detection.detector", "_corner_quality", "quality"),
    ("edgecal.detection.detector", "add_board_covariances", "covariance"),
    ("edgecal.detection.detector", "_outside_boards", "exclusion"),
    ("edgecal.detection.board_corners", "refine_corners", "subpixel"),
    ("edgecal.detection.board_corners", "nearest_spacing", "spacing"),
    ("edgecal.detection.board_corners", "saddle_refine", "saddle"),
    ("edgecal.detection.board_corners", "refine_rim", "rim"),
    ("edgecal.detection.board_corners", "xjunction_fit", "xjunction"),
    ("edgecal.detection.board_corners", "bend_shift", "bend"),
    ("edgecal.detection.board_corners", "xjunction_radius", "xjunction"),
    ("edgecal.detection.subpixel", "refine_corners", "subpixel"),
    ("edgecal.detection.detector", "resettle_slid_corners", "resettle"),
)


#: --clock: elapsed time, or the CPU time of this process (leaves out the waits for a core on a shared machine).
CLOCKS: dict[str, Callable[[], float]] = {"wall": time.perf_counter, "cpu": time.process_time}


class StageClock:
    """Exclusive time per stage: wraps the stage functions in their calling modules while active."""

    def __init__(self, clock: Callable[[], float] = time.perf_counter) -> None:
        self.clock = clock
        self.ms: dict[str, float] = defaultdict(float)
        self._stack: list[float] = []  # time spent in nested stages, per open call
        self._saved: list[tuple[object, str, Callable]] = []

    def _wrap(self, fn: Callable, stage: str) -> Callable:
        @functools.wraps(fn)
        def timed(*args, **kwargs):
            self._stack.append(0.0)
            t0 = self.clock()
            try:
                return fn(*args, **kwargs)
            finally:
                elapsed = self.clock() - t0
                nested = self._stack.pop()
                self.ms[stage] += 1e3 * (elapsed - nested)
                if self._stack:
                    self._stack[-1] += elapsed
        return timed

    def __enter__(self) -> StageClock:
        import importlib
        for module_name, name, stage in STAGES:
            module = importlib.import_module(module_name)
            fn = getattr(module, name, None)
            if fn is None:  # the pipeline changed: say so rather than time nothing
                print(f"# profile: {module_name}.{name} not found (stage {stage} not timed)", file=sys.stderr)
                continue
            self._saved.append((module, name, fn))
            setattr(module, name, self._wrap(fn, stage))
        return self

    def __exit__(self, *exc) -> None:
        for module, name, fn in reversed(self._saved):
            setattr(module, name, fn)
        self._saved.clear()

    def take(self) -> dict[str, float]:
        """The stage times since the last take, and reset."""
        out = dict(self.ms)
        self.ms.clear()
        return out


def rendered(kind: str, size: tuple[int, int], n: int) -> list[tuple[np.ndarray, Target]]:
    """``n`` renders: one 9x6 board (15-45 px squares, normal photometry) or no board, at ``size``."""
    from edgecal.synth.scenes import negative_view, planar_view
    out = []
    for k in range(n):
        if kind == "planar":
            view = planar_view((7, k), size=size, square_px=(15.0, 45.0) if size[0] < 1000 else (25.0, 70.0))
        else:
            view = negative_view((7, k), size=size)
        out.append((view.image, planar_target(9, 6)))
    return out


def robot_hard(n: int) -> list[tuple[np.ndarray, Target]]:
    """Left and right images of the first frames of bench/live.py's sequence, rendered with hard photometry."""
    from edgecal.synth import scenes
    target = scenes.robot_target()
    out = []
    for frame in scenes.robot_sequence(7, (n + 1) // 2, size=(1280, 800), photometric="hard"):
        out += [(frame.left.image, target), (frame.right.image, target)]
    return out[:n]


def shared_set(name: str, n: int) -> list[tuple[np.ndarray, Target]]:
    """The first ``n`` images of ../shared/data/synthetic/NAME with their targets."""
    import json

    from edgecal.images import load_grey
    from edgecal.targets import Board
    folder = DATA / "synthetic" / name
    out = []
    for png in sorted(folder.glob("*.png"))[:n]:
        js = png.with_suffix(".json")
        if not js.is_file():
            continue
        boards = json.loads(js.read_text()).get("target", {}).get("boards", [])
        target = (Target(name, tuple(Board(b["name"], b["cols"], b["rows"], b.get("square_mm", 1.0))
                                     for b in boards), name) if boards else planar_target(9, 6))
        out.append((load_grey(png), target))
    return out


#: Real photographs of ../shared/data/real with one board of a size SOURCE.md gives (inner corners).
REAL_BOARDS = {"opencv_stereo_9x6": (9, 6), "ocamcalib_urban_fisheye1": (6, 8),
               "ocamcalib_scaramuzza_fisheye190": (6, 7)}


def real_set(name: str, n: int) -> list[tuple[np.ndarray, Target]]:
    """The first ``n`` photographs of ../shared/data/real/NAME with its board (empty when absent)."""
    from edgecal.images import IMAGE_SUFFIXES, load_grey
    folder = DATA / "real" / name
    if not folder.is_dir():
        return []
    files = sorted(f for f in folder.iterdir() if f.suffix.lower() in IMAGE_SUFFIXES)[:n]
    return [(load_grey(f), planar_target(*REAL_BOARDS[name])) for f in files]


def load_sets(names: list[str], n: int) -> dict[str, list[tuple[np.ndarray, Target]]]:
    """The named sets (absent shared sets are skipped)."""
    makers: dict[str, Callable[[], list]] = {
        "planar_640": lambda: rendered("planar", (640, 480), n),
        "planar_1280": lambda: rendered("planar", (1280, 800), n),
        "negatives_640": lambda: rendered("negative", (640, 480), n),
        "negatives_1280": lambda: rendered("negative", (1280, 800), n),
        "robot_hard": lambda: robot_hard(n),
    }
    for shared in ("planar", "hard", "multi", "negatives"):
        makers[f"shared_{shared}"] = functools.partial(shared_set, shared, n)
    for real in REAL_BOARDS:
        makers[f"real_{real}"] = functools.partial(real_set, real, n)
    out = {}
    for name in names:
        if name not in makers:
            raise SystemExit(f"profile: unknown set {name!r}; choose from {', '.join(makers)}")
        items = makers[name]()
        if items:
            out[name] = items
        else:
            print(f"# {name}: absent, skipped", file=sys.stderr)
    return out


def profile_set(items: list[tuple[np.ndarray, Target]], repeat: int,
                clock: Callable[[], float] = time.perf_counter) -> dict:
    """Median total ms, mean ms per stage, and mean counts per image over ``items``."""
    totals, per_stage = [], defaultdict(list)
    counts = defaultdict(list)
    with StageClock(clock) as stages_clock:
        for image, target in items:
            runs = []
            for _ in range(repeat):
                stages_clock.take()
                t0 = clock()
                debug = edgecal.detect_debug(image, target)
                total = 1e3 * (clock() - t0)
                runs.append((total, stages_clock.take()))
            total, stages = sorted(runs, key=lambda r: r[0])[len(runs) // 2]
            totals.append(total)
            for stage in {s for _m, _n, s in STAGES}:
                per_stage[stage].append(stages.get(stage, 0.0))
            per_stage["other"].append(total - sum(stages.values()))
            counts["candidates"].append(len(debug.candidates))
            counts["accepted"].append(len(debug.accepted))
            counts["boards"].append(len(debug.detections))
    return {"median_ms": float(np.median(totals)), "p90_ms": float(np.percentile(totals, 90)),
            "stages": {k: float(np.mean(v)) for k, v in per_stage.items()},
            "counts": {k: float(np.mean(v)) for k, v in counts.items()}, "images": len(items)}


def main(argv: list[str] | None = None) -> int:
    """Profile the selected sets and print one table."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sets", default="planar_640,planar_1280,negatives_640,negatives_1280,robot_hard",
                    help="comma-separated: planar_640, planar_1280, negatives_640, negatives_1280, robot_hard, "
                         "shared_planar, shared_hard, shared_multi, shared_negatives, "
                         + ", ".join(f"real_{r}" for r in REAL_BOARDS))
    ap.add_argument("--images", type=int, default=8, help="images per set (default 8)")
    ap.add_argument("--repeat", type=int, default=3, help="calls per image; the median call is kept")
    ap.add_argument("--clock", choices=tuple(CLOCKS), default="wall",
                    help="elapsed time (wall, default) or this process's CPU time (cpu: steadier on a shared machine)")
    args = ap.parse_args(argv)
    cv2.setNumThreads(1)
    sets = load_sets([s.strip() for s in args.sets.split(",") if s.strip()], args.images)
    warm = next(iter(sets.values()))[0]
    edgecal.detect_debug(*warm)  # numba JIT / cache load, not timed
    results = {name: profile_set(items, args.repeat, CLOCKS[args.clock]) for name, items in sets.items()}
    names = list(results)
    stage_order = list(dict.fromkeys(s for _m, _n, s in STAGES)) + ["other"]
    width = max(12, *(len(n) for n in names))
    print(f"# ms per image ({'elapsed' if args.clock == 'wall' else 'CPU'} time), single thread; stage times "
          f"exclusive (mean), totals median of "
          f"{args.images} images x {args.repeat} calls")
    print(f"{'':<12}" + "".join(f"{n:>{width + 1}}" for n in names))
    size = {n: "x".join(str(v) for v in sets[n][0][0].shape[1::-1]) for n in names}
    print(f"{'size':<12}" + "".join(f"{size[n]:>{width + 1}}" for n in names))
    for key in ("median_ms", "p90_ms"):
        print(f"{key:<12}" + "".join(f"{results[n][key]:>{width + 1}.1f}" for n in names))
    for stage in stage_order:
        print(f"  {stage:<10}" + "".join(f"{results[n]['stages'].get(stage, 0.0):>{width + 1}.2f}" for n in names))
    for c in ("candidates", "accepted", "boards"):
        print(f"{c:<12}" + "".join(f"{results[n]['counts'][c]:>{width + 1}.0f}" for n in names))
    return 0


if __name__ == "__main__":
    tune_allocator()  # as every edgecal command does (importing edgecal does not)
    sys.exit(main())
