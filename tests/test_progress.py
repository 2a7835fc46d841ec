"""The progress line: drawn in place on a terminal, silent in a pipe or a log."""

import io
import os
import pty

from edgecal.progress import Progress, bar


def test_progress_draws_on_a_terminal_only():
    master, slave = pty.openpty()
    with os.fdopen(slave, "w") as tty:
        with Progress("detecting", 4, stream=tty) as p:
            p.update(1, "left03.jpg", force=True)
        text = os.read(master, 4096).decode()
    os.close(master)
    assert "\r\x1b[2K" in text and "detecting [" in text and "1/4 left03.jpg" in text
    pipe = io.StringIO()
    with Progress("detecting", 4, stream=pipe) as p:
        p.update(1, "left03.jpg", force=True)
    assert pipe.getvalue() == ""


def test_bar_is_full_only_when_done():
    assert bar(0.96, 10) == "[#########.]" and bar(1.0, 10) == "[##########]" and bar(-1, 4) == "[....]"
