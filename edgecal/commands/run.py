"""``edgecal run --config configs/robot.yaml``: the live pose daemon.

Reads stereo frames, detects the robot's boards in both images, estimates T_rig_robot and publishes it
on a ZeroMQ socket (schema: README.md, "Pose stream"). Logs go to stdout (the journal under systemd).
SIGTERM/SIGINT stop it cleanly; SIGHUP reloads the config file (a broken file is logged and ignored).
"""

from __future__ import annotations

import argparse
import faulthandler
import logging
import os
import signal
import sys
import threading
import time

from edgecal.stream.config import load_live_config
from edgecal.stream.loop import LiveLoop

STOP_GRACE_S = 0.6     # after SIGTERM, how long the loop may take to finish its frame before abort()


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register ``edgecal run``."""
    p = subparsers.add_parser("run", help="the live robot-pose loop: stereo source -> pose -> ZeroMQ",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", required=True, help="live-loop config YAML (e.g. configs/robot.yaml)")
    p.add_argument("--check", action="store_true", help="validate the config and exit (opens no device)")
    return p


def _log_to_stdout() -> None:
    """INFO and up of edgecal's loggers on stdout, one line each (systemd adds its own timestamps)."""
    handler = logging.StreamHandler(sys.stdout)
    under_systemd = "JOURNAL_STREAM" in os.environ or "NOTIFY_SOCKET" in os.environ
    fmt = "%(levelname)s %(name)s: %(message)s" if under_systemd else \
        "%(asctime)s %(levelname)s %(name)s: %(message)s"
    handler.setFormatter(logging.Formatter(fmt))
    logger = logging.getLogger("edgecal")
    logger.addHandler(handler)
    logger.setLevel(min(logger.getEffectiveLevel(), logging.INFO))
    logger.propagate = False


def run(args: argparse.Namespace) -> int:
    """Validate the config (one-line error, exit 2, before any device opens), then run until stopped.

    The loop runs in its own thread; the main thread only waits, so signals are served at once. A stop
    request that the loop has not honoured within STOP_GRACE_S (it is inside a slow frame) makes the
    main thread release the camera and the socket itself, so SIGTERM always ends the process within
    about a second.
    """
    config = load_live_config(args.config)
    if args.check:
        print(f"{args.config}: OK (source {config.source.uri}, publish {config.publish.endpoint})")
        return 0
    _log_to_stdout()
    loop = LiveLoop(config)
    outcome: list = []

    def body() -> None:
        try:
            outcome.append(loop.run())
        except BaseException as exc:     # handed to the main thread, which reports it as the CLI does
            outcome.append(exc)

    # Handlers only set flags; the loop acts on them between frames.
    signal.signal(signal.SIGTERM, lambda *_: loop.request_stop())
    signal.signal(signal.SIGINT, lambda *_: loop.request_stop())
    signal.signal(signal.SIGHUP, lambda *_: loop.request_reload())
    faulthandler.register(signal.SIGUSR1)      # `kill -USR1` prints every thread's stack: a hang is diagnosable
    worker = threading.Thread(target=body, name="live-loop", daemon=True)
    worker.start()
    while worker.is_alive():
        worker.join(0.05)
        asked = loop.stop_requested_ns
        if asked and worker.is_alive() and time.monotonic_ns() - asked > STOP_GRACE_S * 1e9:
            loop.abort()
            break
    result = outcome[0] if outcome else 0
    if isinstance(result, BaseException):
        raise result
    # The camera and the socket are released and the logs written by now. Skip the interpreter's own
    # teardown: native libraries' finalizers take seconds on a loaded machine, and systemd expects the
    # service gone within a second of SIGTERM.
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(int(result))
