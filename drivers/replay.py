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

``preload: true`` (image files only, not a video) decodes every image once at ``open()`` and hands out
the decoded arrays, read-only, so that ``read()`` costs what a camera's does: a PNG decode per frame
(~14 ms for 1280x800) would otherwise be counted as the consumer's time. Pixels, stamps, seq, looping
and pacing are the same as without it; an unreadable file still raises its InputError at its own
``read()``. ``preload_max_mb`` bounds the memory (estimated from the first images before decoding all;
drivers/preload.py).
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from edgecal.config import setting
from edgecal.drivers.base import Frame, Source, StereoFrame, StereoSource
from edgecal.drivers.preload import Unreadable, frame_image, preload_for, read_image_file
from edgecal.drivers.recording import MANIFEST, load_manifest
from edgecal.drivers.spec import SourceSettings, SourceSpec, pace_setting
from edgecal.errors import InputError
from edgecal.fileio import read_input
from edgecal.imageheader import image_size
from edgecal.images import DEFAULT_MAX_PIXELS, IMAGE_SUFFIXES, image_files

DEFAULT_FPS = 30.0
# A rendered stereo sequence's ground truth (edgecal.synth), whose frames carry their capture stamps.
SYNTH_TRUTH = "truth.json"


@dataclass(frozen=True)
class ReplaySettings(SourceSettings):
    """Settings of a replay (a folder of images, a video file, an edgecal recording)."""

    pace: str = pace_setting()
    loop: bool = setting(False, doc="start again at the end")
    fps: float | None = setting(None, doc="frame rate of images without stamps, or of a video (default: its own)",
                                positive=True, maximum=10000)
    preload: bool = setting(False, doc="decode every image once at open() (frames as a camera gives them)")
    preload_max_mb: float = setting(2048.0, doc="refuse a preload whose decoded frames would need more (MiB)",
                                    positive=True)
    max_pixels: int = setting(DEFAULT_MAX_PIXELS, doc="refuse larger images (read from the header, before "
                                                      "decoding)", minimum=1)


@dataclass(frozen=True)
class ReplayItem:
    """One frame to replay: where its pixels are and what its metadata was."""

    file: Path | None      # None for a video frame (decoded in order)
    stamp_ns: int
    seq: int
    camera_id: str
    exposure_us: float | None = None
    gain_db: float | None = None


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
        super().__init__(spec.uri, spec.settings)
        self.spec = spec
        self.items = items or []
        self.video = video
        self.description = description
        self._cap: cv2.VideoCapture | None = None
        self._seq: _Sequence | None = None
        self._pacer = Pacer(spec.settings.pace == "fast")
        self.on_demand = self._pacer.fast
        self._span_ns = 0
        self._images: list[np.ndarray | Unreadable] | None = None  # preload: the decoded frames
        if video is not None and spec.settings.preload:
            raise InputError(f"{video}: preload works for image files only, not a video; "
                             "remove the preload setting to replay the video")

    def describe(self) -> dict:
        """The replayed recording's own source description (so a re-recording keeps it), else the URI."""
        out = {"uri": self.uri, "driver": "replay", "settings": self.spec.settings.as_dict()}
        if self.description:
            out["recorded_from"] = self.description
        return out

    def _open(self) -> None:
        """Open the video (if any) and rewind; with ``preload``, decode every image now."""
        if self.video is not None:
            self._cap = cv2.VideoCapture(str(self.video))
            if not self._cap.isOpened():
                raise InputError(f"{self.video}: cannot open as a video (unsupported format or codec?)")
            w, h = int(self._cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(self._cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
            if w * h > self.spec.settings.max_pixels:
                self.close()
                raise InputError(f"{self.video}: {w}x{h} frames are {w * h / 1e6:.3g} MP, more than max_pixels "
                                 f"({self.spec.settings.max_pixels / 1e6:.3g} MP); raise the source's max_pixels")
            n = int(self._cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
            fps = self.spec.settings.fps or self._cap.get(cv2.CAP_PROP_FPS) or DEFAULT_FPS
            period = int(round(1e9 / fps))
            self._seq = _Sequence(max(n, 1) if n > 0 else 1 << 62, period, self.spec.settings.loop)
            self._video_index = 0
        else:
            stamps = [it.stamp_ns for it in self.items]
            period = int(np.median(np.diff(stamps))) if len(stamps) > 1 else int(1e9 / DEFAULT_FPS)
            if self._images is None:
                self._images = preload_for(self.spec, [it.file for it in self.items])  # type: ignore[misc]
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

    def _read(self, timeout_s: float | None) -> Frame | None:
        """The next frame (paced per ``pace``), or None at the end."""
        assert self._seq is not None
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
        image = frame_image(self._images, k, item.file, self.spec.settings.max_pixels)  # type: ignore[arg-type]
        shift = self._seq.passes * self._span_ns
        stamp = item.stamp_ns + shift
        self._pacer.wait(stamp)
        seq = item.seq + self._seq.passes * len(self.items)
        return Frame(image, stamp, time.monotonic_ns(), seq, item.camera_id, item.exposure_us, item.gain_db)

    def _close(self) -> None:
        """Release the video file and the preloaded frames."""
        if self._cap is not None:
            self._cap.release()
            self._cap = None
        self._seq = None
        self._images = None


class StereoReplaySource(StereoSource):
    """A stereo replay: pairs of image files (a stereo recording, or left/ and right/ folders)."""

    def __init__(self, spec: SourceSpec, pairs: list[tuple[ReplayItem, ReplayItem]],
                 description: dict[str, Any] | None = None) -> None:
        super().__init__(spec.uri, spec.settings)
        self.spec = spec
        self.pairs = pairs
        self.description = description
        self._seq: _Sequence | None = None
        self._pacer = Pacer(spec.settings.pace == "fast")
        self.on_demand = self._pacer.fast
        self._span_ns = 0
        self._images: list[np.ndarray | Unreadable] | None = None  # preload: left, right, left, right ...

    def describe(self) -> dict:
        """The replayed recording's own description, if any, and the replay settings."""
        out = {"uri": self.uri, "driver": "replay", "layout": "stereo", "settings": self.spec.settings.as_dict()}
        if self.description:
            out["recorded_from"] = self.description
        return out

    def _open(self) -> None:
        """Rewind; with ``preload``, decode every image now."""
        if self._images is None:
            self._images = preload_for(self.spec, [it.file for pair in self.pairs for it in pair],  # type: ignore[misc]
                                        group=2)
        stamps = [min(a.stamp_ns, b.stamp_ns) for a, b in self.pairs]
        period = int(np.median(np.diff(stamps))) if len(stamps) > 1 else int(1e9 / DEFAULT_FPS)
        self._seq = _Sequence(len(self.pairs), period, self.spec.settings.loop)
        self._span_ns = (stamps[-1] - stamps[0] + period) if stamps else 0

    def _read(self, timeout_s: float | None) -> StereoFrame | None:
        """The next pair (paced per ``pace``), or None at the end."""
        assert self._seq is not None
        k = self._seq.next_index()
        if k is None:
            return None
        shift = self._seq.passes * self._span_ns
        seq_shift = self._seq.passes * len(self.pairs)
        frames = []
        for side, item in enumerate(self.pairs[k]):
            frames.append((frame_image(self._images, 2 * k + side, item.file,  # type: ignore[arg-type]
                                        self.spec.settings.max_pixels), item))
        self._pacer.wait(min(it.stamp_ns for _, it in frames) + shift)
        now = time.monotonic_ns()
        left, right = (Frame(img, it.stamp_ns + shift, now, it.seq + seq_shift, it.camera_id, it.exposure_us,
                             it.gain_db) for img, it in frames)
        return StereoFrame(left, right)

    def _close(self) -> None:
        """Release the position and the preloaded frames."""
        self._seq = None
        self._images = None


def _synth_sequence(path: Path, spec: SourceSpec) -> list[tuple[ReplayItem, ReplayItem]] | None:
    """Pairs with the capture stamps of a rendered sequence's truth.json (``edgecal render robot``), if any.

    The renderer knows when each pair was "captured"; replaying with its stamps lets the live loop's
    output be compared with the ground truth frame by frame.
    """
    truth = path / SYNTH_TRUTH
    if not truth.is_file():
        return None
    raw = read_input(truth, "frame list")
    try:
        data = json.loads(raw.decode("utf-8"))
        entries = data["frames"]
        pairs = []
        for i, e in enumerate(entries):
            stamp, seq = int(e["stamp_ns"]), int(e.get("index", i))
            pairs.append((ReplayItem(path / e["left"], stamp, seq, f"{spec.camera_id}#left"),
                          ReplayItem(path / e["right"], stamp, seq, f"{spec.camera_id}#right")))
    except (ValueError, KeyError, TypeError) as exc:
        raise InputError(f"{truth}: cannot read the sequence's frame list ({str(exc)[:80]}); remove it to replay the "
                         "left/ and right/ images at a nominal rate") from None
    return pairs or None


@dataclass(frozen=True)
class ReplayContents:
    """What a replay holds, found without opening it (for checking a config before it runs)."""

    frames: int                            # frames of one pass (a video: 1 when its first frame decodes)
    stereo: bool
    image_size: tuple[int, int] | None     # (width, height) of the first frame; None when it does not decode


def replay_contents(spec: SourceSpec) -> ReplayContents:
    """The number of frames, the layout and the first frame's size of the replay ``spec`` names.

    Raises InputError as :func:`open_replay` does (no such path, no images); decodes one image (or a video's
    first frame) and nothing else.
    """
    source = open_replay(spec)
    first: Path | None = None
    if isinstance(source, StereoReplaySource):
        frames, stereo = len(source.pairs), True
        first = source.pairs[0][0].file if source.pairs else None
    elif isinstance(source, ReplaySource) and source.video is not None:
        cap = cv2.VideoCapture(str(source.video))
        try:
            ok, image = cap.read() if cap.isOpened() else (False, None)
        finally:
            cap.release()
        size = (int(image.shape[1]), int(image.shape[0])) if ok and image is not None else None
        return ReplayContents(int(ok), False, size)
    else:
        assert isinstance(source, ReplaySource)  # open_replay makes one of the two
        frames, stereo = len(source.items), False
        first = source.items[0].file if source.items else None
    size = None
    if first is not None:
        try:
            # The header is enough (a config check runs on every reload); decoded only for a format whose
            # header is not read.
            size = image_size(read_input(first, "image file"))
            if size is None:
                image = read_image_file(first, spec.settings.max_pixels)
                size = (int(image.shape[1]), int(image.shape[0]))
        except InputError:
            pass            # an unreadable frame is skipped at run time; the size stays unknown
    return ReplayContents(frames, stereo, size)


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
