"""``edgecal sources``: which cameras are attached and usable, and which drivers are not and why."""

from __future__ import annotations

import argparse
import json


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register ``edgecal sources``."""
    p = sub.add_parser("sources", help="list attached cameras and which drivers are usable",
                       description="Ask every camera driver (V4L2, Aravis, IEEE-1394, DepthAI) what it sees. "
                                   "GigE Vision discovery broadcasts on the network; --no-network skips it.")
    p.add_argument("--no-network", action="store_true",
                   help="do not broadcast for GigE Vision or DepthAI network devices (USB, FireWire, V4L2 only)")
    p.add_argument("--fake", action="store_true", help="include libaravis's built-in fake camera")
    p.add_argument("--probe", action="append", default=[], metavar="URI",
                   help="also open URI and read one frame (e.g. aravis:192.168.1.20); repeatable")
    p.add_argument("--json", action="store_true", help="print JSON instead of text")
    return p


def run(args: argparse.Namespace) -> int:
    """Print the survey; exit 0 even when nothing is attached (that is an answer, not an error)."""
    from edgecal.drivers.discovery import probe, survey
    reports = survey(network=not args.no_network, fake=args.fake)
    probes = [probe(uri) for uri in args.probe]
    if args.json:
        print(json.dumps({"drivers": [r.as_json() for r in reports], "probes": probes}, indent=1))
        return 0
    for r in reports:
        state = "usable" if r.usable else "UNAVAILABLE"
        print(f"{r.driver:8s} {state}" + (f": {r.why}" if r.why else ""))
        for s in r.sources:
            mark = "ok" if s.get("usable") else f"not usable: {s.get('why')}"
            print(f"  {s['uri']:40s} {s.get('name', '')}  [{mark}]")
    for pr in probes:
        if pr["usable"]:
            print(f"probe    {pr['uri']}: ok, {pr['size']} {pr.get('name', '')}")
        else:
            print(f"probe    {pr['uri']}: NOT USABLE: {pr['why']}")
    return 0
