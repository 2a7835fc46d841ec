"""Test frames rendered with numpy for the driver tests (no files from outside the repository)."""

from __future__ import annotations

import time

import numpy as np

from edgecal.drivers.base import Frame, Source


def render_frame(index: int, shape: tuple[int, ...] = (48, 64), dtype: type = np.uint8) -> np.ndarray:
    """A chessboard-like pattern shifted by ``index`` plus seeded noise: every frame differs in every bit plane."""
    h, w = shape[:2]
    y, x = np.mgrid[0:h, 0:w]
    board = (((x + index) // 8 + y // 8) % 2).astype(np.float64)
    rng = np.random.default_rng(index)
    hi = np.iinfo(dtype).max
    img = board * (hi * 0.6) + rng.uniform(0, hi * 0.4, size=(h, w))
    img = img.astype(dtype)
    if len(shape) == 3:
        img = np.stack([img, np.roll(img, 1, axis=1), np.roll(img, 2, axis=0)], axis=2)
    return img


class ListSource(Source):
    """A finite Source over prepared frames; ``period_s`` > 0 makes it deliver at that pace (a fake camera).

    Used to feed the stereo pairer and the latest-frame queue with exact timestamps; it is test
    scaffolding standing in for a camera, not a copy of edgecal code.
    """

    def __init__(self, frames: list[Frame], period_s: float = 0.0, uri: str = "list:") -> None:
        self.frames = frames
        self.period_s = period_s
        self.uri = uri
        self.i = 0
        self.opened = False
        self.closed = False

    def _open(self) -> None:
        self.opened = True

    def _read(self, timeout_s: float | None):
        if self.i >= len(self.frames):
            return None
        if self.period_s:
            time.sleep(self.period_s)
        f = self.frames[self.i]
        self.i += 1
        return f

    def _close(self) -> None:
        self.closed = True


def frames_at(stamps_ns: list[int], camera_id: str = "cam") -> list[Frame]:
    """Frames with the given capture stamps (seq = position), tiny images."""
    return [Frame(render_frame(i, (8, 8)), int(s), int(s), i, camera_id) for i, s in enumerate(stamps_ns)]
