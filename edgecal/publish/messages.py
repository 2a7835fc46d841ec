"""The JSON messages of the pose stream (schema version 1; documented in README.md, "Pose stream").

Pure functions: a Pose or loop statistics in, a JSON-ready dict out. Non-finite numbers become null
(JSON has no NaN).
"""

from __future__ import annotations

import json
import math
from typing import Any

from edgecal.pose.types import Pose

SCHEMA_VERSION = 1
POSE_TOPIC = b"pose"
STATUS_TOPIC = b"status"


def _num(x: float, digits: int | None = None) -> float | None:
    x = float(x)
    if not math.isfinite(x):
        return None
    return round(x, digits) if digits is not None else x


LATENCY_BASES = ("capture", "receive")
DETECTION_KINDS = ("tracked", "searched")


def pose_message(pose: Pose, seq: int, stamp_ns: int, publish_ns: int, frame_id: str = "rig",
                 child_frame_id: str = "robot", *, capture_ns: int | None = None, latency_from: str = "capture",
                 detection: str | None = None) -> dict[str, Any]:
    """The whole "pose" message of one frame; ``pose`` and ``covariance`` are null when none could be computed.

    ``stamp_ns``: the source's stamp of the pair; ``capture_ns``: when it was captured on this host's
    CLOCK_MONOTONIC (default ``stamp_ns``), so ``latency_ns`` = publish - capture, and ``latency_from`` says
    what that capture time is ("capture": the device stamp; "receive": when the frame reached edgecal).
    ``detection``: how the boards were found ("tracked" or "searched"; left out when not given).
    ``frame_id`` / ``child_frame_id`` are publish.frame_id / publish.child_frame_id.
    """
    if latency_from not in LATENCY_BASES:
        raise ValueError(f"latency_from must be one of {LATENCY_BASES}, not {latency_from!r}")
    if detection is not None and detection not in DETECTION_KINDS:
        raise ValueError(f"detection must be one of {DETECTION_KINDS}, not {detection!r}")
    computed = bool(math.isfinite(float(pose.t_m[0])))
    cov = [_num(v) for v in pose.covariance.ravel()] if computed else None
    quality: dict[str, Any] = {
        "mode": pose.mode,
        "rms_px": _num(pose.rms_px, 4),
        "corners_left": int(pose.n_left),
        "corners_right": int(pose.n_right),
        "corners_both": int(pose.n_both),
        "boards": list(pose.boards),
        "rejected": list(pose.rejected),
        "outliers": int(pose.outliers),
        "edge_on": list(pose.edge_on),
        "position_std_mm": _num(pose.position_std_mm, 4) if computed else None,
        "rotation_std_deg": _num(pose.rotation_std_deg, 5) if computed else None,
    }
    if detection is not None:
        quality["detection"] = detection
    return {
        "version": SCHEMA_VERSION,
        "type": "pose",
        "seq": int(seq),
        "stamp_ns": int(stamp_ns),
        "publish_ns": int(publish_ns),
        "latency_ns": int(publish_ns - (stamp_ns if capture_ns is None else capture_ns)),
        "latency_from": latency_from,
        "frame_id": frame_id,
        "child_frame_id": child_frame_id,
        "valid": bool(pose.valid),
        "reason": pose.reason,
        "pose": {
            "position_m": [_num(v) for v in pose.t_m],
            "orientation_xyzw": [_num(v) for v in pose.quaternion_xyzw],
        } if computed else None,
        "covariance": cov,
        "quality": quality,
    }


def status_message(state: str, stats: dict[str, Any], now_ns: int, message: str = "") -> dict[str, Any]:
    """The once-a-second "status" message; ``stats`` holds the loop's counters (see LoopStats.snapshot)."""
    out: dict[str, Any] = {"version": SCHEMA_VERSION, "type": "status", "stamp_ns": int(now_ns), "state": state,
                           "message": message}
    for k, v in stats.items():
        out[k] = _num(v, 3) if isinstance(v, float) else v
    return out


def encode(message: dict[str, Any]) -> bytes:
    """Compact UTF-8 JSON (strict: no NaN)."""
    return json.dumps(message, separators=(",", ":"), allow_nan=False).encode("utf-8")


def decode(data: bytes) -> dict[str, Any]:
    """Parse one message body."""
    return json.loads(data.decode("utf-8"))
