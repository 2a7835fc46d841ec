"""``edgecal capture SOURCE``: grab frames, detect the target in each, print timestamps and findings.

The quickest check of a camera on a new robot: does it deliver, at what rate, with what timestamps,
and can the detector see the boards in its images.
"""

from __future__ import annotations

import argparse
import json
import time
from typing import Any

from edgecal.commands.argtypes import positive_int


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register ``edgecal capture``."""
    p = sub.add_parser("capture", help="grab frames, detect boards, print per-frame timestamps and findings",
                       description="Read frames from SOURCE (a URI, see docs/drivers.md), run the detector on "
                                   "each (with --target or --board) and print one line per frame: sequence, "
                                   "capture timestamp, interval, latency (receipt to print), age (capture to "
                                   "print, live cameras), size and the boards found.")
    p.add_argument("source", metavar="SOURCE", help="source URI, e.g. aravis:192.168.1.20 or replay:DIR")
    p.add_argument("--frames", type=positive_int, default=10, metavar="N",
                   help="frames (or pairs) to grab (default 10)")
    p.add_argument("--out", metavar="DIR", help="also record the frames into DIR (an edgecal recording)")
    p.add_argument("--force", action="store_true", help="replace a recording already in --out DIR")
    what = p.add_mutually_exclusive_group()
    what.add_argument("--target", metavar="FILE.yaml", help="target file to detect (configs/targets/...)")
    what.add_argument("--board", metavar="CxR", help="a flat board of C x R inner corners, e.g. 9x6")
    p.add_argument("--json", action="store_true", help="one JSON object per frame instead of text")
    return p


def _detect(image: Any, target: Any) -> tuple[list[dict], list[str]]:
    """The boards found in one frame (name, copy, corners found of the board's) and the detector's notes
    (e.g. a grid of another size than the target's)."""
    from edgecal.detection.detector import detect_debug
    from edgecal.images import as_grey
    found = []
    debug = detect_debug(as_grey(image), target)
    for d in debug.detections:
        found.append({"board": d.board, "copy": d.copy, "corners": int(len(d.corners)),
                      "of": target.board(d.board).n_corners, "complete": bool(d.complete)})
    return found, list(debug.notes)


def _describe_frame(f: Any, prev_stamp: int | None, now: int, target: Any, live: bool) -> dict:
    h, w = f.image.shape[:2]
    kind = "BGR" if f.image.ndim == 3 else "grey"
    out = {"camera": f.camera_id, "seq": f.seq, "stamp_ns": f.stamp_ns,
           "interval_ms": None if prev_stamp is None else round((f.stamp_ns - prev_stamp) / 1e6, 3),
           "latency_ms": round((now - f.recv_ns) / 1e6, 3), "size": f"{w}x{h}", "pixels": f"{kind} {f.image.dtype}"}
    if live:  # capture-to-delivery: the stamp is on this host's monotonic clock
        out["age_ms"] = round((now - f.stamp_ns) / 1e6, 3)
    if f.exposure_us is not None:
        out["exposure_us"] = f.exposure_us
    if target is not None:
        out["boards"], notes = _detect(f.image, target)
        if notes:
            out["notes"] = notes
    return out


def _text(d: dict) -> str:
    interval = "" if d["interval_ms"] is None else f" +{d['interval_ms']:.2f}ms"
    line = (f"{d['camera']} seq={d['seq']} stamp_ns={d['stamp_ns']}{interval} "
            f"latency={d['latency_ms']:.2f}ms" + (f" age={d['age_ms']:.2f}ms" if "age_ms" in d else "")
            + f" {d['size']} {d['pixels']}")
    if "boards" in d:
        boards = ", ".join(f"{b['board']}" + (f"#{b['copy']}" if b["copy"] else "") + f" {b['corners']}/{b['of']}"
                           for b in d["boards"]) or "no board"
        line += f": {boards}" + "".join(f" ({n})" for n in d.get("notes", []))
    return line


def run(args: argparse.Namespace) -> int:
    """Grab ``--frames`` frames (or until a replay ends) and print them."""
    from edgecal.drivers import StereoFrame, open_source
    from edgecal.drivers.recording import Recorder
    from edgecal.targets import load_target, parse_board_spec
    target = load_target(args.target) if args.target else parse_board_spec(args.board) if args.board else None
    prev: dict[str, int] = {}
    with open_source(args.source) as src:
        recorder = Recorder(args.out, src.describe(), force=args.force) if args.out else None
        try:
            for _ in range(args.frames):
                item = src.read()
                if item is None:
                    break
                now = time.monotonic_ns()
                if recorder is not None:
                    recorder.add(item)
                frames = [item.left, item.right] if isinstance(item, StereoFrame) else [item]
                rows = []
                for f in frames:
                    rows.append(_describe_frame(f, prev.get(f.camera_id), now, target, src.live))
                    prev[f.camera_id] = f.stamp_ns
                if isinstance(item, StereoFrame):
                    rows[1]["skew_ms"] = round(item.skew_ns / 1e6, 3)
                for r in rows:
                    text = _text(r) + (f" skew={r['skew_ms']:.3f}ms" if "skew_ms" in r else "")
                    print(json.dumps(r) if args.json else text, flush=True)
        finally:
            if recorder is not None:
                recorder.close()
        if src.dropped:
            print(f"# {src.dropped} frames dropped by the source", flush=True)
    if target is None and not args.json:
        print("# no --target/--board given: detection skipped", flush=True)
    return 0
