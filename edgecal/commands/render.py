"""``edgecal render SCENE --out DIR``: render synthetic images with exact ground truth.

Scenes: planar, hard, partial (cut by the image border), occluded (a plate in front), multi, negative
(PNG + JSON per image), box (stereo pairs of the calibration box:
_L/_R images and a _pair.json), robot (a stereo sequence: left/, right/ and truth.json; --count frames).
The JSON is the "edgecal-synth-gt/1" format of docs/synth.md.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

from edgecal.commands.argtypes import positive_int
from edgecal.errors import InputError
from edgecal.fileio import check_outputs

SCENES = ("planar", "fisheye", "rational", "hard", "partial", "occluded", "multi", "negative", "box", "robot")


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT, e.g. 1280x800 (got {text!r})") from None
    if not (16 <= w <= 8192 and 16 <= h <= 8192):
        raise argparse.ArgumentTypeError(f"image size {w}x{h} is out of range (16..8192)")
    return w, h


def _square_px(text: str) -> tuple[float, float]:
    try:
        parts = [float(v) for v in text.split(":")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected PX or MIN:MAX, e.g. 30 or 8:150 (got {text!r})") from None
    if len(parts) not in (1, 2) or not all(math.isfinite(v) and v >= 2.0 for v in parts):
        raise argparse.ArgumentTypeError(f"expected PX or MIN:MAX with squares of at least 2 px (got {text!r})")
    return (parts[0], parts[-1])


def _board(text: str) -> tuple[int, int]:
    try:
        c, r = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected COLSxROWS inner corners, e.g. 9x6 (got {text!r})") from None
    if c < 2 or r < 2:
        raise argparse.ArgumentTypeError("a board needs at least 2x2 inner corners")
    return c, r


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register ``edgecal render``."""
    p = subparsers.add_parser("render", help="render synthetic chessboard images with exact ground truth",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scene", choices=SCENES, help="what to render")
    p.add_argument("--out", required=True, help="output folder (created if missing)")
    p.add_argument("--count", type=positive_int, default=1, help="images, pairs or frames to render (default 1)")
    p.add_argument("--seed", type=int, default=0, help="random seed; the same seed renders the same images")
    p.add_argument("--size", type=_size, default=None,
                   help="image size WIDTHxHEIGHT (default 640x480; box, robot and multi 1280x800)")
    p.add_argument("--square-px", type=_square_px, default=None,
                   help="square size in pixels, PX or MIN:MAX (all but negative, box and robot)")
    p.add_argument("--board", type=_board, default=(9, 6),
                   help="inner corners COLSxROWS (planar, hard, partial, occluded; default 9x6)")
    p.add_argument("--photometric", choices=("clean", "normal", "hard"), default=None,
                   help="photometric conditions (default: normal; robot: clean)")
    p.add_argument("--force", action="store_true", help="overwrite existing files")
    return p


def run(args: argparse.Namespace) -> int:
    """Render ``--count`` items of the scene into ``--out``."""
    from edgecal.synth import scenes, writer

    check_outputs([Path(args.out) / "truth.json"], force=True, create_folders=True)  # before rendering
    big = (1280, 800)
    size = args.size or (big if args.scene in ("box", "robot", "multi") else (640, 480))
    phot = args.photometric or ("clean" if args.scene == "robot" else "normal")
    t0 = time.perf_counter()
    if args.scene == "robot":
        rig = scenes.robot_rig(args.seed, size)
        frames = scenes.robot_sequence(args.seed, args.count, size=size, photometric=phot)
        n = writer.write_robot_sequence(args.out, frames, rig, scenes.robot_target(), 30.0, args.force)
        print(f"wrote {n} stereo frames to {args.out} ({time.perf_counter() - t0:.1f} s)", file=sys.stderr)
        return 0
    cols, rows = args.board
    for i in range(args.count):
        seed = (args.seed, i)
        stem = f"{args.scene}_{i:03d}"
        try:
            if args.scene in ("planar", "fisheye", "rational"):
                # fisheye / rational: the planar scene through a 150-200 deg Kannala-Brandt or a wide rational lens
                kw = {"square_px": args.square_px} if args.square_px else {}
                if args.scene != "planar":
                    kw["distortion"] = args.scene
                view = scenes.planar_view(seed, size=size, cols=cols, rows=rows, photometric=phot, **kw)
            elif args.scene == "hard":
                kw = {"square_px": args.square_px} if args.square_px else {}
                view = scenes.hard_view(seed, size=size, cols=cols, rows=rows, **kw)
            elif args.scene == "partial":
                kw = {"square_px": args.square_px} if args.square_px else {}
                view = scenes.partial_view(seed, size=size, cols=cols, rows=rows, photometric=phot, **kw)
            elif args.scene == "occluded":
                kw = {"square_px": args.square_px} if args.square_px else {}
                view = scenes.occluded_view(seed, size=size, cols=cols, rows=rows, photometric=phot, **kw)
            elif args.scene == "multi":
                kw = {"square_px": args.square_px} if args.square_px else {}
                view = scenes.multi_view(seed, size=size, photometric=phot, **kw)
            elif args.scene == "negative":
                view = scenes.negative_view(seed, size=size, photometric=phot)
            else:
                pair = scenes.box_stereo(seed, size=size, photometric=phot)
                writer.write_stereo(args.out, stem, pair, args.force)
                continue
        except ValueError as exc:
            # A scene that cannot be built from these options (e.g. a board too big for the image).
            raise InputError(f"render {args.scene}: {exc}") from None
        writer.write_view(args.out, stem, view, args.force)
    print(f"wrote {args.count} {args.scene} item(s) to {args.out} ({time.perf_counter() - t0:.1f} s)",
          file=sys.stderr)
    return 0
