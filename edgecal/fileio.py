"""Writing results safely: atomic replacement, and no silent clobbering of an earlier result."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Iterable

import cv2
import numpy as np

from edgecal.errors import InputError


def refuse_existing(paths: Iterable[Path], force: bool) -> None:
    """InputError for the first path that already exists, unless ``force``."""
    if force:
        return
    for p in paths:
        if Path(p).exists():
            raise InputError(f"{p}: already exists; choose another output path or pass --force to overwrite")


def write_atomic(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file in the same folder and os.replace.

    A reader never sees half a file, and a crash leaves the earlier file intact.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=str(path.parent))
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise


def write_png(path: str | Path, image: np.ndarray, force: bool = False) -> None:
    """Encode ``image`` as PNG and write it atomically (refusing to replace a file unless ``force``)."""
    refuse_existing([Path(path)], force)
    ok, buf = cv2.imencode(".png", image)
    if not ok:
        raise InputError(f"{path}: could not encode the image as PNG")
    write_atomic(path, buf.tobytes())
