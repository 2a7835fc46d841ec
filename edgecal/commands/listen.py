"""``edgecal listen ENDPOINT``: print the pose stream of a running ``edgecal run``.

Subscribes through edgecal.publish.subscriber.PoseSubscriber (the example for writing your own subscriber: a
ZeroMQ SUB socket, connected and subscribed to the topics you want; the second frame of each message is JSON,
schema in README.md, "Pose stream").
A stream bound beyond the loopback interface is CURVE-secured: give this subscriber's key pair (--key) and
the publisher's public key (--server-key); the publisher must hold this subscriber's public key.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

from edgecal.errors import QUOTE_MAX_CHARS, InputError, quote
from edgecal.publish.curve import load_client_keys
from edgecal.publish.subscriber import TOPICS, PoseSubscriber, parse_message


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register the ``listen`` sub-command."""
    p = subparsers.add_parser("listen", help="print the pose stream published by `edgecal run`",
                              description="Subscribe to a pose stream and print one line per message.")
    p.add_argument("endpoint", nargs="?", default="tcp://127.0.0.1:5560",
                   help="where `edgecal run` publishes (default tcp://127.0.0.1:5560)")
    p.add_argument("--topic", choices=TOPICS, action="append", help="only this topic (repeatable; default all)")
    p.add_argument("--json", action="store_true", help="print each message as raw JSON")
    p.add_argument("--count", type=int, default=0, help="stop after this many messages (0 = never)")
    p.add_argument("--timeout", type=float, default=0.0,
                   help="stop with exit code 1 after this many seconds without a message (0 = wait forever)")
    p.add_argument("--key", metavar="NAME.key_secret",
                   help="this subscriber's key pair (from `edgecal keys`): subscribe to a CURVE-secured stream")
    p.add_argument("--server-key", metavar="SERVER.key",
                   help="the publisher's public key file (with --key)")
    return p


def describe_message(msg: dict) -> str:
    """format_message's line, or a short note naming the message when it lacks what that line needs."""
    try:
        return format_message(msg)
    except (KeyError, TypeError, ValueError, IndexError, AttributeError):
        return f"unrecognised {quote(msg.get('type'))} message: {quote(msg)}"


def format_message(msg: dict) -> str:
    """One human-readable line for a pose or status message."""
    if msg.get("type") == "status":
        lat = msg.get("latency_ms") or {}
        return (f"status {msg.get('state')}: {msg.get('fps')} fps, latency median {lat.get('median')} ms "
                f"p99 {lat.get('p99')} ms, dropped {msg.get('dropped_frames')}, detection failures "
                f"{msg.get('detection_failures')}, tracked {msg.get('tracked_frames')}/{msg.get('frames')} "
                f"{msg.get('message') or ''}").rstrip()
    head = f"pose #{msg['seq']} latency {msg['latency_ns'] / 1e6:.1f} ms"
    q = msg["quality"]
    if msg["pose"] is None or not msg["valid"]:
        return f"{head} INVALID ({msg['reason']})"
    p, o = msg["pose"]["position_m"], msg["pose"]["orientation_xyzw"]
    how = f" {q['detection']}" if q.get("detection") else ""
    return (f"{head} {q['mode']}{how} xyz_m [{p[0]:+.4f} {p[1]:+.4f} {p[2]:+.4f}] "
            f"q_xyzw [{o[0]:+.4f} {o[1]:+.4f} {o[2]:+.4f} {o[3]:+.4f}] "
            f"rms {q['rms_px']} px std {q['position_std_mm']} mm {q['rotation_std_deg']} deg"
            + (f" rejected {', '.join(q['rejected'])}" if q.get("rejected") else "")
            + (f" outliers {q['outliers']}" if q.get("outliers") else ""))


def run(args: argparse.Namespace) -> int:
    """Subscribe and print until --count messages, --timeout of silence, or Ctrl-C."""
    keys = None
    if args.key or args.server_key:
        if not (args.key and args.server_key):
            raise InputError("--key and --server-key go together: this subscriber's NAME.key_secret and the "
                             "publisher's public key file")
        keys = load_client_keys(args.key, args.server_key)
    sub = PoseSubscriber(args.endpoint, args.topic or TOPICS, keys=keys)
    received = 0
    try:
        last = time.monotonic()
        while args.count <= 0 or received < args.count:
            frames = sub.receive_frames(0.2)
            if frames is None:
                if args.timeout > 0 and time.monotonic() - last > args.timeout:
                    print(f"edgecal listen: no message from {args.endpoint} for {args.timeout:g} s",
                          file=sys.stderr)
                    return 1
                continue
            last = time.monotonic()
            msg = parse_message(frames)
            if msg is None:
                # Someone else's publisher, another schema, a damaged message: say so briefly, keep listening.
                print(f"edgecal listen: skipped a message that is not [topic, JSON object] "
                      f"({len(frames)} frames: {quote(b' '.join(f[:QUOTE_MAX_CHARS] for f in frames[:3]))})",
                      file=sys.stderr, flush=True)
                continue
            print(json.dumps(msg) if args.json else describe_message(msg), flush=True)
            received += 1
    finally:
        sub.close()
    return 0
