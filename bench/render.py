#!/usr/bin/env python3
"""Renderer benchmark: time per rendered view, single thread, after warm-up.

    .venv/bin/python bench/render.py [--repeat 15]

Prints median and p90 ms for the scene generators at 640x480 and 1280x800 (each image a new random
camera, so the ray grid is computed each time), for a view with a fixed camera (the ray grid cached,
as in the robot sequence), the parts of one 1280x800 render, and as a reference the naive OpenCV way
of drawing a board (8x supersampled warpPerspective + INTER_AREA, no distortion, no exact truth).
"""

from __future__ import annotations

import os

for _var in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from edgecal.runtime import tune_allocator  # noqa: E402
from edgecal.synth import scenes  # noqa: E402
from edgecal.synth.camera import _RAY_CACHE, corner_ray_grid  # noqa: E402
from edgecal.synth.clutter import clutter_background  # noqa: E402
from edgecal.synth.panels import panels_from_target  # noqa: E402
from edgecal.synth.photometric import apply_photometric, random_photometric  # noqa: E402
from edgecal.synth.render import render_radiance  # noqa: E402
from edgecal.synth.truth import board_truth  # noqa: E402
from edgecal.synth.view import render_view  # noqa: E402
from edgecal.targets import planar_target  # noqa: E402


def timed(fn: Callable[[int], object], repeat: int) -> tuple[float, float, float]:
    """Median and p90 wall ms, and median CPU ms, of fn(k) for k = 1..repeat, after a warm-up call fn(0).

    CPU time (this process only) is what the render costs; wall time also counts waiting for a core on
    a shared machine.
    """
    fn(0)
    ms, cpu = [], []
    for k in range(1, repeat + 1):
        t0, c0 = time.perf_counter(), time.process_time()
        fn(k)
        ms.append((time.perf_counter() - t0) * 1e3)
        cpu.append((time.process_time() - c0) * 1e3)
    return float(np.median(ms)), float(np.percentile(ms, 90)), float(np.median(cpu))


def opencv_reference(size: tuple[int, int], cols: int, rows: int, square_px: float, H: np.ndarray) -> np.ndarray:
    """A board drawn the naive OpenCV way: 8x supersampled warp, then area-averaged down."""
    ss = 8
    s = int(square_px)
    board = np.full(((rows + 3) * s, (cols + 3) * s), 217, np.uint8)
    for j in range(rows + 1):
        for i in range(cols + 1):
            if (i + j) % 2 == 0:
                board[(j + 1) * s:(j + 2) * s, (i + 1) * s:(i + 2) * s] = 15
    S = np.diag([ss, ss, 1.0])
    big = cv2.warpPerspective(board, S @ H, (size[0] * ss, size[1] * ss), flags=cv2.INTER_LINEAR,
                              borderValue=128)
    return cv2.resize(big, size, interpolation=cv2.INTER_AREA)


def main() -> int:
    """Run the timings and print the table."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeat", type=int, default=15, help="timed renders per row (default 15)")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    n = args.repeat
    rows: list[tuple[str, float, float, float]] = []
    for size in ((640, 480), (1280, 800)):
        tag = f"{size[0]}x{size[1]}"
        rows.append((f"planar_view {tag} (new camera, clutter, normal)",
                     *timed(lambda k, size=size: scenes.planar_view(k, size=size), n)))
        rows.append((f"planar_view {tag} (new camera, uniform, clean)",
                     *timed(lambda k, size=size: scenes.planar_view(k, size=size, background="uniform",
                                                                    photometric="clean"), n)))
        cam = scenes.random_camera(np.random.default_rng(0), size)
        tgt = planar_target(9, 6, 25.0)
        board = tgt.boards[0]
        poses = [scenes.place_board(np.random.default_rng(k), cam, board, 0.06 * size[0]) for k in range(n + 1)]
        panels = panels_from_target(tgt)
        rows.append((f"render_view {tag} (fixed camera, 9x6 board)",
                     *timed(lambda k, cam=cam, panels=panels, poses=poses: render_view(cam, panels, *poses[k][:2]), n)))
        rows.append((f"  reference: OpenCV 8x warp {tag} (no distortion, no truth)",
                     *timed(lambda k, size=size: opencv_reference(size, 9, 6, 0.06 * size[0], np.array(
                         [[1.0, 0.1 * np.sin(k), 100.0], [0.05, 1.0, 80.0], [1e-4, 0.0, 1.0]])), n)))
    rows.append(("multi_view 1280x800", *timed(lambda k: scenes.multi_view(k), max(3, n // 3))))
    rows.append(("box_stereo pair 1280x800", *timed(lambda k: scenes.box_stereo(k), max(3, n // 3))))
    seq = scenes.robot_sequence(0, None)
    rows.append(("robot_sequence stereo frame 1280x800", *timed(lambda k: next(seq), n)))

    # The parts of one 1280x800 render.
    size = (1280, 800)
    rng = np.random.default_rng(1)
    cams = [scenes.random_camera(np.random.default_rng(k), size) for k in range(n + 1)]
    rows.append(("  part: ray grid of a new camera 1280x800",
                 *timed(lambda k: (_RAY_CACHE.clear(), corner_ray_grid(cams[k])), n)))
    cam = cams[0]
    tgt = planar_target(9, 6, 25.0)
    R, t, _ = scenes.place_board(rng, cam, tgt.boards[0], 40.0)
    panels = panels_from_target(tgt)
    rows.append(("  part: ray-cast 9x6 board, 40 px squares", *timed(lambda k: render_radiance(cam, panels, R, t), n)))
    radiance, _ = render_radiance(cam, panels, R, t)
    phot = random_photometric(rng, "normal")
    rows.append(("  part: photometry (normal)", *timed(lambda k: apply_photometric(radiance, phot, rng), n)))
    rows.append(("  part: clutter background", *timed(lambda k: clutter_background(np.random.default_rng(k), size), n)))
    rows.append(("  part: ground truth", *timed(lambda k: board_truth(cam, panels, R, t), n)))

    width = max(len(r[0]) for r in rows)
    print(f"# load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    print(f"{'what':<{width}}  {'median ms':>9}  {'p90 ms':>8}  {'CPU ms':>7}")
    for name, med, p90, cpu in rows:
        print(f"{name:<{width}}  {med:9.1f}  {p90:8.1f}  {cpu:7.1f}")
    return 0


if __name__ == "__main__":
    tune_allocator()  # as every edgecal command does (importing edgecal does not)
    raise SystemExit(main())
