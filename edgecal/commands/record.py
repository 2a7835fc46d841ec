"""``edgecal record SOURCE --out DIR``: lossless frames, timestamps and settings, replayable bit for bit;
``--out FILE.mcap``: ROS 2 Image messages in an MCAP file (Foxglove, ROS, ``mcap:``)."""

from __future__ import annotations

import argparse
import sys

from edgecal.commands.argtypes import positive_float, positive_int


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register ``edgecal record``."""
    p = sub.add_parser("record", help="record a camera (or replay) to PNG frames + manifest.json",
                       description="Record SOURCE (a URI such as aravis:192.168.1.20, v4l2:/dev/video0, "
                                   "depthai:, stereo:A,B) into DIR as lossless PNG frames and a manifest of "
                                   "timestamps and settings. `replay:DIR` plays it back bit for bit. "
                                   "With --out FILE.mcap: ROS 2 sensor_msgs/msg/Image messages in an MCAP file "
                                   "(/camera/image_raw, or /left/image_raw + /right/image_raw).")
    p.add_argument("source", metavar="SOURCE", help="source URI (see docs/drivers.md)")
    p.add_argument("--out", required=True, metavar="DIR",
                   help="recording folder (must be empty unless --force), or a FILE.mcap")
    p.add_argument("--image", choices=("raw", "png", "jpeg"), default="raw",
                   help="MCAP only: Image messages (raw, default) or CompressedImage (png lossless, jpeg 8-bit)")
    limit = p.add_mutually_exclusive_group()
    limit.add_argument("--frames", type=positive_int, metavar="N", help="stop after N frames (or pairs)")
    limit.add_argument("--seconds", type=positive_float, metavar="S", help="stop after S seconds")
    p.add_argument("--force", action="store_true", help="replace a recording already in DIR (or FILE.mcap)")
    return p


def run(args: argparse.Namespace) -> int:
    """Record until the limit, the end of a replay, or Ctrl-C; the manifest is written in every case."""
    from edgecal.drivers import open_source, record
    with open_source(args.source) as src:
        summary = record(src, args.out, frames=args.frames, seconds=args.seconds, force=args.force,
                         image_format=args.image)
    rate = summary.frames / summary.seconds if summary.seconds > 0 else 0.0
    print(f"recorded {summary.frames} {'pairs' if summary.layout == 'stereo' else 'frames'} in "
          f"{summary.seconds:.2f} s ({rate:.1f}/s), {summary.dropped} dropped, into {summary.out}",
          file=sys.stderr)
    return 0
