"""Counters and per-period latency/fps figures of the live loop."""

from __future__ import annotations

from typing import Any

import numpy as np


class LoopStats:
    """Counts since start, and latencies / frame times of the current reporting period.

    ``period()`` closes the period and returns its figures (fps, latency median and p99 in ms) with
    the totals; the next period starts empty so the numbers always describe the last second or so.
    """

    def __init__(self, now_ns: int) -> None:
        self.frames = 0                 # stereo frames processed
        self.poses_valid = 0
        self.poses_invalid = 0
        self.detection_failures = 0     # images (left or right) in which no board was found
        self.tracked_frames = 0         # frames whose predicted corners were verified (no full search)
        self.corrupt_frames = 0         # frames that could not be used at all (bad image, read error)
        self.errors = 0                 # unexpected exceptions while processing a frame
        self.dropped_frames = 0         # frames the source skipped (latest-frame-wins, device losses)
        self.reconnects = 0
        self.reload_failures = 0
        self._dropped_base = 0          # dropped frames of sources already closed
        self._latencies_ns: list[int] = []
        self._period_frames = 0
        self._period_start_ns = now_ns

    def frame_done(self, latency_ns: int, valid: bool, failed_images: int) -> None:
        """Record one processed frame."""
        self.frames += 1
        self._period_frames += 1
        self._latencies_ns.append(int(latency_ns))
        if valid:
            self.poses_valid += 1
        else:
            self.poses_invalid += 1
        self.detection_failures += failed_images

    def source_dropped(self, current_source_dropped: int) -> None:
        """Update from the open source's own ``dropped`` counter."""
        self.dropped_frames = self._dropped_base + int(current_source_dropped)

    def source_closed(self) -> None:
        """The source was closed: keep its drops in the total."""
        self._dropped_base = self.dropped_frames

    def period(self, now_ns: int) -> dict[str, Any]:
        """Close the current period and return its figures plus the totals."""
        span_s = max((now_ns - self._period_start_ns) / 1e9, 1e-9)
        lat = np.array(self._latencies_ns, dtype=np.float64) / 1e6
        out: dict[str, Any] = {
            "fps": round(self._period_frames / span_s, 2),
            "latency_ms": {"median": round(float(np.median(lat)), 2) if lat.size else None,
                           "p99": round(float(np.percentile(lat, 99)), 2) if lat.size else None},
            "frames": self.frames, "poses_valid": self.poses_valid, "poses_invalid": self.poses_invalid,
            "dropped_frames": self.dropped_frames, "detection_failures": self.detection_failures,
            "tracked_frames": self.tracked_frames,
            "corrupt_frames": self.corrupt_frames, "errors": self.errors, "reconnects": self.reconnects,
            "reload_failures": self.reload_failures,
        }
        self._latencies_ns = []
        self._period_frames = 0
        self._period_start_ns = now_ns
        return out
