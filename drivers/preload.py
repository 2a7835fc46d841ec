"""Replay frames held in memory: image files decoded once (``preload: true``) and handed out read-only.

A PNG decode per frame (~14 ms for 1280x800) would otherwise be counted as the consumer's time; preloaded,
``read()`` costs what a camera's does. A file that does not decode keeps its InputError for its own frame.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from edgecal.drivers.spec import SourceSpec
from edgecal.errors import InputError
from edgecal.images import DEFAULT_MAX_PIXELS, read_image

MIB = 1 << 20


def read_image_file(path: Path, max_pixels: int = DEFAULT_MAX_PIXELS) -> np.ndarray:
    """The image's pixels unchanged (grey or BGR, uint8 or uint16); InputError naming the file otherwise
    (including an image above ``max_pixels``, refused from its header before decoding)."""
    image = read_image(path, max_pixels)
    if image.ndim == 3 and image.shape[2] == 4:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
    return image


@dataclass(frozen=True)
class Unreadable:
    """A preloaded file that did not decode: its InputError message, raised again at that frame's read()."""

    message: str


def preload_images(files: Sequence[Path], where: Path | str, max_mb: float, group: int = 1,
                   max_pixels: int = DEFAULT_MAX_PIXELS) -> list[np.ndarray | Unreadable]:
    """Decode ``files`` once: read-only arrays (Unreadable for a file that does not decode), in order.

    ``group`` files make one frame (2 for stereo pairs): the first group's decoded size times the number
    of groups is the memory estimate, refused with an InputError naming ``where`` before the rest is
    decoded when it exceeds ``max_mb``; the running total is checked too (the images may differ in size).
    A file that does not decode is kept as Unreadable, so that its frame fails at read() as without preload.
    """
    def refuse(estimate_bytes: float) -> InputError:
        mb = estimate_bytes / MIB
        size = f"{mb:.0f}" if mb >= 10 else f"{mb:.2f}"
        return InputError(f"{where}: preloading {len(files)} images needs about {size} MB, more than "
                          f"preload_max_mb ({max_mb:g}); raise preload_max_mb or set preload: false")

    out: list[np.ndarray | Unreadable] = []
    total = 0
    limit = max_mb * MIB
    estimated = False
    for i, path in enumerate(files):
        try:
            image = read_image_file(path, max_pixels)
        except InputError as exc:
            out.append(Unreadable(str(exc)))
        else:
            # Read-only: the same array is handed out on every loop pass, so a consumer writing into
            # it would corrupt later passes; this makes such a write fail loudly instead.
            image.flags.writeable = False
            out.append(image)
            total += image.nbytes
        if not estimated and i + 1 >= group and total > 0:
            # Once, from the first frame that decoded (normally the first group): refuse before the long decode.
            estimated = True
            if total / (i + 1) * len(files) > limit:
                raise refuse(total / (i + 1) * len(files))
        if total > limit:
            raise refuse(total / (i + 1) * len(files))
    return out


def preload_for(spec: SourceSpec, files: list[Path], group: int = 1) -> list[np.ndarray | Unreadable] | None:
    """``files`` decoded (preload_images) when ``spec`` asks for a preload, else None."""
    if not spec.settings.preload:
        return None
    return preload_images(files, Path(spec.target).expanduser(), spec.settings.preload_max_mb, group,
                          spec.settings.max_pixels)


def frame_image(images: list[np.ndarray | Unreadable] | None, index: int, file: Path,
                 max_pixels: int = DEFAULT_MAX_PIXELS) -> np.ndarray:
    """Frame ``index``'s image: the preloaded array (a file that did not decode raises its InputError
    anew, as a per-frame decode would), or ``file`` decoded now when nothing was preloaded."""
    if images is None:
        return read_image_file(file, max_pixels)
    entry = images[index]
    if isinstance(entry, Unreadable):
        raise InputError(entry.message)
    return entry
