"""``edgecal sources``: which cameras are attached and usable, and which drivers are not and why;
``edgecal sources FILE.mcap`` / ``BAG``: the image topics of a robot log."""

from __future__ import annotations

import argparse
import json


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register ``edgecal sources``."""
    p = sub.add_parser("sources", help="list attached cameras and which drivers are usable",
                       description="Ask every camera driver (V4L2, Aravis, IEEE-1394, DepthAI) what it sees. "
                                   "GigE Vision discovery broadcasts on the network; --no-network skips it.")
    p.add_argument("log", nargs="?", metavar="LOG",
                   help="an MCAP file, ROS 1 .bag or ROS 2 bag folder: list its image topics instead")
    p.add_argument("--no-network", action="store_true",
                   help="do not broadcast for GigE Vision or DepthAI network devices (USB, FireWire, V4L2 only)")
    p.add_argument("--fake", action="store_true", help="include libaravis's built-in fake camera")
    p.add_argument("--probe", action="append", default=[], metavar="URI",
                   help="also open URI and read one frame (e.g. aravis:192.168.1.20); repeatable")
    p.add_argument("--json", action="store_true", help="print JSON instead of text")
    return p


def run(args: argparse.Namespace) -> int:
    """Print the survey; exit 0 even when nothing is attached (that is an answer, not an error)."""
    if args.log:
        return _list_log(args.log, args.json)
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


def _list_log(path: str, as_json: bool) -> int:
    """Print the topics of a robot log: image topics with count, size, encoding and the URI to open them."""
    from pathlib import Path

    from edgecal.drivers.robolog import MessageLog

    p = Path(path).expanduser()
    log: MessageLog
    if p.suffix == ".mcap" and not p.is_dir():
        from edgecal.drivers.mcap_source import McapLog
        log, driver = McapLog(p), "mcap"
    else:
        from edgecal.drivers.rosbag_source import RosbagLog
        log, driver = RosbagLog(p), "rosbag"
    infos = log.topics()
    broken = log.broken
    if as_json:
        print(json.dumps({"log": str(p), "driver": driver,
                          "topics": [{"topic": i.topic, "type": i.msgtype, "count": i.count, "image": i.is_image,
                                      "size": i.size or None, "encoding": i.encoding or None} for i in infos.values()],
                          "broken": None if broken is None else {"offset": broken.offset, "detail": broken.detail}},
                         indent=1))
        return 0
    images = [i for i in infos.values() if i.is_image]
    print(f"{p}: {len(images)} image topic{'s' if len(images) != 1 else ''} of {len(infos)}")
    for i in images:
        print(f"  {i.topic:32s} {i.msgtype.rsplit('/', 1)[-1]:16s} {i.count:7d} msgs  {i.size:>10s}  {i.encoding}")
    for i in infos.values():
        if not i.is_image:
            print(f"  {i.topic:32s} {i.msgtype or '?':16s} {i.count:7d} msgs  (not images)")
    if images:
        first = images[0].topic
        print(f"open with: {driver}:{p}?topic={first}" +
              (f"   or  {driver}:{p}?left={first}&right={images[1].topic}" if len(images) > 1 else ""))
    if broken is not None:
        where = f"at byte {broken.offset}" if broken.offset is not None else "part-way"
        print(f"warning: the log is truncated or corrupt {where} ({broken.detail}); the counts above may "
              "include messages after the break that cannot be read")
    return 0
