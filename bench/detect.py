#!/usr/bin/env python3
"""Detection benchmark: edgecal against the reference detectors on the same images, single thread.

    .venv/bin/python bench/detect.py [--sets planar,hard,real/*] [--detectors edgecal,opencv] \
        [--repeat 3] [--clock cpu] [--json out/bench.json] [--force] [--noise 1 [--noise-copies 3]]

Per set and detector it prints: boards found with all corners correctly ordered (and the rate), false
boards (detections lying on no true board; on negatives every detection is one), corner RMS against
ground truth (or reference corners) over the found boards, median and p90 ms per image, and the ratio
of each to edgecal. The first call of every detector (numba JIT, lazy initialisation) is timed apart
and printed as warm-up; it is not in the per-image times. Sets whose data is absent are skipped.
``--noise SIGMA``: every scored image is replaced by noisy copies (white noise of SIGMA grey levels, one seed
each), to see which results hold when the image changes by what a sensor's noise changes between shots.

Scoring (edgecal.scoring): edgecal must number boards as the truth does, up to the board's own
symmetries; the references know nothing of our numbering, so any grid symmetry is accepted for them.
OpenCV's detectors take one board size per call and return at most one board; they are called once per
distinct board size of the target. The libcbdetect binding reports how many boards it saw but returns
the corners of one only. calib-targets needs no board size; its components count when complete and of a
target board's size.
"""

from __future__ import annotations

import os

if __name__ == "__main__":
    # Single thread everywhere, before numpy/numba/OpenCV are imported (not when a test imports this).
    for _var in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
                 "RAYON_NUM_THREADS"):
        os.environ[_var] = "1"

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import fnmatch  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import traceback  # noqa: E402
import zlib  # noqa: E402
from collections.abc import Callable  # noqa: E402
from dataclasses import dataclass, field  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from edgecal.errors import EdgecalError  # noqa: E402
from edgecal.fileio import write_atomic  # noqa: E402
from edgecal.images import IMAGE_SUFFIXES, load_grey  # noqa: E402
from edgecal.runtime import tune_allocator  # noqa: E402
from edgecal.scoring import (  # noqa: E402
    FoundGrid,
    ImageScore,
    corner_rms,
    grid_is_plausible,
    percentile,
    score_image,
)
from edgecal.synth.truth import GroundTruth, load_ground_truth, truth_targets  # noqa: E402
from edgecal.targets import Board, Target, planar_target  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the sibling module, also when a test imports this file
from references import load_ocamcalib_json, load_opencv_corners_dat  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
DEFAULT_DATA = Path(os.environ.get("EDGECAL_DATA", REPO.parent / "shared" / "data"))

SYNTHETIC_SETS = ("planar", "hard", "multi", "box_stereo", "negatives")

#: Real photographs: board size (inner corners cols x rows, from each folder's SOURCE.md) and where
#: reference corners come from. None: several boards of sizes SOURCE.md does not give; only counted.
REAL_SETS: dict[str, dict] = {
    "opencv_stereo_9x6": {"board": (9, 6)},
    "opencv_testdata_chess1": {"board": (5, 7), "reference": "chess_corners1.dat"},
    "ocamcalib_scaramuzza_fisheye190": {"board": (6, 7), "reference": "Fisheye190Pts.json"},
    "ocamcalib_urban_fisheye1": {"board": (6, 8)},
    "libcbdetect_examples": {"board": None},
    "ortho3_box_stereo": {"board": None},
}

#: A call slower than this (ms) is not repeated (the checkerboard package takes seconds per image).
SLOW_CALL_MS = 1000.0

#: What a call's time is measured with (--clock): elapsed time, or the CPU time of this process (every
#: detector runs in it, single thread). On a machine shared with other work the elapsed time includes the
#: waits for a core, which hit detectors unevenly; the CPU time leaves them out (not the cache and memory
#: contention).
CLOCKS: dict[str, Callable[[], float]] = {"wall": time.perf_counter, "cpu": time.process_time}

#: The target used on synthetic negatives (no board in the scene): the planar set's board.
NEGATIVE_BOARD = (9, 6)


# ----------------------------------------------------------------------------------------------------
# Data


@dataclass
class Item:
    """One image of a set: the grey image, the target to look for, and what is known about it.

    ``truth`` is exact ground truth or reference corners (None if unknown); ``expect`` the board size
    whose detection is checked for plausibility when there is no truth.
    """

    name: str
    grey: np.ndarray
    target: Target | None
    truth: GroundTruth | None
    expect: tuple[int, int] | None = None


@dataclass
class BenchSet:
    """A named list of items; ``timing_only`` sets print times only."""

    name: str
    items: list[Item]
    note: str = ""
    timing_only: bool = False
    count_only: bool = False


def _target_from_boards(boards: list[dict], name: str) -> Target | None:
    """A Target from the ``target.boards`` list of a ground-truth document (None when it is empty)."""
    out = []
    for i, b in enumerate(boards):
        out.append(Board(str(b.get("name", f"board{i}")), int(b["cols"]), int(b["rows"]),
                         float(b.get("square_mm", 1.0)),
                         np.asarray(b.get("origin_mm", [0, 0, 0]), dtype=float),
                         np.asarray(b.get("x_axis", [1, 0, 0]), dtype=float),
                         np.asarray(b.get("y_axis", [0, 1, 0]), dtype=float)))
    return Target(name, tuple(out), name) if out else None


def _target_from_truth_json(path: Path) -> Target | None:
    return _target_from_boards(truth_targets(path), path.stem)


def synthetic_set(root: Path, name: str) -> BenchSet | None:
    """A folder of the renderer's PNG + ground-truth JSON pairs (stereo pair files are skipped)."""
    folder = root / "synthetic" / name
    if not folder.is_dir():
        return None
    items = []
    for png in sorted(folder.glob("*.png")):
        js = png.with_suffix(".json")
        if not js.is_file():
            continue
        truth = load_ground_truth(js)
        target = _target_from_truth_json(js) or planar_target(*NEGATIVE_BOARD)
        items.append(Item(png.name, load_grey(png), target, truth))
    return BenchSet(f"synthetic/{name}", items) if items else None


def real_set(root: Path, name: str) -> BenchSet | None:
    """A folder of real photographs, with the board size of REAL_SETS and reference corners if any."""
    folder = root / "real" / name
    spec = REAL_SETS[name]
    if not folder.is_dir():
        return None
    files = sorted(f for f in folder.iterdir() if f.suffix.lower() in IMAGE_SUFFIXES)
    refs: dict[str, GroundTruth] = {}
    ref_name = spec.get("reference")
    if ref_name and (folder / ref_name).is_file():
        if ref_name.endswith(".dat"):
            img = files[0]
            grey = load_grey(img)
            cols, rows = spec["board"]
            refs[img.name] = load_opencv_corners_dat(folder / ref_name, img.name,
                                                     (grey.shape[1], grey.shape[0]), cols, rows)
        else:
            refs = load_ocamcalib_json(folder / ref_name)
    board = spec["board"]
    items = []
    for f in files:
        grey = load_grey(f)
        target = planar_target(*board) if board else None
        truth = refs.get(f.name)
        if truth is not None and target is not None:
            # the reference board is the target's board: same name, so names are not scored as wrong
            named = tuple(dataclasses.replace(tb, name=target.boards[0].name) for tb in truth.boards)
            truth = dataclasses.replace(truth, boards=named)
        items.append(Item(f.name, grey, target, truth, expect=board))
    note = ""
    if refs:
        note = f"reference corners for {len(refs)} of {len(items)} images (not exact truth)"
    if board is None:
        note = "several boards of unknown size: boards reported are counted, nothing is scored"
    return BenchSet(f"real/{name}", items, note, count_only=board is None) if items else None


def timing_set(sets: list[BenchSet], size: tuple[int, int] = (1280, 800)) -> BenchSet | None:
    """All loaded images of ``size`` with a target: the speed target's frames."""
    items = [it for s in sets if not s.timing_only for it in s.items
             if it.target is not None and (it.grey.shape[1], it.grey.shape[0]) == size]
    if not items:
        return None
    return BenchSet(f"timing/{size[0]}x{size[1]}", items, "timing only: the images above of that size",
                    timing_only=True)


#: Scale sweep: nominal square size (px) -> board (inner corners) that still fits a 1280x800 frame.
SWEEP = {8: (9, 6), 12: (9, 6), 20: (9, 6), 35: (9, 6), 60: (9, 6), 100: (6, 4), 150: (4, 3)}
RENDER_SIZE = (1280, 800)
FISHEYE_RENDER_SIZE = (752, 480)


def rendered_sets(wanted: Callable[[str], bool], per_set: int = 4, seed: int = 2026) -> list[BenchSet]:
    """Sets rendered on the fly by edgecal.synth: a scale sweep, clean renders and wide-lens views.

    ``rendered/scale_NNNpx`` (1280x800): one board, squares of NNN px nominal (the board shrinks for the big
    squares), tilt up to 40 degrees, typical camera photometry and clutter. ``rendered/clean`` (1280x800):
    sharp, faintly noisy renders (the corner RMS target). ``rendered/fisheye`` (752x480, the 190-degree
    set's size; 3 x ``per_set`` views): a 6x7 board through a 150-200 degree Kannala-Brandt lens, tilt up to
    50 degrees, often reaching the lens's rim. Deterministic seeds; only wanted sets are rendered.
    """
    try:
        from edgecal.synth.scenes import planar_view
        from edgecal.synth.truth import ground_truth_from_mapping
    except ImportError as exc:
        print(f"# rendered sets skipped: edgecal.synth not importable ({exc})", file=sys.stderr)
        return []
    # (name, square px, board, photometry, tilt, lens, size, views)
    specs = [(f"rendered/scale_{sq:03d}px", sq, board, "normal", 40.0, "mild", RENDER_SIZE, per_set)
             for sq, board in SWEEP.items()]
    specs.append(("rendered/clean", (15.0, 45.0), (9, 6), "clean", 40.0, "mild", RENDER_SIZE, per_set))
    specs.append(("rendered/fisheye", (40.0, 90.0), (6, 7), "normal", 50.0, "fisheye", FISHEYE_RENDER_SIZE,
                  3 * per_set))
    sets = []
    for name, square_px, (cols, rows), phot, tilt, lens, size, count in specs:
        if not wanted(name):
            continue
        t0 = time.perf_counter()
        items: list[Item] = []
        k = -1
        while len(items) < count:
            k += 1
            if k >= 20 * count:  # (no view of these seeds holds the board: say so instead of looping on)
                print(f"# {name}: only {len(items)} of {count} views hold the board", file=sys.stderr)
                break
            try:
                view = planar_view((seed, zlib.crc32(name.encode()) % 10_000, k), size=size, cols=cols, rows=rows,
                                   square_px=square_px, tilt_max_deg=tilt, photometric=phot, distortion=lens)
            except ValueError:  # a board of these squares does not fit this view: the next seed
                continue
            if not view.truth["boards"]:  # (a wide lens's view can leave the board behind the camera)
                continue
            truth = ground_truth_from_mapping(view.truth, f"{name}#{k}")
            target = _target_from_boards(view.truth["target"]["boards"], f"{cols}x{rows}")
            items.append(Item(f"{name.split('/')[1]}_{k}", view.image, target, truth))
        what = f"{square_px} px squares" if isinstance(square_px, int) else \
            f"{square_px[0]:.0f}-{square_px[1]:.0f} px squares"
        lens_note = ", 150-200 deg fisheye" if lens == "fisheye" else ""
        sets.append(BenchSet(name, items, f"{cols}x{rows}, {what}{lens_note}, {phot} photometry, rendered in "
                                          f"{time.perf_counter() - t0:.1f} s"))
    return sets


# ----------------------------------------------------------------------------------------------------
# Detectors


def _distinct_sizes(target: Target) -> list[tuple[int, int]]:
    sizes: list[tuple[int, int]] = []
    for b in target.boards:
        if (b.cols, b.rows) not in sizes:
            sizes.append((b.cols, b.rows))
    return sizes


def _row_major_ids(cols: int, rows: int) -> np.ndarray:
    k = np.arange(cols * rows)
    return np.stack([k % cols, k // cols], axis=1).astype(np.int64)


def _subpix_half_window(corners: np.ndarray) -> int:
    """cornerSubPix half window from the corner spacing (the usual fixed 11 swallows small squares)."""
    d = np.linalg.norm(corners[:, None] - corners[None], axis=2)
    np.fill_diagonal(d, np.inf)
    spacing = float(np.percentile(d.min(axis=1), 10))
    return int(np.clip(spacing * 0.5, 2, 11))


_SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.01)


def detect_opencv(grey: np.ndarray, target: Target) -> tuple[list[FoundGrid], int]:
    """cv2.findChessboardCorners (adaptive threshold, normalise) + cornerSubPix, once per board size."""
    out = []
    for cols, rows in _distinct_sizes(target):
        ok, c = cv2.findChessboardCorners(grey, (cols, rows),
                                          cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
        if not ok:
            continue
        w = _subpix_half_window(c.reshape(-1, 2))
        c = cv2.cornerSubPix(grey, c, (w, w), (-1, -1), _SUBPIX_CRITERIA)
        out.append(FoundGrid(c.reshape(-1, 2).astype(np.float64), _row_major_ids(cols, rows), (cols, rows)))
    return out, len(out)


def detect_opencv_sb(grey: np.ndarray, target: Target) -> tuple[list[FoundGrid], int]:
    """cv2.findChessboardCornersSB (exhaustive, accuracy), once per board size."""
    out = []
    for cols, rows in _distinct_sizes(target):
        ok, c = cv2.findChessboardCornersSB(grey, (cols, rows),
                                            cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY)
        if ok:
            out.append(FoundGrid(c.reshape(-1, 2).astype(np.float64), _row_major_ids(cols, rows),
                                 (cols, rows)))
    return out, len(out)


def make_libcbdetect() -> Callable:
    """The PyPI ``libcbdetect`` binding (module libCBDetect): size-free, one board's corners per call."""
    import libCBDetect

    def detect(grey: np.ndarray, target: Target | None) -> tuple[list[FoundGrid], int]:
        h, w = grey.shape
        cb = libCBDetect.Checkerboard()
        cb.show_processing = False
        cb.array_norm_to_image(grey.astype(np.float64).ravel() / 255.0, h, w)
        cb.find_corners()
        cb.find_board_from_corners()
        rows, cols = int(cb.rows), int(cb.cols)
        if rows * cols == 0:
            return [], 0
        # number_of_boards reads one less than the boards found (the index of the last one);
        # rows/cols and get_board_corners describe that last board only
        reported = int(cb.number_of_boards) + 1
        u, v = np.zeros(rows * cols), np.zeros(rows * cols)
        cb.get_board_corners(u, v)
        xy = np.stack([u, v], axis=1)
        ok = np.isfinite(xy).all(axis=1) & (xy > 0).all(axis=1)
        # listed row by row, `cols` corners per row
        return [FoundGrid(xy[ok], _row_major_ids(cols, rows)[ok], (cols, rows), bool(ok.all()))], reported

    return detect


def make_checkerboard() -> Callable:
    """The PyPI ``checkerboard`` package (detect_checkerboard), once per board size."""
    from checkerboard import detect_checkerboard

    def detect(grey: np.ndarray, target: Target) -> tuple[list[FoundGrid], int]:
        out = []
        for cols, rows in _distinct_sizes(target):
            c, _score = detect_checkerboard(grey, (cols, rows))
            if c is None:
                continue
            k = np.arange(cols * rows)
            # its grid is indexed [col][row]: the row index runs fastest
            ids = np.stack([k // rows, k % rows], axis=1).astype(np.int64)
            out.append(FoundGrid(np.asarray(c, dtype=np.float64).reshape(-1, 2), ids, (cols, rows)))
        return out, len(out)

    return detect


def make_calib_targets() -> Callable:
    """The PyPI ``calib-targets`` package (Rust; ChESS corners + grid growing): ``detect_chessboard_all``
    needs no board size and returns every chessboard component it recovers; a component counts when its
    grid is complete and has the size of one of the target's boards (either way round)."""
    import calib_targets

    def detect(grey: np.ndarray, target: Target) -> tuple[list[FoundGrid], int]:
        sizes = {frozenset(s) for s in _distinct_sizes(target)}
        out = []
        for res in calib_targets.detect_chessboard_all(np.ascontiguousarray(grey)):
            if not res.corners:
                continue
            xy = np.array([c.position for c in res.corners], dtype=np.float64)
            uv = np.array([(c.grid.u, c.grid.v) for c in res.corners], dtype=np.int64)
            uv -= uv.min(axis=0)
            span = tuple(int(s) for s in uv.max(axis=0) + 1)
            if frozenset(span) not in sizes or len(uv) != span[0] * span[1]:
                continue
            out.append(FoundGrid(xy, uv, span))
        return out, len(out)

    return detect


def make_edgecal(refiner: str | None = None) -> Callable:
    """edgecal.detect(image, target) -> list[Detection]; ``refiner`` overrides DetectorParams.subpixel_refiner
    (the refiners side by side on the same images)."""
    from edgecal import detect as edgecal_detect
    from edgecal.detection.params import DetectorParams
    params = DetectorParams(subpixel_refiner=refiner) if refiner else None

    def detect(grey: np.ndarray, target: Target) -> tuple[list[FoundGrid], int]:
        dets = edgecal_detect(grey, target, params)
        out = [FoundGrid(np.asarray(d.corners, dtype=np.float64).reshape(-1, 2),
                         np.asarray(d.ids, dtype=np.int64).reshape(-1, 2),
                         (int(d.grid[0]), int(d.grid[1])), bool(d.complete), str(d.board)) for d in dets]
        return out, len(out)

    return detect


@dataclass
class Detector:
    """A detector under test: ``run(grey, target) -> (found grids, boards reported)``."""

    name: str
    run: Callable | None
    policy: str  # scoring policy of edgecal.scoring
    needs_target: bool = True
    status: str = "ok"
    warmup_ms: float = float("nan")


DETECTOR_NAMES = ("edgecal", "edgecal_csp", "opencv", "opencv_sb", "libcbdetect", "checkerboard", "calib_targets")


def load_detectors(names: list[str]) -> list[Detector]:
    """Build the selected detectors; one that fails to import is kept with its reason and not run."""
    makers: dict[str, tuple[Callable[[], Callable], str, bool]] = {
        "edgecal": (make_edgecal, "board", True),
        # edgecal with cornerSubPix alone as its final refiner (the default adds the saddle fit)
        "edgecal_csp": (lambda: make_edgecal("cornersubpix"), "board", True),
        "opencv": (lambda: detect_opencv, "grid", True),
        "opencv_sb": (lambda: detect_opencv_sb, "grid", True),
        "libcbdetect": (make_libcbdetect, "grid", False),
        "checkerboard": (make_checkerboard, "grid", True),
        "calib_targets": (make_calib_targets, "grid", True),
    }
    out = []
    for name in names:
        make, policy, needs_target = makers[name]
        try:
            out.append(Detector(name, make(), policy, needs_target))
        except Exception as exc:  # an optional package missing or broken: say so and go on
            out.append(Detector(name, None, policy, needs_target,
                                status=f"unavailable ({type(exc).__name__}: {exc})"))
    return out


# ----------------------------------------------------------------------------------------------------
# Running and scoring


@dataclass
class ImageResult:
    """One detector on one image."""

    image: str
    ms: float
    reported: int
    score: ImageScore | None
    plausible: bool | None = None
    error: str = ""
    grids: list[tuple[int, int]] = field(default_factory=list)


@dataclass
class SetResult:
    """One detector on one set."""

    detector: str
    images: list[ImageResult] = field(default_factory=list)

    def summary(self) -> dict:
        """Aggregates: found/total boards, false boards, RMS, median/p90 ms, errors."""
        ms = [r.ms for r in self.images if not r.error]
        scored = [r.score for r in self.images if r.score is not None]
        n_truth = sum(s.n_truth for s in scored)
        n_found = sum(s.n_found for s in scored)
        plaus = [r.plausible for r in self.images if r.plausible is not None]
        errs = [s.found_errors() for s in scored]
        errs = np.concatenate(errs) if errs else np.zeros(0)
        return {
            "images": len(self.images),
            "truth_boards": n_truth + len(plaus),
            "found": n_found + sum(plaus),
            "false_boards": sum(s.false_boards for s in scored),
            "partial": sum(s.partial for s in scored),
            "misnamed": sum(s.misnamed for s in scored),
            "reported_boards": sum(r.reported for r in self.images),
            "rms_px": corner_rms(errs),
            "corners_scored": int(errs.size),
            "median_ms": percentile(ms, 50),
            "p90_ms": percentile(ms, 90),
            "errors": sum(1 for r in self.images if r.error),
        }


def common_rms(a: SetResult, b: SetResult) -> tuple[float, float, int]:
    """Corner RMS of ``a`` and of ``b`` over the truth boards both found (a fair accuracy comparison).

    Returns (rms of a, rms of b, number of boards in common).
    """
    by_name = {r.image: r for r in b.images}
    ea: list[np.ndarray] = []
    eb: list[np.ndarray] = []
    for ra in a.images:
        rb = by_name.get(ra.image)
        if ra.score is None or rb is None or rb.score is None:
            continue
        for ma, mb in zip(ra.score.matches, rb.score.matches):
            if ma is not None and mb is not None and ma.found and mb.found:
                ea.append(ma.errors[ma.correct])
                eb.append(mb.errors[mb.correct])
    if not ea:
        return float("nan"), float("nan"), 0
    return corner_rms(np.concatenate(ea)), corner_rms(np.concatenate(eb)), len(ea)


def run_one(det: Detector, item: Item, repeat: int, clock: Callable[[], float] = time.perf_counter) -> ImageResult:
    """Time ``det`` on one image (median of ``repeat`` calls, ``clock`` one of CLOCKS) and score its last
    result."""
    target = item.target
    times = []
    found: list[FoundGrid] = []
    reported = 0
    try:
        for _ in range(max(1, repeat)):
            t0 = clock()
            found, reported = det.run(item.grey, target)
            times.append((clock() - t0) * 1e3)
            if times[-1] > SLOW_CALL_MS:
                break  # seconds per call: repeating adds run time, not information
    except Exception as exc:  # a crash in one detector is a result, not the end of the run
        return ImageResult(item.name, float("nan"), 0, None, error=f"{type(exc).__name__}: {exc}")
    ms = float(np.median(times))
    grids = [tuple(int(v) for v in f.grid) for f in found]
    if item.truth is not None:
        return ImageResult(item.name, ms, reported, score_image(found, item.truth, det.policy), grids=grids)
    if item.expect is not None:
        cols, rows = item.expect
        ok = any(grid_is_plausible(f) and sorted(f.grid) == sorted((cols, rows)) for f in found)
        return ImageResult(item.name, ms, reported, None, plausible=ok, grids=grids)
    return ImageResult(item.name, ms, reported, None, grids=grids)


def warm_up(detectors: list[Detector], item: Item) -> None:
    """First call of each detector (JIT compilation, caches): timed here and left out of the tables."""
    for det in detectors:
        if det.run is None:
            continue
        t0 = time.perf_counter()
        try:
            det.run(item.grey, item.target)
        except Exception as exc:
            det.status = f"failed on warm-up: {type(exc).__name__}: {exc}"
            traceback.print_exc(file=sys.stderr)
            det.run = None
            continue
        det.warmup_ms = (time.perf_counter() - t0) * 1e3
        if det.name.startswith("edgecal") and item.target is not None:
            # once more on a board with cut outer squares: the rim refinement's kernels (not timed here)
            from edgecal.stream.frame_pipeline import warm_up_image
            board = item.target.boards[0]
            det.run(warm_up_image((640, 480), board.cols, board.rows), item.target)


def run_set(bset: BenchSet, detectors: list[Detector], repeat: int,
            done: dict[tuple[int, str], ImageResult],
            clock: Callable[[], float] = time.perf_counter) -> dict[str, SetResult]:
    """Every detector on every image, interleaved image by image (drift of a shared machine hits all).

    ``done`` holds results by (id of the item, detector): an image already run in another set (the
    timing set reuses the others' frames) is not run again. Detectors that need a board size skip
    images without one.
    """
    results = {d.name: SetResult(d.name) for d in detectors if d.run is not None}
    for item in bset.items:
        for det in detectors:
            if det.run is None or (det.needs_target and item.target is None):
                continue
            key = (id(item), det.name)
            if key not in done:
                done[key] = run_one(det, item, repeat, clock)
            results[det.name].images.append(done[key])
    return results


# ----------------------------------------------------------------------------------------------------
# Report


def _fmt(v: float, digits: int = 1) -> str:
    return "-" if v is None or (isinstance(v, float) and not np.isfinite(v)) else f"{v:.{digits}f}"


def _ratio(v: float, ref: float) -> str:
    if not (np.isfinite(v) and np.isfinite(ref)) or ref <= 0:
        return "-"
    return f"{v / ref:.2f}x"


def format_table(bset: BenchSet, results: dict[str, SetResult]) -> str:
    """The table of one set: one line per detector, ratios against edgecal when it ran."""
    sums = {name: r.summary() for name, r in results.items()}
    base = sums.get("edgecal")
    lines = [f"## {bset.name}  ({len(bset.items)} images{'; ' + bset.note if bset.note else ''})"]
    if bset.timing_only:
        lines.append(f"{'detector':<13} {'median ms':>10} {'p90 ms':>9} {'ms/edgecal':>11}")
    else:
        lines.append(f"{'detector':<13} {'found':>9} {'rate':>6} {'false':>6} {'part':>4} {'reported':>8} "
                     f"{'rms px':>7} {'rms/edg*':>8} {'median ms':>10} {'p90 ms':>9} {'ms/edgecal':>11}")
    if bset.timing_only and base and "opencv_sb" in sums and "opencv" in sums:
        sb = sums["opencv_sb"]["median_ms"] / base["median_ms"]
        cl = sums["opencv"]["median_ms"] / base["median_ms"]
        lines.insert(1, f"speed targets (issue 12): findChessboardCornersSB / edgecal >= 10: {sb:.2f} "
                        f"({'met' if sb >= 10 else 'NOT met'}); findChessboardCorners / edgecal >= 1: "
                        f"{cl:.2f} ({'met' if cl >= 1 else 'NOT met'})")
    elif base and "opencv" in sums and not bset.count_only and base["images"] and not base["truth_boards"]:
        cl = sums["opencv"]["median_ms"] / base["median_ms"]
        lines.insert(1, f"speed target (issue 12) without a board: findChessboardCorners / edgecal >= 20: "
                        f"{cl:.2f} ({'met' if cl >= 20 else 'NOT met'})")
    for name, s in sums.items():
        if s["images"] == 0:
            lines.append(f"{name:<13} (not run: needs a board size)")
            continue
        ms_ratio = _ratio(s["median_ms"], base["median_ms"]) if base else "-"
        if bset.timing_only:
            lines.append(f"{name:<13} {_fmt(s['median_ms']):>10} {_fmt(s['p90_ms']):>9} {ms_ratio:>11}")
            continue
        total = s["truth_boards"]
        found = f"{s['found']}/{total}" if total else "-"
        rate = f"{100 * s['found'] / total:.0f}%" if total else "-"
        # accuracy ratio over the boards both found, not over each one's own (easier or harder) subset
        rms_ratio = "-"
        if base and name != "edgecal":
            ra, rb, _n = common_rms(results[name], results["edgecal"])
            rms_ratio = _ratio(ra, rb)
        elif base:
            rms_ratio = "1.00x"
        err = f"  ({s['errors']} errors)" if s["errors"] else ""
        if s["misnamed"]:
            err += f"  ({s['misnamed']} found boards given another board's name)"
        lines.append(f"{name:<13} {found:>9} {rate:>6} {s['false_boards']:>6} {s['partial']:>4} "
                     f"{s['reported_boards']:>8} {_fmt(s['rms_px'], 3):>7} {rms_ratio:>8} "
                     f"{_fmt(s['median_ms']):>10} {_fmt(s['p90_ms']):>9} {ms_ratio:>11}{err}")
    return "\n".join(lines)


def format_markdown(all_results: list[tuple[BenchSet, dict[str, SetResult]]], detectors: list[str]) -> str:
    """Two Markdown tables for the README: detection (found, false, RMS) and speed (median ms, ratio)."""
    head = "| set | images | " + " | ".join(detectors) + " |"
    rule = "|---|---:|" + "---:|" * len(detectors)
    refs = [n for n in detectors if n != "edgecal"]
    acc_head = "| set | " + " | ".join(refs) + " |"
    acc_rule = "|---|" + "---:|" * len(refs)
    found_rows, speed_rows, acc_rows = [], [], []
    for bset, results in all_results:
        if "edgecal" in results and not bset.timing_only:
            cells = []
            for n in refs:
                ra, rb, k = common_rms(results[n], results["edgecal"]) if n in results else (0, 0, 0)
                cells.append(f"{ra:.3f} / {rb:.3f} ({k})" if k else "-")
            if any(c != "-" for c in cells):
                acc_rows.append(f"| {bset.name} | " + " | ".join(cells) + " |")
        sums = {n: r.summary() for n, r in results.items()}
        base = sums.get("edgecal")
        found_cells, speed_cells = [], []
        for n in detectors:
            s = sums.get(n)
            if s is None or s["images"] == 0:
                found_cells.append("n/a")
                speed_cells.append("n/a")
                continue
            ratio = _ratio(s["median_ms"], base["median_ms"]) if base and base["images"] else "-"
            ms = _fmt(s["median_ms"], 0)
            speed_cells.append(ms if ratio == "-" else f"{ms} ({ratio.replace('x', '×')})")
            parts = []
            if s["truth_boards"]:
                parts.append(f"{s['found']}/{s['truth_boards']}")
            if bset.count_only:
                parts.append(f"{s['reported_boards']} reported")
            if np.isfinite(s["rms_px"]):
                parts.append(f"{s['rms_px']:.3f} px")
            if s["false_boards"] or (not s["truth_boards"] and not bset.count_only):
                parts.append(f"{s['false_boards']} false")
            if s["misnamed"]:
                parts.append(f"{s['misnamed']} misnamed")
            found_cells.append(" · ".join(parts))
        if not bset.timing_only:
            found_rows.append(f"| {bset.name} | {len(bset.items)} | " + " | ".join(found_cells) + " |")
        speed_rows.append(f"| {bset.name} | {len(bset.items)} | " + " | ".join(speed_cells) + " |")
    return "\n".join(["Boards found with all corners correctly ordered / boards · corner RMS over found boards"
                      " · false boards:", "", head, rule, *found_rows, "",
                      "Corner RMS over the boards both found, reference px / edgecal px (boards):", "",
                      acc_head, acc_rule, *acc_rows, "",
                      "Median ms per image (ratio to edgecal; above 1× means slower than edgecal):", "",
                      head, rule, *speed_rows, ""])


def machine_line() -> str:
    """Where the numbers were taken."""
    return (f"{platform.node()} {platform.machine()}, {os.cpu_count()} cores (shared), "
            f"Python {platform.python_version()}, OpenCV {cv2.__version__} (threads {cv2.getNumThreads()}), "
            f"numpy {np.__version__}, NUMBA_NUM_THREADS={os.environ.get('NUMBA_NUM_THREADS', 'unset')}")


def write_json_atomic(path: Path, data: dict, force: bool) -> None:
    """Write ``data`` to ``path`` via a temp file in the same folder; refuse to overwrite unless force."""
    write_text_atomic(path, json.dumps(data, indent=1, default=float), force)


def write_text_atomic(path: Path, text: str, force: bool) -> None:
    """Write ``text`` to ``path`` atomically with the umask's permissions; refuse to overwrite unless force."""
    if path.exists() and not force:
        raise EdgecalError(f"{path}: exists; pass --force to overwrite it")
    write_atomic(path, text.encode("utf-8"))


def _json_safe(v: object) -> object:
    if isinstance(v, float) and not np.isfinite(v):
        return None
    return v


def result_json(bset: BenchSet, results: dict[str, SetResult]) -> dict:
    """Summary and per-image records of one set."""
    out: dict = {"images": len(bset.items), "note": bset.note, "timing_only": bset.timing_only,
                 "detectors": {}}
    for name, r in results.items():
        per_image = []
        for ir in r.images:
            rec: dict = {"image": ir.image, "ms": _json_safe(ir.ms), "reported": ir.reported,
                         "grids": [list(g) for g in ir.grids]}
            if ir.score is not None:
                rec.update(truth=ir.score.n_truth, found=ir.score.n_found, false=ir.score.false_boards,
                           partial=ir.score.partial, misnamed=ir.score.misnamed,
                           rms_px=_json_safe(corner_rms(ir.score.found_errors())))
            if ir.plausible is not None:
                rec["plausible"] = ir.plausible
            if ir.error:
                rec["error"] = ir.error
            per_image.append(rec)
        out["detectors"][name] = {"summary": {k: _json_safe(v) for k, v in r.summary().items()},
                                  "per_image": per_image}
    return out


# ----------------------------------------------------------------------------------------------------
# Main


def select_sets(root: Path, patterns: list[str]) -> list[BenchSet]:
    """Load the sets whose names match any of ``patterns`` (fnmatch; a bare name matches its tail)."""
    names = [f"synthetic/{n}" for n in SYNTHETIC_SETS] + [f"real/{n}" for n in REAL_SETS]
    # rendered/* sets are made by edgecal.synth and need no shared data

    def wanted(name: str) -> bool:
        return any(fnmatch.fnmatch(name, p) or fnmatch.fnmatch(name.split("/", 1)[1], p) for p in patterns)

    sets: list[BenchSet] = []
    for name in names:
        if not wanted(name):
            continue
        kind, short = name.split("/", 1)
        s = synthetic_set(root, short) if kind == "synthetic" else real_set(root, short)
        if s is None:
            print(f"# {name}: absent, skipped", file=sys.stderr)
            continue
        sets.append(s)
    sets.extend(rendered_sets(wanted))
    if any(fnmatch.fnmatch("timing/1280x800", p) or p == "timing" for p in patterns):
        # the frames come from the synthetic and rendered sets; ones not selected are loaded for it alone
        loaded = {x.name for x in sets}
        extra = [x for n in SYNTHETIC_SETS if f"synthetic/{n}" not in loaded
                 for x in [synthetic_set(root, n)] if x is not None]
        extra += rendered_sets(lambda n: n not in loaded)
        t = timing_set(sets + extra)
        if t is not None:
            sets.append(t)
    return sets


def with_added_noise(sets: list[BenchSet], sigma: float, seeds: int) -> list[BenchSet]:
    """The scored sets of ``sets`` with each image replaced by ``seeds`` copies with white noise of ``sigma``
    grey levels added (rounded, clipped to 8 bits; copy k from seed k): how a result holds when the image
    changes by what a sensor's noise changes between two shots. Timing sets are left out."""
    out = []
    for bset in sets:
        if bset.timing_only:
            continue
        items = []
        for k in range(seeds):
            rng = np.random.default_rng([k, zlib.crc32(bset.name.encode())])
            for it in bset.items:
                noisy = it.grey.astype(np.float32) + rng.normal(0.0, sigma, it.grey.shape).astype(np.float32)
                items.append(dataclasses.replace(it, name=f"{it.name}~{k}",
                                                 grey=np.clip(np.rint(noisy), 0, 255).astype(np.uint8)))
        out.append(dataclasses.replace(bset, name=f"{bset.name} +noise {sigma:g}", items=items,
                                       note=f"{seeds} noisy copies of each image; {bset.note}".rstrip("; ")))
    return out


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark; returns the exit code."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sets", default="*",
                    help="comma-separated set names or patterns (e.g. planar,real/*,timing); default all")
    ap.add_argument("--detectors", default=",".join(DETECTOR_NAMES),
                    help=f"comma-separated subset of {','.join(DETECTOR_NAMES)}")
    ap.add_argument("--repeat", type=int, default=1, help="timed calls per image (the median is kept)")
    ap.add_argument("--clock", choices=tuple(CLOCKS), default="wall",
                    help="time calls by elapsed time (wall, default) or by this process's CPU time (cpu: "
                         "steadier on a shared machine)")
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA, help="folder holding synthetic/ and real/")
    ap.add_argument("--json", type=Path, help="also write all results to this JSON file")
    ap.add_argument("--markdown", type=Path, help="also write the README tables (Markdown) to this file")
    ap.add_argument("--force", action="store_true", help="overwrite the --json/--markdown files if they exist")
    ap.add_argument("--noise", type=float, default=0.0, metavar="SIGMA",
                    help="add white noise of SIGMA grey levels to every image (robustness; timing sets dropped)")
    ap.add_argument("--noise-copies", type=int, default=3, metavar="N",
                    help="with --noise: noisy copies of each image, each from its own seed (default 3)")
    args = ap.parse_args(argv)
    if not (0.0 <= args.noise <= 64.0) or args.noise_copies < 1:
        print(f"bench: --noise must be 0-64 grey levels and --noise-copies at least 1 (got {args.noise:g}, "
              f"{args.noise_copies})", file=sys.stderr)
        return 2
    cv2.setNumThreads(1)

    names = [n.strip() for n in args.detectors.split(",") if n.strip()]
    unknown = [n for n in names if n not in DETECTOR_NAMES]
    if unknown:
        print(f"bench: unknown detector(s) {', '.join(unknown)}; choose from {', '.join(DETECTOR_NAMES)}",
              file=sys.stderr)
        return 2
    for out in (args.json, args.markdown):
        if out and out.exists() and not args.force:
            print(f"bench: {out} exists; pass --force to overwrite it", file=sys.stderr)
            return 2
    patterns = [p.strip() for p in args.sets.split(",") if p.strip()]
    if "*" in patterns:
        patterns.append("timing/*")

    try:
        sets = select_sets(args.data, patterns)
    except EdgecalError as exc:
        print(f"bench: {exc}", file=sys.stderr)
        return 2
    if args.noise > 0.0:
        sets = with_added_noise(sets, args.noise, args.noise_copies)
    if not sets:
        print("bench: no set selected or present", file=sys.stderr)
        return 2
    detectors = load_detectors(names)
    first = next(it for s in sets for it in s.items if it.target is not None)
    warm_up(detectors, first)

    print(f"# detection benchmark — {machine_line()}")
    print(f"# repeat {args.repeat}; times are per image (all calls a detector needs for that image), "
          f"{'elapsed' if args.clock == 'wall' else 'CPU'} time (--clock {args.clock})")
    print("# found: boards with all corners found and correctly ordered / boards (real sets without"
          " reference corners: a plausible grid of the board's size); false: detections on no board;"
          " part: detections on a board that are not its complete match; reported: boards the"
          " detector reported; rms: over the found boards, against truth or reference corners;"
          " rms/edg*: both RMS taken over the boards both detectors found")
    for d in detectors:
        extra = f", warm-up (first call) {d.warmup_ms:.0f} ms" if np.isfinite(d.warmup_ms) else ""
        print(f"# {d.name}: {d.status}{extra}; scored as '{d.policy}'")
    report: dict = {"machine": machine_line(), "repeat": args.repeat, "clock": args.clock,
                    "detectors": {d.name: {"status": d.status, "warmup_ms": _json_safe(d.warmup_ms),
                                           "policy": d.policy} for d in detectors},
                    "sets": {}}
    done: dict[tuple[int, str], ImageResult] = {}
    all_results = []
    for bset in sets:
        results = run_set(bset, detectors, args.repeat, done, CLOCKS[args.clock])
        all_results.append((bset, results))
        print()
        print(format_table(bset, results), flush=True)
        report["sets"][bset.name] = result_json(bset, results)
    if args.json:
        write_json_atomic(args.json, report, args.force)
        print(f"\n# wrote {args.json}")
    if args.markdown:
        ran = [d.name for d in detectors if d.run is not None]
        text = f"Measured {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())} on {machine_line()}; " \
               f"--repeat {args.repeat} --clock {args.clock}.\n\n" + format_markdown(all_results, ran)
        write_text_atomic(args.markdown, text, args.force)
        print(f"# wrote {args.markdown}")
    return 0


if __name__ == "__main__":
    tune_allocator()  # as every edgecal command does (importing edgecal does not)
    sys.exit(main())
