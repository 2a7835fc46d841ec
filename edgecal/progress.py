"""A one-line progress bar on stderr for long command-line steps, drawn only when stderr is a terminal.

Commands print their results as lines; the bar is redrawn in place with a carriage return, so it never
ends up in a log file, a pipe or a test's captured output. It must not be used by the daemon.
"""

from __future__ import annotations

import sys
import time
from typing import TextIO

BAR_WIDTH = 24
REDRAW_S = 0.1  # at most ten redraws a second: a terminal is slow and the work is what matters


def is_terminal(stream: TextIO) -> bool:
    """Whether ``stream`` is an interactive terminal."""
    try:
        return stream.isatty()
    except (AttributeError, ValueError):
        return False


def bar(fraction: float, width: int = BAR_WIDTH) -> str:
    """A bar of ``width`` characters filled to ``fraction`` (0..1), e.g. ``[######......]``."""
    n = int(max(0.0, min(1.0, fraction)) * width)  # full only when it is: 0.96 shows 9 of 10
    return "[" + "#" * n + "." * (width - n) + "]"


class Progress:
    """``with Progress("detecting", total) as p: p.update(i, "left03.jpg")``; silent unless a terminal.

    ``total`` None shows a count without a bar (a live camera has no end).
    """

    def __init__(self, label: str, total: int | None, stream: TextIO | None = None) -> None:
        self.label = label
        self.total = total
        self.stream = stream if stream is not None else sys.stderr
        self.enabled = is_terminal(self.stream)
        self._last = 0.0
        self._shown = False

    def update(self, done: int, what: str = "", force: bool = False) -> None:
        """Show ``done`` of ``total`` and what is being worked on."""
        if not self.enabled:
            return
        now = time.monotonic()
        if not force and now - self._last < REDRAW_S:
            return
        self._last = now
        if self.total:
            text = f"{self.label} {bar(done / self.total)} {done}/{self.total} {what}"
        else:
            text = f"{self.label} {done} {what}"
        self.stream.write("\r\x1b[2K" + text[:160])
        self.stream.flush()
        self._shown = True

    def clear(self) -> None:
        """Remove the bar (before printing a result line, and at the end)."""
        if self.enabled and self._shown:
            self.stream.write("\r\x1b[2K")
            self.stream.flush()
            self._shown = False

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, *exc: object) -> None:
        self.clear()
