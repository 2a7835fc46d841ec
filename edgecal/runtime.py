"""Process-level tuning that edgecal's commands (edgecal.cli) and benchmarks apply once, at start.

glibc hands every allocation above 128 KiB straight to mmap and gives it back on free, so each new image
buffer (every frame, every intermediate image) costs a round of page faults: on a small robot computer
that made plain image arithmetic 5-7x slower than the arithmetic itself. Raising the mmap and trim
thresholds lets freed buffers be reused from the heap. Set EDGECAL_KEEP_MALLOC=1 to leave glibc as it is.
Importing the library does not do it: the allocator belongs to the program, which may have its own needs.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os

_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3


def tune_allocator(mmap_threshold: int = 256 << 20, trim_threshold: int = 512 << 20) -> bool:
    """Raise glibc's mmap/trim thresholds; True if applied (False on other C libraries or when opted out)."""
    if os.environ.get("EDGECAL_KEEP_MALLOC") == "1":
        return False
    name = ctypes.util.find_library("c")
    if not name:
        return False
    try:
        libc = ctypes.CDLL(name)
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False  # not glibc (musl, macOS): nothing to tune
    return bool(mallopt(_M_MMAP_THRESHOLD, mmap_threshold)) and bool(mallopt(_M_TRIM_THRESHOLD, trim_threshold))


def quiet_opencv_log(verbose: bool = False) -> None:
    """Keep OpenCV's own log lines off stderr (unless ``verbose``): edgecal reports every image it cannot
    decode itself, in one line naming the file, and OpenCV's warnings would repeat it in its words."""
    import cv2  # imported here: the benchmarks import this module for tune_allocator alone

    levels = cv2.utils.logging
    levels.setLogLevel(levels.LOG_LEVEL_WARNING if verbose else levels.LOG_LEVEL_SILENT)
