"""``edgecal detect``: find chessboards in images and print one JSON line per image."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from edgecal.commands.argtypes import pixel_count, positive_float
from edgecal.detection.detector import detect_debug
from edgecal.detection.params import DEFAULT_PARAMS_FILE_HINT, DetectorParams, load_params
from edgecal.errors import EdgecalError
from edgecal.fileio import check_outputs, make_folders
from edgecal.images import DEFAULT_MAX_PIXELS, expand_image_args, load_grey
from edgecal.targets import Target, load_target, parse_board_spec


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register ``edgecal detect``."""
    p = sub.add_parser("detect", help="find chessboards in images (one JSON line per image)",
                       description="Find the target's chessboards in each image and print one JSON object "
                                   "per line: image, size, boards (name, copy, corners, ids), notes, ms.")
    what = p.add_mutually_exclusive_group(required=True)
    what.add_argument("--target", metavar="FILE.yaml", help="target file (configs/targets/...)")
    what.add_argument("--board", metavar="CxR", help="a flat board of C x R inner corners, e.g. 9x6")
    p.add_argument("--square-mm", type=positive_float, default=1.0, help="square size with --board (default 1)")
    p.add_argument("--max-pixels", type=pixel_count, default=DEFAULT_MAX_PIXELS, metavar="N",
                   help="refuse images of more pixels, from the header before decoding "
                        f"(default {DEFAULT_MAX_PIXELS} = 2^26)")
    p.add_argument("--params", metavar="FILE.yaml", help=f"detector thresholds ({DEFAULT_PARAMS_FILE_HINT})")
    p.add_argument("--draw", metavar="DIR", help="write an overlay PNG per image into DIR (board outline, first "
                                                 "corner and row direction, ids, name; 'not found' on a miss)")
    p.add_argument("--debug", action="store_true", help="with --draw: add the detector's layers (candidates, "
                                                        "accepted points, border directions)")
    p.add_argument("--force", action="store_true", help="overwrite existing overlays in --draw DIR")
    p.add_argument("images", nargs="+", metavar="IMAGE", help="image files or folders of images")
    return p


def _target(args: argparse.Namespace) -> Target:
    if args.target:
        return load_target(args.target)
    return parse_board_spec(args.board, args.square_mm)


def run(args: argparse.Namespace) -> int:
    """Detect in every image; a missing or unreadable image is reported and makes the exit code 2."""
    target = _target(args)
    params = load_params(args.params) if args.params else DetectorParams()
    draw_dir = Path(args.draw) if args.draw else None
    if draw_dir is not None:
        from edgecal.detection.draw import write_overlay  # only with --draw: drawing is not on the hot path
        check_outputs([draw_dir / "overlay.png"], force=True, create_folders=True)  # before the first image
        make_folders(draw_dir)
    failed = 0
    for path in expand_image_args(args.images):
        try:
            grey = load_grey(path, args.max_pixels)
        except EdgecalError as exc:
            print(f"edgecal: error: {exc}", file=sys.stderr)
            failed += 1
            continue
        t0 = time.perf_counter()
        debug = detect_debug(grey, target, params)
        ms = (time.perf_counter() - t0) * 1e3
        for note in debug.notes:
            print(f"edgecal: {path}: {note}", file=sys.stderr)
        record = {"image": str(path), "size": [int(grey.shape[1]), int(grey.shape[0])],
                  "boards": [d.as_json() for d in debug.detections], "notes": list(debug.notes),
                  "ms": round(ms, 2)}
        print(json.dumps(record), flush=True)
        if draw_dir is not None:
            write_overlay(draw_dir / (Path(path).stem + "_detect.png"), grey, debug, force=args.force,
                          show_debug=args.debug)
    return 2 if failed else 0
