"""mcap: and rosbag: sources over logs written by the ROS libraries themselves."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from edgecal.drivers import StereoSource, open_source
from edgecal.errors import ConfigError, InputError

from .ros_logs import LogImage, gradient, write_mcap, write_rosbag

T0 = 1_700_000_000_123_456_789


def _stamps(n: int, period: int = 33_333_333, jitter: int = 0) -> list[int]:
    rng = np.random.default_rng(3)
    return [T0 + i * period + (int(rng.integers(-jitter, jitter + 1)) if jitter else 0) for i in range(n)]


def _read_all(uri: str) -> list:
    with open_source(uri) as src:
        return list(src)


@pytest.mark.parametrize("encoding, shape, dtype, pad, big", [
    ("mono8", (24, 32), np.uint8, 0, False),
    ("mono8", (24, 30), np.uint8, 2, False),           # rows padded: step > width
    ("mono16", (20, 16), np.uint16, 0, False),
    ("mono16", (20, 16), np.uint16, 0, True),          # big-endian data
    ("bgr8", (24, 32, 3), np.uint8, 4, False),
])
def test_raw_images_come_back_unchanged(tmp_path: Path, encoding: str, shape: tuple, dtype: type, pad: int,
                                        big: bool) -> None:
    stamps = _stamps(5, jitter=2_000_000)
    items = [LogImage("/cam/image_raw", s, gradient(i, shape, dtype), encoding, pad, big) for i, s in enumerate(stamps)]
    path = write_mcap(tmp_path / "a.mcap", items, {"/chatter": 3})
    frames = _read_all(f"mcap:{path}?topic=/cam/image_raw&pace=fast")
    assert [f.seq for f in frames] == list(range(5))
    assert [f.stamp_ns for f in frames] == stamps                     # the header stamp, not the log time
    assert {f.camera_id for f in frames} == {"/cam/image_raw"}
    for item, f in zip(items, frames):
        assert f.image.dtype == dtype and f.image.shape == shape
        assert np.array_equal(f.image, item.image)


def test_colour_encodings_become_bgr(tmp_path: Path) -> None:
    bgr = gradient(1, (16, 20, 3))
    bgra = np.dstack([bgr, np.full(bgr.shape[:2], 255, np.uint8)])
    items = [LogImage("/rgb", T0, bgr[..., ::-1].copy(), "rgb8"),
             LogImage("/bgra", T0, bgra, "bgra8"),
             LogImage("/rgba", T0, bgra[..., [2, 1, 0, 3]].copy(), "rgba8")]
    path = write_mcap(tmp_path / "c.mcap", items)
    for topic in ("/rgb", "/bgra", "/rgba"):
        (f,) = _read_all(f"mcap:{path}?topic={topic}&pace=fast")
        assert np.array_equal(f.image, bgr), topic


@pytest.mark.parametrize("pattern", ["rggb", "bggr", "gbrg", "grbg"])
def test_bayer_is_demosaiced_with_the_right_colours(tmp_path: Path, pattern: str) -> None:
    # A flat colour scene (B=40, G=120, R=220) seen through the named 2x2 filter block.
    value = {"r": 220, "g": 120, "b": 40}
    mosaic = np.zeros((16, 16), np.uint8)
    for k, ch in enumerate(pattern):
        mosaic[k // 2::2, k % 2::2] = value[ch]
    path = write_mcap(tmp_path / "b.mcap", [LogImage("/raw", T0, mosaic, f"bayer_{pattern}8")])
    (f,) = _read_all(f"mcap:{path}?topic=/raw&pace=fast")
    assert f.image.shape == (16, 16, 3)
    assert np.abs(f.image[4:12, 4:12].astype(int) - [40, 120, 220]).max() <= 1


def test_compressed_images(tmp_path: Path) -> None:
    grey = gradient(2, (32, 40))
    colour = cv2.GaussianBlur(gradient(3, (32, 40, 3)), (5, 5), 2)
    items = [LogImage("/png", T0, grey, "png"), LogImage("/jpeg", T0 + 5, colour, "jpeg")]
    path = write_mcap(tmp_path / "z.mcap", items)
    (png,) = _read_all(f"mcap:{path}?topic=/png&pace=fast")
    assert np.array_equal(png.image, grey)                            # PNG is lossless
    (jpg,) = _read_all(f"mcap:{path}?topic=/jpeg&pace=fast")
    assert jpg.image.shape == colour.shape and jpg.stamp_ns == T0 + 5
    assert np.abs(jpg.image.astype(int) - colour).mean() < 4          # JPEG is close


def test_stereo_topics_are_paired_by_header_stamp(tmp_path: Path) -> None:
    stamps = _stamps(8)
    items = []
    for i, s in enumerate(stamps):
        items.append(LogImage("/left", s, gradient(i)))
        if i != 3:                                                    # one right frame lost
            items.append(LogImage("/right", s + 400_000 * (i % 2), gradient(100 + i)))
    path = write_mcap(tmp_path / "s.mcap", items)
    src = open_source(f"mcap:{path}?left=/left&right=/right&pace=fast&max_skew_ms=1")
    assert isinstance(src, StereoSource)
    with src:
        pairs = list(src)
        dropped = src.dropped
    assert len(pairs) == 7 and dropped == 1
    assert [p.left.stamp_ns for p in pairs] == [s for i, s in enumerate(stamps) if i != 3]
    assert all(p.skew_ns <= 400_000 for p in pairs)
    assert np.array_equal(pairs[3].right.image, gradient(104))
    assert (pairs[0].left.camera_id, pairs[0].right.camera_id) == ("/left", "/right")


def test_loop_keeps_stamps_and_seq_increasing(tmp_path: Path) -> None:
    stamps = _stamps(4)
    path = write_mcap(tmp_path / "l.mcap", [LogImage("/cam", s, gradient(i)) for i, s in enumerate(stamps)])
    with open_source(f"mcap:{path}?topic=/cam&pace=fast&loop=true") as src:
        frames = [src.read() for _ in range(10)]
    assert [f.seq for f in frames] == list(range(10))
    assert np.all(np.diff([f.stamp_ns for f in frames]) > 0)
    assert frames[4].stamp_ns - frames[0].stamp_ns == 4 * 33_333_333
    assert np.array_equal(frames[9].image, gradient(1))


def test_pace_realtime_is_the_recorded_pace(tmp_path: Path) -> None:
    path = write_mcap(tmp_path / "p.mcap", [LogImage("/cam", s, gradient(i)) for i, s in enumerate(_stamps(3))])
    with open_source(f"mcap:{path}?topic=/cam&pace=realtime") as src:
        frames = list(src)
    # Delivery follows the recorded intervals (a lower bound only: a loaded machine may be late).
    assert frames[2].recv_ns - frames[0].recv_ns >= 2 * 33_333_333 - 2_000_000


def test_missing_topic_lists_the_image_topics(tmp_path: Path) -> None:
    path = write_mcap(tmp_path / "t.mcap", [LogImage("/cam/left", T0, gradient(0)),
                                            LogImage("/cam/right", T0, gradient(0), "png")], {"/chatter": 2})
    with pytest.raises(InputError) as err:
        _read_all(f"mcap:{path}?topic=/camera/image_raw")
    text = str(err.value)
    assert "/camera/image_raw" in text and "/cam/left (Image, 1)" in text and "/cam/right (CompressedImage, 1)" in text
    assert "/chatter" not in text
    with pytest.raises(InputError, match="holds std_msgs/msg/String, not images"):
        _read_all(f"mcap:{path}?topic=/chatter")


def test_unsupported_encoding_is_named(tmp_path: Path) -> None:
    depth = np.zeros((4, 4), np.float32).view(np.uint8).reshape(4, 16)
    path = write_mcap(tmp_path / "u.mcap", [LogImage("/depth", T0, depth, "32FC1")])
    with pytest.raises(InputError, match="unsupported image encoding '32FC1'"):
        _read_all(f"mcap:{path}?topic=/depth&pace=fast")


def test_truncated_file_gives_the_frames_before_the_break_then_the_offset(tmp_path: Path) -> None:
    stamps = _stamps(40)
    # Small chunks, so that the cut falls inside a late chunk and the earlier ones are intact.
    path = write_mcap(tmp_path / "full.mcap", [LogImage("/cam", s, gradient(i, (48, 64))) for i, s in
                                               enumerate(stamps)], chunk_size=8000)
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[:int(len(data) * 0.6)])
    src = open_source(f"mcap:{cut}?topic=/cam&pace=fast")
    frames = []
    with src:
        with pytest.raises(InputError) as err:
            while True:
                f = src.read()
                assert f is not None
                frames.append(f)
        assert src.read() is None                                      # the pass has ended
    assert 10 < len(frames) < 40
    assert [f.stamp_ns for f in frames] == stamps[:len(frames)]
    message = str(err.value)
    assert "\n" not in message and "truncated or corrupt at byte" in message
    offset = int(message.split("at byte ")[1].split()[0])
    assert 0 < offset < len(data) * 0.6


def test_corrupt_chunk_is_reported_with_its_offset(tmp_path: Path) -> None:
    path = write_mcap(tmp_path / "c.mcap", [LogImage("/cam", s, gradient(i, (48, 64))) for i, s in
                                            enumerate(_stamps(30))], chunk_size=8000)
    data = bytearray(path.read_bytes())
    middle = len(data) // 2
    data[middle:middle + 64] = bytes(64)                               # garble bytes inside a chunk
    path.write_bytes(bytes(data))
    frames = []
    with open_source(f"mcap:{path}?topic=/cam&pace=fast") as src:
        with pytest.raises(InputError, match="truncated or corrupt at byte"):
            while (f := src.read()) is not None:
                frames.append(f)
    assert 0 < len(frames) < 30


def test_uri_needs_topics_and_a_file(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="'topic' is missing"):
        open_source("mcap:x.mcap")
    with pytest.raises(ConfigError, match="'right' is missing"):
        open_source("mcap:x.mcap?left=/l")
    with pytest.raises(ConfigError, match="cannot be given together with left/right"):
        open_source("rosbag:x.bag?topic=/a&left=/l&right=/r")
    with pytest.raises(InputError, match="no such MCAP file"):
        open_source(f"mcap:{tmp_path / 'absent.mcap'}?topic=/a")
    (tmp_path / "not.mcap").write_bytes(b"hello world, not an mcap")
    with pytest.raises(InputError, match="not an MCAP file"):
        open_source(f"mcap:{tmp_path / 'not.mcap'}?topic=/a")
    spec_section = {"uri": f"mcap:{tmp_path / 'x.mcap'}", "left": "/l", "right": "/r", "pace": "fast"}
    from edgecal.drivers import spec_from_config
    spec = spec_from_config(spec_section)
    assert (spec.settings.left, spec.settings.right, spec.settings.pace) == ("/l", "/r", "fast")


@pytest.mark.parametrize("kind", ["ros1", "sqlite3", "mcap"])
def test_rosbag_sources(tmp_path: Path, kind: str) -> None:
    stamps = _stamps(6)
    items = []
    for i, s in enumerate(stamps):
        items.append(LogImage("/left", s, gradient(i)))
        items.append(LogImage("/right", s + 1000, gradient(50 + i, (24, 32, 3)), "bgr8"))
        items.append(LogImage("/right/compressed", s + 1000, gradient(50 + i, (24, 32, 3)), "png"))
    path = write_rosbag(tmp_path / ("run.bag" if kind == "ros1" else "run"), items, kind)
    mono = _read_all(f"rosbag:{path}?topic=/left&pace=fast")
    assert [f.stamp_ns for f in mono] == stamps
    assert all(np.array_equal(f.image, gradient(i)) for i, f in enumerate(mono))
    pairs = _read_all(f"rosbag:{path}?left=/left&right=/right&pace=fast")
    assert len(pairs) == 6
    assert all(np.array_equal(p.right.image, gradient(50 + i, (24, 32, 3))) for i, p in enumerate(pairs))
    packed = _read_all(f"rosbag:{path}?left=/left&right=/right/compressed&pace=fast")
    assert all(np.array_equal(p.right.image, gradient(50 + i, (24, 32, 3))) for i, p in enumerate(packed))
    with pytest.raises(InputError, match=r"no topic '/nope'.*image topics: /left \(Image, 6\)"):
        _read_all(f"rosbag:{path}?topic=/nope")


def test_rosbag_refuses_what_is_not_a_bag(tmp_path: Path) -> None:
    (tmp_path / "x.bag").write_bytes(b"#ROSBAG V2.0\n" + bytes(100))
    with pytest.raises(InputError, match="x.bag"):
        _read_all(f"rosbag:{tmp_path / 'x.bag'}?topic=/a")
    with pytest.raises(InputError, match="for a bare .mcap file use mcap:"):
        _read_all(f"rosbag:{write_mcap(tmp_path / 'a.mcap', [])}?topic=/a")


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "edgecal", *args], capture_output=True, text=True, timeout=120)


def test_sources_command_lists_the_image_topics(tmp_path: Path) -> None:
    items = [LogImage("/left", s, gradient(i, (24, 32))) for i, s in enumerate(_stamps(3))]
    items += [LogImage("/right", s, gradient(i, (24, 32, 3)), "jpeg") for i, s in enumerate(_stamps(2))]
    path = write_mcap(tmp_path / "r.mcap", items, {"/chatter": 4})
    r = _cli("sources", str(path))
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    left = next(ln for ln in lines if ln.lstrip().startswith("/left"))
    right = next(ln for ln in lines if ln.lstrip().startswith("/right"))
    assert "3" in left.split() and "32x24" in left and "mono8" in left
    assert "2" in right.split() and "32x24" in right and "jpeg" in right
    assert "/chatter" in r.stdout                                     # listed, marked as not images
    bag = write_rosbag(tmp_path / "r.bag", items, "ros1")
    r = _cli("sources", str(bag))
    assert r.returncode == 0 and "/right" in r.stdout, r.stderr
    r = _cli("sources", str(tmp_path / "absent.mcap"))
    assert r.returncode == 2 and "absent.mcap" in r.stderr and "Traceback" not in r.stderr


def _camera_frames(n: int, shape: tuple, dtype: type = np.uint8) -> list:
    from edgecal.drivers import Frame
    stamps = _stamps(n, jitter=1_000_000)
    return [Frame(gradient(i, shape, dtype), s, s + 5, 7 + i, "cam") for i, s in enumerate(stamps)]


@pytest.mark.parametrize("shape, dtype", [((24, 32), np.uint8), ((24, 32, 3), np.uint8), ((20, 16), np.uint16)])
def test_record_to_mcap_round_trip(tmp_path: Path, shape: tuple, dtype: type) -> None:
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    from edgecal.drivers import record

    from .driver_frames import ListSource
    frames = _camera_frames(5, shape, dtype)
    out = tmp_path / "rec.mcap"
    with ListSource(frames) as src:
        summary = record(src, out)
    assert summary.frames == 5
    # Read back with the mcap libraries alone: standard ROS 2 Image messages.
    with out.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        decoded = list(reader.iter_decoded_messages())
        assert reader.get_summary().statistics.message_count == 5
    assert {(s.name, c.topic) for s, c, _, _ in decoded} == {("sensor_msgs/msg/Image", "/camera/image_raw")}
    first = decoded[0][3]
    assert (first.width, first.height, first.header.frame_id) == (shape[1], shape[0], "camera")
    assert first.encoding == ("bgr8" if len(shape) == 3 else "mono8" if dtype == np.uint8 else "mono16")
    # ... and through edgecal's mcap: source: the same pixels and stamps.
    back = _read_all(f"mcap:{out}?topic=/camera/image_raw&pace=fast")
    assert [f.stamp_ns for f in back] == [f.stamp_ns for f in frames]
    assert all(np.array_equal(a.image, b.image) and b.image.dtype == dtype for a, b in zip(frames, back))


def test_record_stereo_to_mcap_and_formats(tmp_path: Path) -> None:
    from edgecal.errors import InputError as _InputError
    stamps = _stamps(4)
    items = [LogImage("/l", s, gradient(i)) for i, s in enumerate(stamps)]
    items += [LogImage("/r", s + 100, gradient(20 + i)) for i, s in enumerate(stamps)]
    src_log = write_mcap(tmp_path / "src.mcap", items)
    out = tmp_path / "stereo.mcap"
    r = _cli("record", f"mcap:{src_log}?left=/l&right=/r&pace=fast", "--out", str(out))
    assert r.returncode == 0, r.stderr
    pairs = _read_all(f"mcap:{out}?left=/left/image_raw&right=/right/image_raw&pace=fast")
    assert [p.left.stamp_ns for p in pairs] == stamps and [p.right.stamp_ns for p in pairs] == [s + 100 for s in stamps]
    assert all(np.array_equal(p.right.image, gradient(20 + i)) for i, p in enumerate(pairs))
    # An existing file is not overwritten without --force.
    r = _cli("record", f"mcap:{src_log}?topic=/l&pace=fast", "--out", str(out))
    assert r.returncode == 2 and "exists" in r.stderr and "Traceback" not in r.stderr
    r = _cli("record", f"mcap:{src_log}?topic=/l&pace=fast", "--out", str(out), "--force", "--image", "png")
    assert r.returncode == 0, r.stderr
    mono = _read_all(f"mcap:{out}?topic=/camera/image_raw&pace=fast")
    assert all(np.array_equal(f.image, gradient(i)) for i, f in enumerate(mono))        # PNG: lossless
    r = _cli("record", f"mcap:{src_log}?topic=/l&pace=fast", "--out", str(tmp_path / "j.mcap"), "--image", "jpeg")
    assert r.returncode == 0, r.stderr
    assert len(_read_all(f"mcap:{tmp_path / 'j.mcap'}?topic=/camera/image_raw&pace=fast")) == 4
    with pytest.raises(_InputError, match="ends in .mcap"):
        from edgecal.mcap_writer import McapLogWriter
        McapLogWriter(tmp_path / "x.bag")


def test_a_killed_ros2_recorder_is_read_up_to_the_kill(tmp_path: Path) -> None:
    # What a killed `ros2 bag record` leaves: no metadata.yaml, an mcap file without its summary.
    stamps = _stamps(40)
    items = [LogImage("/cam", s, gradient(i, (240, 320))) for i, s in enumerate(stamps)]   # ~3 MiB: 3 chunks
    bag = write_rosbag(tmp_path / "killed", items, "mcap")
    (bag / "metadata.yaml").unlink()
    (part,) = bag.glob("*.mcap")
    data = part.read_bytes()
    part.write_bytes(data[:int(len(data) * 0.8)])
    frames = []
    with open_source(f"rosbag:{bag}?topic=/cam&pace=fast") as src:
        with pytest.raises(InputError, match=rf"truncated or corrupt at byte \d+ \({part.name}: "):
            while (f := src.read()) is not None:
                frames.append(f)
    assert 10 < len(frames) < 40 and [f.stamp_ns for f in frames] == stamps[:len(frames)]
    assert all(np.array_equal(f.image, gradient(i, (240, 320))) for i, f in enumerate(frames))


def test_bags_rosbags_cannot_open_are_one_line_with_the_repair(tmp_path: Path) -> None:
    items = [LogImage("/cam", s, gradient(i, (48, 64))) for i, s in enumerate(_stamps(20))]
    bag1 = write_rosbag(tmp_path / "cut.bag", items, "ros1")
    bag1.write_bytes(bag1.read_bytes()[:3000])
    with pytest.raises(InputError, match="rosbag reindex"):
        _read_all(f"rosbag:{bag1}?topic=/cam")
    bag2 = write_rosbag(tmp_path / "nometa", items, "sqlite3")
    (bag2 / "metadata.yaml").unlink()
    with pytest.raises(InputError, match="ros2 bag reindex"):
        _read_all(f"rosbag:{bag2}?topic=/cam")


def test_sources_command_warns_about_a_truncated_log(tmp_path: Path) -> None:
    path = write_mcap(tmp_path / "full.mcap", [LogImage("/cam", s, gradient(i, (48, 64))) for i, s in
                                               enumerate(_stamps(30))], chunk_size=8000)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes()[:len(path.read_bytes()) // 2])
    r = _cli("sources", str(cut))
    assert r.returncode == 0, r.stderr
    assert "/cam" in r.stdout and "truncated or corrupt at byte" in r.stdout


def test_garbage_anywhere_is_an_input_error_never_a_traceback(tmp_path: Path) -> None:
    path = write_mcap(tmp_path / "g.mcap", [LogImage("/cam", s, gradient(i, (48, 64))) for i, s in
                                            enumerate(_stamps(20))], chunk_size=8000)
    data = path.read_bytes()
    rng = np.random.default_rng(5)
    for k, at in enumerate(np.linspace(16, len(data) - 40, 25).astype(int)):
        bad = bytearray(data)
        bad[at:at + 24] = rng.integers(0, 256, 24, dtype=np.uint8).tobytes()
        p = tmp_path / f"g{k}.mcap"
        p.write_bytes(bytes(bad))
        try:
            with open_source(f"mcap:{p}?topic=/cam&pace=fast") as src:
                while src.read() is not None:
                    pass
        except InputError:
            pass                                     # a one-line message; any other exception fails the test
