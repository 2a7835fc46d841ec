"""Replay and recording: a recording replays bit for bit (pixels and capture timestamps)."""

from __future__ import annotations

import json
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from edgecal.drivers import Frame, StereoFrame, StereoSource, open_source, record
from edgecal.errors import DeviceError, DeviceLost, InputError

from .driver_frames import ListSource, render_frame


def _camera_frames(n: int, shape: tuple[int, ...], dtype: type, start_ns: int = 123_456_789_012) -> list[Frame]:
    # Irregular stamps (jitter) so that a replay that re-stamps at a nominal rate would be caught.
    rng = np.random.default_rng(7)
    stamps = start_ns + np.cumsum(rng.integers(30_000_000, 36_000_000, size=n))
    return [Frame(render_frame(i, shape, dtype), int(s), int(s) + 1000, 10 + 2 * i, "cam0", 5000.0 + i, 1.5)
            for i, s in enumerate(stamps)]


@pytest.mark.parametrize("shape, dtype", [((40, 56), np.uint8), ((40, 56, 3), np.uint8), ((30, 20), np.uint16)])
def test_recording_round_trip_is_bit_exact(tmp_path: Path, shape: tuple[int, ...], dtype: type) -> None:
    frames = _camera_frames(6, shape, dtype)
    with ListSource(frames) as src:
        summary = record(src, tmp_path / "rec")
    assert summary.frames == 6 and summary.layout == "mono"
    manifest = json.loads((tmp_path / "rec" / "manifest.json").read_text())
    assert manifest["format"] == "edgecal-recording" and len(manifest["frames"]) == 6
    with open_source(f"replay:{tmp_path / 'rec'}?pace=fast") as rep:
        out = list(rep)
    assert len(out) == 6
    for a, b in zip(frames, out):
        assert b.image.dtype == a.image.dtype and b.image.shape == a.image.shape
        assert np.array_equal(a.image, b.image)
        assert (b.stamp_ns, b.seq, b.camera_id, b.exposure_us, b.gain_db) == (
            a.stamp_ns, a.seq, a.camera_id, a.exposure_us, a.gain_db)


def test_stereo_recording_round_trip_and_stereo_folder(tmp_path: Path) -> None:
    left = _camera_frames(4, (24, 32), np.uint8)
    right = [Frame(render_frame(100 + i, (24, 32)), f.stamp_ns + 700, f.recv_ns, f.seq, "cam1")
             for i, f in enumerate(left)]

    class Pairs(ListSource, StereoSource):
        pass

    with Pairs([StereoFrame(a, b) for a, b in zip(left, right)]) as src:
        assert record(src, tmp_path / "rec").layout == "stereo"
    assert sorted(p.name for p in (tmp_path / "rec").iterdir()) == ["left", "manifest.json", "right"]
    src = open_source(f"replay:{tmp_path / 'rec'}?pace=fast")
    assert isinstance(src, StereoSource)
    with src:
        pairs = list(src)
    assert len(pairs) == 4
    for p, a, b in zip(pairs, left, right):
        assert np.array_equal(p.left.image, a.image) and np.array_equal(p.right.image, b.image)
        assert (p.left.stamp_ns, p.right.stamp_ns, p.skew_ns) == (a.stamp_ns, b.stamp_ns, 700)
    # A rendered stereo sequence (left/ and right/ image folders, no manifest) is a stereo source too.
    (tmp_path / "seq" / "left").mkdir(parents=True)
    (tmp_path / "seq" / "right").mkdir()
    for i in range(3):
        cv2.imwrite(str(tmp_path / "seq" / "left" / f"{i:03d}.png"), render_frame(i))
        cv2.imwrite(str(tmp_path / "seq" / "right" / f"{i:03d}.png"), render_frame(50 + i))
    with open_source(f"replay:{tmp_path / 'seq'}?pace=fast&fps=20") as seq:
        assert isinstance(seq, StereoSource)
        pairs = list(seq)
    assert [p.left.stamp_ns for p in pairs] == [0, 50_000_000, 100_000_000]
    assert np.array_equal(pairs[2].right.image, render_frame(52))


def test_replay_paces_at_the_recorded_rate_and_loops(tmp_path: Path) -> None:
    folder = tmp_path / "imgs"
    folder.mkdir()
    for i in range(3):
        cv2.imwrite(str(folder / f"f{i}.png"), render_frame(i))
    with open_source(f"replay:{folder}?fps=20") as src:
        t0 = time.monotonic()
        frames = list(src)
        elapsed = time.monotonic() - t0
    assert len(frames) == 3 and elapsed >= 0.095  # two 50 ms intervals, slept for in real time
    with open_source(f"replay:{folder}?fps=20&pace=fast&loop=true") as src:
        looped = [src.read() for _ in range(7)]
    assert [f.seq for f in looped] == list(range(7))
    assert np.all(np.diff([f.stamp_ns for f in looped]) == 50_000_000)
    assert np.array_equal(looped[4].image, frames[1].image)


def test_replay_of_a_video_file(tmp_path: Path) -> None:
    path = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 25.0, (64, 48))
    if not writer.isOpened():
        pytest.skip("this OpenCV build cannot write MJPG AVI")
    for i in range(5):
        writer.write(render_frame(i, (48, 64, 3)))
    writer.release()
    with open_source(f"replay:{path}?pace=fast") as src:
        frames = list(src)
    assert len(frames) == 5 and frames[0].image.shape == (48, 64, 3)
    assert [f.stamp_ns for f in frames] == [i * 40_000_000 for i in range(5)]


def test_recorder_never_clobbers_without_force(tmp_path: Path) -> None:
    out = tmp_path / "rec"
    with ListSource(_camera_frames(2, (8, 8), np.uint8)) as src:
        record(src, out)
    with ListSource(_camera_frames(1, (8, 8), np.uint8)) as src, pytest.raises(InputError, match="not empty"):
        record(src, out)
    with ListSource(_camera_frames(1, (8, 8), np.uint8)) as src:
        assert record(src, out, force=True).frames == 1
    assert len(json.loads((out / "manifest.json").read_text())["frames"]) == 1
    assert sorted(p.name for p in (out / "frames").iterdir()) == ["000000.png"]


def test_record_stops_at_frames_or_seconds(tmp_path: Path) -> None:
    with ListSource(_camera_frames(10, (8, 8), np.uint8)) as src:
        assert record(src, tmp_path / "a", frames=3).frames == 3
    with ListSource(_camera_frames(50, (8, 8), np.uint8), period_s=0.01) as src:
        n = record(src, tmp_path / "b", seconds=0.1).frames
    assert 3 <= n < 50


def test_replay_errors_name_the_path(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="no such file or folder"):
        open_source(f"replay:{tmp_path / 'missing'}")
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="holds no images"):
        open_source(f"replay:{tmp_path / 'empty'}")
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "manifest.json").write_text("{}")
    with pytest.raises(InputError, match="not an edgecal recording"):
        open_source(f"replay:{tmp_path / 'bad'}")
    (tmp_path / "junk").mkdir()
    (tmp_path / "junk" / "a.png").write_bytes(b"not a png")
    with open_source(f"replay:{tmp_path / 'junk'}") as src, pytest.raises(InputError, match="a.png: not a readable"):
        src.read()
    with pytest.raises(RuntimeError, match=r"read\(\) before open\(\)"):
        open_source(f"replay:{tmp_path / 'junk'}").read()


def test_rendered_sequence_replays_with_its_truth_stamps(tmp_path: Path) -> None:
    # The layout `edgecal render robot` writes: left/, right/ and truth.json listing each pair's stamp.
    for side in ("left", "right"):
        (tmp_path / side).mkdir()
    frames = []
    for i, stamp in enumerate([0, 33_000_000, 67_500_000]):
        for side, off in (("left", 0), ("right", 10)):
            cv2.imwrite(str(tmp_path / side / f"{i:06d}.png"), render_frame(i + off))
        frames.append({"index": i, "stamp_ns": stamp, "left": f"left/{i:06d}.png", "right": f"right/{i:06d}.png"})
    (tmp_path / "truth.json").write_text(json.dumps({"format": "edgecal-synth-robot/1", "fps": 30.0,
                                                    "frames": frames}))
    with open_source(f"replay:{tmp_path}?pace=fast") as src:
        pairs = list(src)
    assert [p.left.stamp_ns for p in pairs] == [0, 33_000_000, 67_500_000]
    assert all(p.skew_ns == 0 for p in pairs) and [p.right.seq for p in pairs] == [0, 1, 2]
    assert np.array_equal(pairs[1].right.image, render_frame(11))


def test_a_camera_fault_during_recording_keeps_what_was_recorded(tmp_path: Path) -> None:
    frames = _camera_frames(3, (8, 8), np.uint8)

    class Unplugged(ListSource):
        def _read(self, timeout_s):
            if self.i >= len(self.frames):
                raise DeviceLost("cam0: lost contact with the camera")
            return super()._read(timeout_s)

    with Unplugged(frames) as src, pytest.raises(DeviceError, match="lost contact"):
        record(src, tmp_path / "rec", frames=10)
    with open_source(f"replay:{tmp_path / 'rec'}?pace=fast") as rep:
        assert [f.stamp_ns for f in rep] == [f.stamp_ns for f in frames]


def _write_mono_folder(folder: Path, n: int, shape: tuple[int, ...] = (40, 56, 3)) -> Path:
    folder.mkdir(parents=True)
    for i in range(n):
        cv2.imwrite(str(folder / f"{i:03d}.png"), render_frame(i, shape))
    return folder


def _write_stereo_recording(folder: Path, n: int) -> Path:
    left = _camera_frames(n, (24, 32), np.uint16)
    right = [Frame(render_frame(100 + i, (24, 32), np.uint16), f.stamp_ns + 700, f.recv_ns, f.seq, "cam1")
             for i, f in enumerate(left)]

    class Pairs(ListSource, StereoSource):
        pass

    with Pairs([StereoFrame(a, b) for a, b in zip(left, right)]) as src:
        record(src, folder)
    return folder


def _write_stereo_folder(folder: Path, n: int) -> Path:
    for side, off in (("left", 0), ("right", 50)):
        (folder / side).mkdir(parents=True)
        for i in range(n):
            cv2.imwrite(str(folder / side / f"{i:03d}.png"), render_frame(off + i))
    return folder


def _frames_of(item: Frame | StereoFrame) -> list[Frame]:
    return [item.left, item.right] if isinstance(item, StereoFrame) else [item]


@pytest.mark.parametrize("layout", ["mono folder", "stereo folder", "stereo recording"])
def test_preload_gives_the_same_frames_and_stamps_over_two_loop_passes(tmp_path: Path, layout: str) -> None:
    n = 4
    write = {"mono folder": _write_mono_folder, "stereo folder": _write_stereo_folder,
             "stereo recording": _write_stereo_recording}[layout]
    path = write(tmp_path / "seq", n)
    runs = {}
    for preload in ("false", "true"):
        with open_source(f"replay:{path}?pace=fast&loop=true&fps=25&preload={preload}") as src:
            runs[preload] = [src.read() for _ in range(2 * n)]
    for plain, pre in zip(runs["false"], runs["true"]):
        assert type(plain) is type(pre)
        for a, b in zip(_frames_of(plain), _frames_of(pre)):
            assert b.image.dtype == a.image.dtype and np.array_equal(a.image, b.image)
            assert (b.stamp_ns, b.seq, b.camera_id, b.exposure_us, b.gain_db) == (
                a.stamp_ns, a.seq, a.camera_id, a.exposure_us, a.gain_db)
    # The second pass hands out the same decoded arrays, not decoded again.
    first, second = _frames_of(runs["true"][0]), _frames_of(runs["true"][n])
    assert all(a.image is b.image for a, b in zip(first, second))
    assert second[0].seq == first[0].seq + n and second[0].stamp_ns > first[-1].stamp_ns


def test_preloaded_frames_are_read_only_and_released_by_close(tmp_path: Path) -> None:
    import weakref

    folder = _write_mono_folder(tmp_path / "imgs", 3)
    src = open_source(f"replay:{folder}?pace=fast&loop=true&preload=true")
    with src:
        frame = src.read()
        assert not frame.image.flags.writeable
        with pytest.raises(ValueError, match="read-only"):
            frame.image[0, 0] = 0          # a consumer cannot corrupt the next loop pass
        ref = weakref.ref(frame.image)
        del frame
        assert ref() is not None           # still held by the replay for the next pass
    assert ref() is None                   # close() let go of it
    with src:                              # and a re-open decodes again
        assert np.array_equal(src.read().image, render_frame(0, (40, 56, 3)))


def test_preload_is_paced_like_a_plain_replay(tmp_path: Path) -> None:
    folder = _write_mono_folder(tmp_path / "imgs", 3)
    with open_source(f"replay:{folder}?fps=20&preload=true") as src:
        t0 = time.monotonic()
        frames = list(src)
        elapsed = time.monotonic() - t0
    assert len(frames) == 3 and elapsed >= 0.095  # two 50 ms intervals, slept for in real time


def test_preload_refuses_more_memory_than_its_bound_before_decoding_all(tmp_path: Path,
                                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    import edgecal.drivers.preload as preload

    folder = _write_mono_folder(tmp_path / "imgs", 10, (100, 100, 3))   # 10 x 30000 bytes decoded
    decoded = []
    real = preload.read_image_file
    monkeypatch.setattr(preload, "read_image_file", lambda p, *a: decoded.append(p) or real(p, *a))
    src = open_source(f"replay:{folder}?preload=true&preload_max_mb=0.1")
    with pytest.raises(InputError, match=r"imgs: preloading 10 images needs about 0\.29 MB, more than "
                                         r"preload_max_mb \(0\.1\); raise preload_max_mb or set preload: false"):
        src.open()
    assert len(decoded) == 1                       # estimated from the first image, the rest never decoded
    seq = _write_stereo_folder(tmp_path / "seq", 10)  # 2 x 10 x 3072 bytes
    decoded.clear()
    with pytest.raises(InputError, match="seq: preloading 20 images needs about 0.06 MB"):
        open_source(f"replay:{seq}?preload=true&preload_max_mb=0.05").open()
    assert len(decoded) == 2                       # one left and one right image
    with open_source(f"replay:{seq}?pace=fast&preload=true&preload_max_mb=0.1") as src:
        assert len(list(src)) == 10


@pytest.mark.parametrize("stereo", [False, True])
def test_a_corrupt_file_behaves_the_same_with_and_without_preload(tmp_path: Path, stereo: bool) -> None:
    if stereo:
        path = _write_stereo_folder(tmp_path / "seq", 3)
        (path / "right" / "001.png").write_bytes(b"not a png")
    else:
        path = _write_mono_folder(tmp_path / "imgs", 3)
        (path / "001.png").write_bytes((path / "001.png").read_bytes()[:60])   # truncated
    outcomes = {}
    for preload in ("false", "true"):
        got: list = []
        with open_source(f"replay:{path}?pace=fast&loop=true&preload={preload}") as src:
            for _ in range(6):             # two passes: the bad frame fails each time, reading goes on
                try:
                    item = src.read()
                except InputError as exc:
                    got.append(str(exc))
                else:
                    got.append([(f.stamp_ns, f.seq, f.image.tobytes()) for f in _frames_of(item)])
        outcomes[preload] = got
    assert outcomes["true"] == outcomes["false"]
    assert isinstance(outcomes["true"][1], str) and "001.png" in outcomes["true"][1]
    assert outcomes["true"][4] == outcomes["true"][1] and not isinstance(outcomes["true"][2], str)


def test_preload_settings_are_validated_and_refused_for_a_video(tmp_path: Path) -> None:
    from edgecal.drivers import parse_uri, spec_from_config
    from edgecal.errors import ConfigError

    s = spec_from_config({"driver": "replay", "path": "runs/a", "preload": True, "preload_max_mb": 512}, "cam.yaml")
    assert (s.settings.preload, s.settings.preload_max_mb) == (True, 512.0)
    assert (parse_uri("replay:x").settings.preload, parse_uri("replay:x").settings.preload_max_mb) == (False, 2048.0)
    with pytest.raises(ConfigError, match="field 'preload' must be true or false"):
        parse_uri("replay:x?preload=2")
    with pytest.raises(ConfigError, match="field 'preload_max_mb' must be greater than 0"):
        parse_uri("replay:x?preload_max_mb=0")
    with pytest.raises(ConfigError, match="field 'preload' is not a setting of the v4l2 driver"):
        parse_uri("v4l2:/dev/video0?preload=true")
    video = tmp_path / "clip.avi"
    video.write_bytes(b"\0" * 64)      # refused by its kind before it is opened
    with pytest.raises(InputError, match=r"clip\.avi: preload works for image files only, not a video"):
        open_source(f"replay:{video}?preload=true")


@pytest.mark.parametrize("layout", ["mono folder", "stereo folder"])
def test_latest_frame_wins_over_a_fast_replay_waits_for_the_reader(tmp_path: Path, layout: str) -> None:
    """pace: fast makes frames as fast as they are read: the latest-frame-wins thread must not spin making
    and overwriting them (it did: 370,000 drops per second) but hand each one over in turn."""
    write = {"mono folder": _write_mono_folder, "stereo folder": _write_stereo_folder}[layout]
    path = write(tmp_path / "seq", 3)
    with open_source(f"replay:{path}?pace=fast&loop=true&latest_only=true&preload=true") as src:
        seqs = []
        for _ in range(6):
            time.sleep(0.05)                 # a slow consumer
            seqs.append(_frames_of(src.read(1.0))[0].seq)
        assert src.dropped == 0
    assert seqs == list(range(6))
