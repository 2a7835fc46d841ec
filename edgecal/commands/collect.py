"""``edgecal collect SOURCE``: guided collection of calibration views from a camera, a stereo pair or a replay.

    edgecal collect stereo:aravis:A,aravis:B --board 9x6 --square-mm 30 --out views/
    edgecal collect replay:session/ --board 9x6 --square-mm 30 --out views/ --calibrate

Every frame is detected; a view is kept only when the board is found (in both images of a pair), sharp,
still, and not a near-duplicate of a view already kept (calibration/collection.py: ROS's X, Y, size and
skew measures). One line per kept view shows the four coverage bars and what is still missing; on a
terminal a status line counts frames. Collection stops when coverage is complete, at --max-views, at
the end of a replay, or on Ctrl-C; the kept views are an edgecal recording that ``edgecal calibrate
--left DIR`` reads directly.
"""

from __future__ import annotations

import argparse
import shlex
import sys
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from edgecal.calibration.assign import Assignment, assign, assign_stereo
from edgecal.calibration.collection import (
    MEASURES,
    STILL_PX,
    Coverage,
    board_found,
    edge_width_px,
    is_sharp,
    motion_px,
    square_px,
    view_measures,
)
from edgecal.calibration.types import CornerSet
from edgecal.calibration.views import corner_set
from edgecal.errors import ConfigError, InputError
from edgecal.images import as_grey
from edgecal.progress import Progress, bar
from edgecal.targets import Target, load_target, parse_board_spec

# Why frames were not kept, in the order they are checked (the summary counts them).
REASONS = ("no board", "blurred", "moving", "near-duplicate")


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register ``edgecal collect``."""
    p = sub.add_parser("collect", help="keep the calibration views a source shows that add coverage",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("source", metavar="SOURCE", help="source URI: a camera, stereo:A,B, or replay:DIR")
    what = p.add_mutually_exclusive_group(required=True)
    what.add_argument("--board", metavar="CxR", help="a flat board of C x R inner corners, e.g. 9x6")
    what.add_argument("--target", metavar="FILE.yaml", help="target file (configs/targets/...)")
    p.add_argument("--square-mm", type=float, help="square size in mm (with --board)")
    p.add_argument("--out", required=True, metavar="DIR", help="folder for the kept views (an edgecal recording)")
    p.add_argument("--max-views", type=int, metavar="N",
                   help="stop after N kept views (default: when coverage is complete; a box: 1)")
    p.add_argument("--calibrate", action="store_true",
                   help="run edgecal calibrate on the kept views at the end (DIR/rig.yaml, report in DIR/report)")
    p.add_argument("--force", action="store_true", help="replace a recording already in DIR")
    return p


@dataclass
class Decision:
    """What became of one frame: kept, or why not; the corners (per camera) and measures when found."""

    kept: bool
    reason: str
    corners: list[CornerSet]
    measures: np.ndarray | None = None


class Collector:
    """Decides frame by frame which views to keep; holds the previous frame's corners and the coverage."""

    def __init__(self, target: Target, n_cameras: int) -> None:
        self.target = target
        self.n_cameras = n_cameras
        self.coverage = Coverage(n_cameras)
        self.previous: list[CornerSet] | None = None

    def _corners(self, images: list[np.ndarray]) -> list[CornerSet]:
        from edgecal.detection.detector import detect
        dets = [detect(img, self.target) for img in images]
        empty = corner_set(self.target, [], np.zeros((0, 2)))
        found: tuple[Assignment | None, ...]
        if self.n_cameras == 2:
            found = assign_stereo(dets[0], dets[1], self.target)
        else:
            found = (assign(dets[0], self.target),)
        return [a.corners if a is not None else empty for a in found]

    def consider(self, images: list[np.ndarray]) -> Decision:
        """Detect in the frame's images (one per camera) and decide."""
        greys = [as_grey(img) for img in images]
        corners = self._corners(greys)
        previous, self.previous = self.previous, corners
        if not all(board_found(cs, self.target) for cs in corners):
            return Decision(False, "no board", corners)
        size = (greys[0].shape[1], greys[0].shape[0])
        found_measures = [view_measures(cs, self.target, size) for cs in corners]
        measures = [m for m in found_measures if m is not None]
        if len(measures) < len(found_measures):
            return Decision(False, "no board", corners)
        m = np.stack(measures)
        if not all(is_sharp(edge_width_px(g, cs, self.target), square_px(cs)) for g, cs in zip(greys, corners)):
            return Decision(False, "blurred", corners, m)
        if previous is None or any(motion_px(p, c) >= STILL_PX for p, c in zip(previous, corners)):
            return Decision(False, "moving", corners, m)
        if not self.coverage.adds(m):
            return Decision(False, "near-duplicate", corners, m)
        self.coverage.add(m)
        return Decision(True, "", corners, m)


def coverage_line(n: int, name: str, coverage: Coverage) -> str:
    """The line printed for a kept view: its number, the frame, the four bars, what is missing."""
    p = coverage.progress()
    bars = "  ".join(f"{m} {bar(v, 10)}" for m, v in zip(MEASURES, p))
    missing = coverage.missing()
    return f"kept {n:3d} ({name})  {bars}  " + ("coverage complete" if not missing else "next: " + ", ".join(missing))


def _target(args: argparse.Namespace) -> Target:
    if args.target:
        return load_target(args.target)
    if args.square_mm is None or args.square_mm <= 0:
        raise ConfigError("--board needs --square-mm S, the square size in millimetres (> 0)")
    return parse_board_spec(args.board, args.square_mm)


def calibrate_argv(args: argparse.Namespace, out: Path) -> list[str]:
    """The ``edgecal calibrate`` arguments for the collected views."""
    what = ["--target", args.target] if args.target else ["--board", args.board, "--square-mm", f"{args.square_mm:g}"]
    return ["calibrate", *what, "--left", str(out), "--out", str(out / "rig.yaml"), "--report", str(out / "report")]


def run(args: argparse.Namespace) -> int:
    """Collect until coverage is complete, --max-views, the end of the source, or Ctrl-C."""
    from edgecal.drivers import StereoFrame, open_source
    from edgecal.drivers.recording import Recorder
    target = _target(args)
    if args.max_views is not None and args.max_views < 1:
        raise InputError(f"--max-views must be at least 1 (got {args.max_views})")
    # A box calibrates from one shot: the first view that shows every face well is the one.
    max_views = args.max_views if args.max_views is not None else (None if target.is_planar else 1)
    out = Path(args.out)
    seen, kept = 0, 0
    why: Counter[str] = Counter()
    stop = "the source ended"
    with open_source(args.source) as src:
        recorder = Recorder(out, src.describe(), force=args.force)
        collector: Collector | None = None
        try:
            with Progress("collecting", None) as status:
                while True:
                    item = src.read()
                    if item is None:
                        break
                    seen += 1
                    images = [item.left.image, item.right.image] if isinstance(item, StereoFrame) else [item.image]
                    if collector is None:
                        collector = Collector(target, len(images))
                    d = collector.consider(images)
                    if not d.kept:
                        why[d.reason] += 1
                        status.update(seen, f"frames, {kept} kept; last: {d.reason}")
                        continue
                    recorder.add(item)
                    kept += 1
                    status.clear()
                    seq = item.left.seq if isinstance(item, StereoFrame) else item.seq
                    print(coverage_line(kept, f"frame {seq}", collector.coverage), flush=True)
                    if collector.coverage.complete and target.is_planar:
                        stop = "coverage is complete"
                        break
                    if max_views is not None and kept >= max_views:
                        stop = f"{kept} views were kept (--max-views)" if args.max_views else "the box view was kept"
                        break
        except KeyboardInterrupt:
            stop = "interrupted"
        finally:
            recorder.close()
    skipped = ", ".join(f"{why[r]} {r}" for r in REASONS if why[r])
    print(f"kept {kept} of {seen} frames ({skipped or 'none skipped'}) into {out}; stopped: {stop}", file=sys.stderr)
    if collector is not None and not collector.coverage.complete and target.is_planar:
        print("coverage is not complete: " + ", ".join(collector.coverage.missing()), file=sys.stderr)
    argv = calibrate_argv(args, out)
    if kept == 0:
        raise InputError(f"{args.source}: no view was kept ({skipped or 'no frames'}); show the whole board, "
                         "hold it still for a moment at each place")
    print("edgecal " + " ".join(shlex.quote(a) for a in argv), flush=True)
    if args.calibrate:
        from edgecal.cli import main as cli_main
        return cli_main(argv + (["--force"] if args.force else []))
    return 0
