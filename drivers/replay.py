"""Replay: a folder of images, a video file, or an edgecal recording, as a Source.

``replay:PATH`` picks the kind from what PATH is:

* a folder with ``manifest.json``: an edgecal recording (mono or stereo), replayed bit-exact (pixels and
  ``stamp_ns``; ``recv_ns`` is the replay's own delivery time);
* a folder with ``left/`` and ``right/`` image folders: a stereo sequence, paired by sorted file order
  and stamped at ``fps`` - or, for a rendered sequence with a ``truth.json`` frame list
  (``edgecal render robot``), paired and stamped as that list says;
* a folder of images: one frame per image in name order, stamped at ``fps`` (default 30);
* a video file: one frame per decoded frame, stamped at the file's frame rate.

``pace: recorded`` (default) delivers frames in real time at the recorded intervals; ``pace: fast`` as
fast as they decode. ``loop: true`` starts again at the end; later passes keep ``stamp_ns`` and ``seq``
increasing (shifted by the length of the sequence), so only the first pass is bit-exact in time.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from edgecal.drivers.base import Frame, Source, StereoFrame, StereoSource
from edgecal.drivers.recording import MANIFEST, load_manifest
from edgecal.drivers.spec import SourceSpec
from edgecal.errors import DeviceError, InputError
from edgecal.images import IMAGE_SUFFIXES

DEFAULT_FPS = 30.0
# A rendered stereo sequence's ground truth (edgecal.synth), whose frames carry their capture stamps.
SYNTH_TRUTH = "truth.json"


@dataclass(frozen=True)
class ReplayItem:
    """One frame to replay: where its pixels are and what its metadata was."""

    file: Path | None      # None for a video frame (decoded in order)
    stamp_ns: int
    seq: int
    camera_id: str
    exposure_us: float | None = None
    gain_db: float | None = None


def read_image_file(path: Path) -> np.ndarray:
    """The image's pixels unchanged (grey or BGR, uint8 or uint16); InputError naming the file otherwise."""
    try:
        data = np.fromfile(str(path), dtype=np.uint8)
    except OSError as exc:
        raise InputError(f"{path}: cannot read image ({exc.strerror or exc})") from None
    image = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if image is None:
        raise InputError(f"{path}: not a readable image")
    if image.ndim == 3 and image.shape[2] == 4:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
    return image


def image_files(folder: Path) -> list[Path]:
    """The image files of ``folder`` in name order."""
    return sorted(f for f in folder.iterdir() if f.is_file() and f.suffix.lower() in IMAGE_SUFFIXES)


class Pacer:
    """Sleeps so that frames come out at their recorded intervals (``fast``: never sleeps)."""

    def __init__(self, fast: bool) -> None:
        self.fast = fast
        self.t0_host: int | None = None
        self.t0_stamp = 0

    def wait(self, stamp_ns: int) -> None:
        """Block until the frame stamped ``stamp_ns`` is due."""
        if self.fast:
            return
        now = time.monotonic_ns()
        if self.t0_host is None:
            self.t0_host, self.t0_stamp = now, stamp_ns
            return
        due = self.t0_host + (stamp_ns - self.t0_stamp)
        if due > now:
            time.sleep((due - now) / 1e9)


def _items_from_entries(entries: list[dict[str, Any]], folder: Path, default_id: str) -> list[ReplayItem]:
    return [ReplayItem(folder / e["file"], int(e["stamp_ns"]), int(e["seq"]), str(e.get("camera_id") or default_id),
                       e.get("exposure_us"), e.get("gain_db")) for e in entries]


def _items_from_files(files: list[Path], fps: float, camera_id: str) -> list[ReplayItem]:
    period = int(round(1e9 / fps))
    return [ReplayItem(f, i * period, i, camera_id) for i, f in enumerate(files)]


class _Sequence:
    """Walks a list of items (or a video) with looping; shared by the mono and stereo replays."""

    def __init__(self, n: int, period_ns: int, loop: bool) -> None:
        self.n = n
        self.period_ns = period_ns
        self.loop = loop
        self.index = 0
        self.passes = 0

    def next_index(self) -> int | None:
        """The index to deliver next, or None at the end of a non-looping sequence."""
        if self.index >= self.n:
            if not self.loop or self.n == 0:
                return None
            self.index = 0
            self.passes += 1
        i = self.index
        self.index += 1
        return i


class ReplaySource(Source):
    """A mono replay of image files (a folder or a recording) or of a video file."""

    def __init__(self, spec: SourceSpec, items: list[ReplayItem] | None = None, video: Path | None = None,
                 description: dict[str, Any] | None = None) -> None:
        self.spec = spec
        self.uri = spec.uri
        self.items = items or []
        self.video = video
        self.description = description
        self._cap: cv2.VideoCapture | None = None
        self._seq: _Sequence | None = None
        self._pacer = Pacer(spec.settings.pace == "fast")
        self._span_ns = 0

    def describe(self) -> dict:
        """The replayed recording's own source description (so a re-recording keeps it), else the URI."""
        out = {"uri": self.uri, "driver": "replay", "settings": self.spec.settings.as_dict()}
        if self.description:
            out["recorded_from"] = self.description
        return out

    def open(self) -> None:
        """Open the video (if any) and rewind."""
        if self.video is not None:
            self._cap = cv2.VideoCapture(str(self.video))
            if not self._cap.isOpened():
                raise InputError(f"{self.video}: cannot open as a video (unsupported format or codec?)")
            n = int(self._cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
            fps = self.spec.settings.fps or self._cap.get(cv2.CAP_PROP_FPS) or DEFAULT_FPS
            period = int(round(1e9 / fps))
            self._seq = _Sequence(max(n, 1) if n > 0 else 1 << 62, period, self.spec.settings.loop)
            self._video_index = 0
        else:
            stamps = [it.stamp_ns for it in self.items]
            period = int(np.median(np.diff(stamps))) if len(stamps) > 1 else int(1e9 / DEFAULT_FPS)
            self._seq = _Sequence(len(self.items), period, self.spec.settings.loop)
            self._span_ns = (stamps[-1] - stamps[0] + period) if stamps else 0

    def _read_video_frame(self) -> tuple[np.ndarray | None, int]:
        assert self._cap is not None and self._seq is not None
        ok, image = self._cap.read()
        if not ok:
            if self.spec.settings.loop and self._video_index > 0:
                self._cap.set(cv2.CAP_PROP_POS_FRAMES, 0)
                ok, image = self._cap.read()
            if not ok:
                return None, 0
        i = self._video_index
        self._video_index += 1
        return image, i

    def read(self, timeout_s: float | None = None) -> Frame | None:
        """The next frame (paced per ``pace``), or None at the end."""
        if self._seq is None:
            raise DeviceError(f"{self.uri}: read() before open() (use the source as a context manager)")
        if self.video is not None:
            image, i = self._read_video_frame()
            if image is None:
                return None
            stamp = i * self._seq.period_ns
            self._pacer.wait(stamp)
            return Frame(image, stamp, time.monotonic_ns(), i, self.spec.camera_id)
        k = self._seq.next_index()
        if k is None:
            return None
        item = self.items[k]
        image = read_image_file(item.file)  # type: ignore[arg-type]
        shift = self._seq.passes * self._span_ns
        stamp = item.stamp_ns + shift
        self._pacer.wait(stamp)
        seq = item.seq + self._seq.passes * len(self.items)
        return Frame(image, stamp, time.monotonic_ns(), seq, item.camera_id, item.exposure_us, item.gain_db)

    def close(self) -> None:
        """Release the video file."""
        if self._cap is not None:
            self._cap.release()
            self._cap = None
        self._seq = None


class StereoReplaySource(StereoSource):
    """A stereo replay: pairs of image files (a stereo recording, or left/ and right/ folders)."""

    def __init__(self, spec: SourceSpec, pairs: list[tuple[ReplayItem, ReplayItem]],
                 description: dict[str, Any] | None = None) -> None:
        self.spec = spec
        self.uri = spec.uri
        self.pairs = pairs
        self.description = description
        self._seq: _Sequence | None = None
        self._pacer = Pacer(spec.settings.pace == "fast")
        self._span_ns = 0

    def describe(self) -> dict:
        """The replayed recording's own description, if any, and the replay settings."""
        out = {"uri": self.uri, "driver": "replay", "layout": "stereo", "settings": self.spec.settings.as_dict()}
        if self.description:
            out["recorded_from"] = self.description
        return out

    def open(self) -> None:
        """Rewind."""
        stamps = [min(a.stamp_ns, b.stamp_ns) for a, b in self.pairs]
        period = int(np.median(np.diff(stamps))) if len(stamps) > 1 else int(1e9 / DEFAULT_FPS)
        self._seq = _Sequence(len(self.pairs), period, self.spec.settings.loop)
        self._span_ns = (stamps[-1] - stamps[0] + period) if stamps else 0

    def read(self, timeout_s: float | None = None) -> StereoFrame | None:
        """The next pair (paced per ``pace``), or None at the end."""
        if self._seq is None:
            raise DeviceError(f"{self.uri}: read() before open() (use the source as a context manager)")
        k = self._seq.next_index()
        if k is None:
            return None
        shift = self._seq.passes * self._span_ns
        seq_shift = self._seq.passes * len(self.pairs)
        frames = []
        for item in self.pairs[k]:
            frames.append((read_image_file(item.file), item))  # type: ignore[arg-type]
        self._pacer.wait(min(it.stamp_ns for _, it in frames) + shift)
        now = time.monotonic_ns()
        left, right = (Frame(img, it.stamp_ns + shift, now, it.seq + seq_shift, it.camera_id, it.exposure_us,
                             it.gain_db) for img, it in frames)
        return StereoFrame(left, right)

    def close(self) -> None:
        """Nothing to release but the position."""
        self._seq = None


def _synth_sequence(path: Path, spec: SourceSpec) -> list[tuple[ReplayItem, ReplayItem]] | None:
    """Pairs with the capture stamps of a rendered sequence's truth.json (``edgecal render robot``), if any.

    The renderer knows when each pair was "captured"; replaying with its stamps lets the live loop's
    output be compared with the ground truth frame by frame.
    """
    truth = path / SYNTH_TRUTH
    if not truth.is_file():
        return None
    try:
        data = json.loads(truth.read_text(encoding="utf-8"))
        entries = data["frames"]
        pairs = []
        for i, e in enumerate(entries):
            stamp, seq = int(e["stamp_ns"]), int(e.get("index", i))
            pairs.append((ReplayItem(path / e["left"], stamp, seq, f"{spec.camera_id}#left"),
                          ReplayItem(path / e["right"], stamp, seq, f"{spec.camera_id}#right")))
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise InputError(f"{truth}: cannot read the sequence's frame list ({exc}); remove it to replay the "
                         "left/ and right/ images at a nominal rate") from None
    return pairs or None


def open_replay(spec: SourceSpec) -> Source:
    """The replay Source for ``spec.target`` (see the module docstring for what PATH may be)."""
    path = Path(spec.target).expanduser()
    if not path.exists():
        raise InputError(f"{path}: no such file or folder to replay")
    cid = spec.camera_id
    fps = spec.settings.fps or DEFAULT_FPS
    if path.is_file():
        if path.suffix.lower() in IMAGE_SUFFIXES:
            return ReplaySource(spec, _items_from_files([path], fps, cid))
        return ReplaySource(spec, video=path)
    if (path / MANIFEST).is_file():
        m = load_manifest(path)
        if m["layout"] == "stereo":
            lefts = _items_from_entries([e["left"] for e in m["frames"]], path, f"{cid}#left")
            rights = _items_from_entries([e["right"] for e in m["frames"]], path, f"{cid}#right")
            return StereoReplaySource(spec, list(zip(lefts, rights)), m.get("source"))
        return ReplaySource(spec, _items_from_entries(m["frames"], path, cid), description=m.get("source"))
    if (path / "left").is_dir() and (path / "right").is_dir():
        stamped = _synth_sequence(path, spec)
        if stamped is not None:
            return StereoReplaySource(spec, stamped)
        lf, rf = image_files(path / "left"), image_files(path / "right")
        if not lf or not rf:
            raise InputError(f"{path}: left/ and right/ must both hold images")
        if len(lf) != len(rf):
            raise InputError(f"{path}: left/ has {len(lf)} images but right/ has {len(rf)}; "
                             "a stereo sequence needs one right image per left image")
        lefts = _items_from_files(lf, fps, f"{cid}#left")
        rights = _items_from_files(rf, fps, f"{cid}#right")
        return StereoReplaySource(spec, list(zip(lefts, rights)))
    files = image_files(path)
    if not files:
        raise InputError(f"{path}: the folder holds no images ({', '.join(IMAGE_SUFFIXES)}), no manifest.json "
                         "and no left/ and right/ folders")
    return ReplaySource(spec, _items_from_files(files, fps, cid))
