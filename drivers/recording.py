"""edgecal recordings: lossless PNG frames plus a manifest of timestamps and the source's settings.

Layout of a recording folder::

    manifest.json           format, layout (mono | stereo), the source's description, one entry per frame
    frames/000000.png       mono recordings
    left/000000.png         stereo recordings: one file per side, same index = same pair
    right/000000.png

A manifest frame entry holds ``file`` (relative path), ``stamp_ns``, ``recv_ns``, ``seq``, ``camera_id``,
``exposure_us``, ``gain_db``; a stereo entry is ``{"left": {...}, "right": {...}}``. PNG keeps uint8 and
uint16, grey and BGR, bit for bit; replaying gives back the same pixels and ``stamp_ns``.
"""

from __future__ import annotations

import json
import math
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from edgecal.drivers.base import Frame, Source, StereoFrame
from edgecal.errors import InputError, quote
from edgecal.fileio import check_outputs, png_bytes, read_input, sync_paths, write_atomic

MANIFEST = "manifest.json"
FORMAT = "edgecal-recording"
VERSION = 1
# Folders a recording writes into; --force clears exactly these (and the manifest), nothing else.
_FRAME_DIRS = ("frames", "left", "right")


def encode_png(image: np.ndarray, name: str) -> bytes:
    """Lossless PNG bytes of a uint8/uint16 grey or BGR image."""
    if image.dtype not in (np.uint8, np.uint16):
        raise InputError(f"{name}: cannot record a {image.dtype} image (uint8 or uint16 only)")
    return png_bytes(image)


def _frame_entry(frame: Frame, file: str) -> dict[str, Any]:
    return {"file": file, "stamp_ns": int(frame.stamp_ns), "recv_ns": int(frame.recv_ns), "seq": int(frame.seq),
            "camera_id": frame.camera_id, "exposure_us": frame.exposure_us, "gain_db": frame.gain_db}


def recording_layout(layout: str | None, item: Frame | StereoFrame, out: Path) -> str:
    """The layout (``mono``/``stereo``) of a recording after adding ``item``: a recording holds one kind only."""
    kind = "stereo" if isinstance(item, StereoFrame) else "mono"
    if layout is not None and kind != layout:
        raise InputError(f"{out}: a {layout} recording cannot take a {kind} frame")
    return kind


class Recorder:
    """Writes frames (or stereo pairs) into a recording folder; ``close()`` writes the final manifest.

    The manifest is also rewritten every ``flush_every`` frames, so a recording cut short by a crash or
    a power loss is still replayable up to the last flush. Frames are written atomically but fsynced in a
    batch before each manifest (one fsync per frame would stall the capture on a slow card): the manifest
    never lists a frame that is not on the disk.
    """

    def __init__(self, out_dir: str | Path, source: dict[str, Any], force: bool = False,
                 flush_every: int = 100) -> None:
        self.out = Path(out_dir)
        self.source = source
        self.flush_every = flush_every
        self.entries: list[dict[str, Any]] = []
        self._unsynced: list[Path] = []  # frames written since the last manifest
        self.layout: str | None = None
        self.started_utc = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
        if self.out.exists() and not self.out.is_dir():
            raise InputError(f"{self.out}: exists and is not a folder (choose another --out)")
        check_outputs([self.out / MANIFEST], force=True, create_folders=True)  # before any frame is grabbed
        if self.out.is_dir() and any(self.out.iterdir()):
            if not force:
                raise InputError(f"{self.out}: folder is not empty (choose another --out, or --force to replace "
                                 "the recording in it)")
            for d in _FRAME_DIRS:
                if (self.out / d).is_dir():
                    shutil.rmtree(self.out / d)
            if (self.out / MANIFEST).exists():
                (self.out / MANIFEST).unlink()
        self.out.mkdir(parents=True, exist_ok=True)

    def _write_image(self, sub: str, index: int, frame: Frame) -> str:
        rel = f"{sub}/{index:06d}.png"
        (self.out / sub).mkdir(exist_ok=True)
        write_atomic(self.out / rel, encode_png(frame.image, f"{self.out / rel}"), durable=False)
        self._unsynced.append(self.out / rel)
        return rel

    def add(self, item: Frame | StereoFrame) -> None:
        """Append one frame or stereo pair (a recording holds one kind only)."""
        self.layout = recording_layout(self.layout, item, self.out)
        i = len(self.entries)
        if isinstance(item, StereoFrame):
            entry = {"left": _frame_entry(item.left, self._write_image("left", i, item.left)),
                     "right": _frame_entry(item.right, self._write_image("right", i, item.right))}
        else:
            entry = _frame_entry(item, self._write_image("frames", i, item))
        self.entries.append(entry)
        if self.flush_every and len(self.entries) % self.flush_every == 0:
            self.write_manifest()

    def write_manifest(self) -> None:
        """Write manifest.json atomically with every frame added so far (those frames reach the disk first)."""
        sync_paths(self._unsynced)
        self._unsynced = []
        manifest = {"format": FORMAT, "version": VERSION, "layout": self.layout or "mono",
                    "started_utc": self.started_utc, "source": self.source, "frames": self.entries}
        write_atomic(self.out / MANIFEST, json.dumps(manifest, indent=1).encode("utf-8"))

    def close(self) -> None:
        """Write the final manifest."""
        self.write_manifest()


@dataclass
class RecordingSummary:
    """What ``record`` wrote."""

    out: Path
    frames: int
    seconds: float
    dropped: int
    layout: str


def record(source: Source, out_dir: str | Path, frames: int | None = None, seconds: float | None = None,
           force: bool = False, on_frame: Callable[[int, Frame | StereoFrame], None] | None = None,
           image_format: str = "raw") -> RecordingSummary:
    """Record from an opened ``source`` until ``frames`` frames or ``seconds`` have passed (or it ends).

    With neither limit, records until the source ends (a replay) or KeyboardInterrupt (a camera); the
    manifest is written in every case. ``out_dir`` ending in ``.mcap`` records ROS 2 Image messages into
    that MCAP file instead (drivers/mcap_record.py; ``image_format`` raw, png or jpeg).
    """
    rec: Any
    if str(out_dir).endswith(".mcap"):
        from edgecal.drivers.mcap_record import McapRecorder
        rec = McapRecorder(out_dir, source.describe(), force=force, image_format=image_format)
    else:
        rec = Recorder(out_dir, source.describe(), force=force)
    t0 = time.monotonic()
    n = 0
    try:
        while frames is None or n < frames:
            if seconds is not None and time.monotonic() - t0 >= seconds:
                break
            item = source.read()
            if item is None:
                break
            rec.add(item)
            n += 1
            if on_frame is not None:
                on_frame(n - 1, item)
    except KeyboardInterrupt:
        pass
    finally:
        rec.close()
    return RecordingSummary(rec.out, n, time.monotonic() - t0, source.dropped, rec.layout or "mono")


def load_manifest(folder: str | Path) -> dict[str, Any]:
    """Read and check a recording's manifest.json; InputError naming the file on any problem."""
    path = Path(folder) / MANIFEST
    if not path.is_file():
        raise InputError(f"{path}: not found (is {folder} an edgecal recording?)")
    raw = read_input(path, "recording manifest")
    try:
        data = json.loads(raw.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"{path}: unreadable manifest ({exc})") from None
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise InputError(f"{path}: not an edgecal recording manifest (format must be {FORMAT!r})")
    if data.get("version") != VERSION:
        raise InputError(f"{path}: recording version {quote(data.get('version'))} is not supported "
                         f"(this edgecal reads version {VERSION})")
    if data.get("layout") not in ("mono", "stereo") or not isinstance(data.get("frames"), list):
        raise InputError(f"{path}: manifest needs 'layout' (mono or stereo) and a 'frames' list")
    if not isinstance(data.get("source", {}), dict):
        raise InputError(f"{path}: 'source' must be a mapping (the recorded source's description)")
    for i, entry in enumerate(data["frames"]):
        if data["layout"] == "stereo":
            if not isinstance(entry, dict):
                raise InputError(f"{path}: frames[{i}] must be a mapping with 'left' and 'right'")
            for side in ("left", "right"):
                _check_frame_entry(path, f"frames[{i}].{side}", entry.get(side))
        else:
            _check_frame_entry(path, f"frames[{i}]", entry)
    return data


def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _check_frame_entry(path: Path, where: str, e: Any) -> None:
    """InputError naming the manifest and the field of a frame entry that is missing or of the wrong type."""
    if not isinstance(e, dict):
        raise InputError(f"{path}: {where} must be a mapping with file, stamp_ns and seq")
    for key in ("file", "stamp_ns", "seq"):
        if key not in e:
            raise InputError(f"{path}: {where} lacks '{key}'")
    if not isinstance(e["file"], str) or not e["file"]:
        raise InputError(f"{path}: {where}.file must be a file name relative to the recording")
    for key in ("stamp_ns", "seq", "recv_ns"):
        if key in e and not _is_int(e[key]):
            raise InputError(f"{path}: {where}.{key} must be an integer, not {quote(e[key])}")
    if e.get("camera_id") is not None and not isinstance(e["camera_id"], str):
        raise InputError(f"{path}: {where}.camera_id must be a string")
    for key in ("exposure_us", "gain_db"):
        v = e.get(key)
        if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v)):
            raise InputError(f"{path}: {where}.{key} must be a number or null, not {quote(v)}")
