"""The loop's sinks: the MCAP pose log (ROS 2 messages, kill-safe, rotating), frame names and stamps, and the
pose loop over an MCAP recording of the rendered robot sequence."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Channel, Message, Schema
from mcap.stream_reader import StreamReader
from mcap_ros2.decoder import DecoderFactory

from edgecal.drivers import open_source, record
from edgecal.errors import ConfigError, InputError
from edgecal.mcap_writer import McapLogWriter, numbered
from edgecal.publish.sinks import FrameOutput, Sink, fan_out
from edgecal.stream import LiveLoop, load_live_config

from .live_fixtures import free_endpoint, render_robot, wait_until, write_config

N_FRAMES = 4


@pytest.fixture(scope="module")
def sequence(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict]:
    folder = tmp_path_factory.mktemp("robot")
    return folder, render_robot(folder, N_FRAMES, seed=11)


def read_log(path: Path) -> dict[str, list]:
    """Every message of an MCAP file by topic, decoded (ROS 2 with mcap-ros2-support, JSON with json), read
    record by record so that a file without its summary (a killed writer) is read as far as it goes."""
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    factory = DecoderFactory()
    out: dict[str, list] = {}
    with path.open("rb") as f:
        try:
            for rec in StreamReader(f).records:
                if isinstance(rec, Schema):
                    schemas[rec.id] = rec
                elif isinstance(rec, Channel):
                    channels[rec.id] = rec
                elif isinstance(rec, Message):
                    ch = channels[rec.channel_id]
                    if ch.message_encoding == "json":
                        msg = json.loads(rec.data)
                    else:
                        msg = factory.decoder_for(ch.message_encoding, schemas[ch.schema_id])(rec.data)
                    out.setdefault(ch.topic, []).append((rec.log_time, msg))
        except (McapError, EOFError):
            pass                                  # the end of a file cut short
    return out


def _config(tmp_path: Path, folder: Path, publish: dict, source: dict | None = None) -> Path:
    cfg = write_config(tmp_path / "live.yaml", folder, free_endpoint(),
                       source_extra={"pace": "fast", "latest_only": False}, loop={"stop_at_end": True})
    doc = yaml.safe_load(cfg.read_text())
    doc["publish"].update(publish)
    if source is not None:
        doc["source"] = {"latest_only": False, **source}    # every frame, as the replay above
    cfg.write_text(yaml.safe_dump(doc))
    return cfg


def test_record_sink_writes_ros_pose_tf_and_status(sequence: tuple[Path, dict], tmp_path: Path) -> None:
    folder, truth = sequence
    out = tmp_path / "poses.mcap"
    cfg = _config(tmp_path, folder, {"record": str(out), "frame_id": "cam_rig", "child_frame_id": "base_link"})
    loop = LiveLoop(load_live_config(cfg))
    assert loop.run() == 0
    with out.open("rb") as f:                     # a clean stop leaves the summary: indexed reading works
        summary = make_reader(f).get_summary()
    assert summary is not None and summary.statistics.message_count > 0
    log = read_log(out)
    poses, tfs, infos = log["/edgecal/pose"], log["/tf"], log["/edgecal/pose_json"]
    assert len(infos) == N_FRAMES and len(poses) == len(tfs) == sum(m["valid"] for _, m in infos) == N_FRAMES
    assert log["/edgecal/status"][-1][1]["state"] == "stopping"
    assert log["/edgecal/status"][-1][1]["sinks"] == {"mcap": {"dropped": 0, "failures": 0}}
    for (t_log, p), (_, tf), (_, info), frame in zip(poses, tfs, infos, truth["frames"]):
        assert p.header.frame_id == "cam_rig" and info["frame_id"] == "cam_rig"
        assert info["child_frame_id"] == "base_link" and tf.transforms[0].child_frame_id == "base_link"
        stamp = p.header.stamp.sec * 10**9 + p.header.stamp.nanosec
        assert stamp == info["stamp_ns"] == t_log                        # publish.stamp: monotonic (default)
        pos = [p.pose.pose.position.x, p.pose.pose.position.y, p.pose.pose.position.z]
        q = p.pose.pose.orientation
        assert np.allclose(pos, info["pose"]["position_m"]) and np.allclose([q.x, q.y, q.z, q.w],
                                                                          info["pose"]["orientation_xyzw"])
        assert 1000 * np.linalg.norm(np.array(pos) - frame["t_rig_robot_m"]) < 1.0
        assert np.allclose(np.array(p.pose.covariance), info["covariance"])
        tr = tf.transforms[0].transform.translation
        assert np.allclose([tr.x, tr.y, tr.z], pos) and tf.transforms[0].header.frame_id == "cam_rig"


def test_record_sink_realtime_stamps(sequence: tuple[Path, dict], tmp_path: Path) -> None:
    folder, _ = sequence
    out = tmp_path / "rt.mcap"
    cfg = _config(tmp_path, folder, {"record": {"path": str(out), "flush_s": 0.2}, "stamp": "realtime"})
    before = time.time_ns()
    assert LiveLoop(load_live_config(cfg)).run() == 0
    after = time.time_ns()
    poses = read_log(out)["/edgecal/pose"]
    stamps = [p.header.stamp.sec * 10**9 + p.header.stamp.nanosec for _, p in poses]
    assert len(stamps) == N_FRAMES and all(before <= s <= after for s in stamps)   # CLOCK_REALTIME of capture


def test_pose_loop_over_mcap_gives_the_poses_of_the_png_replay(sequence: tuple[Path, dict], tmp_path: Path) -> None:
    folder, _ = sequence
    with open_source(f"replay:{folder}?pace=fast") as src:
        record(src, tmp_path / "robot.mcap")
    from_png = tmp_path / "png.mcap"
    from_mcap = tmp_path / "mcap.mcap"
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    cfg = _config(tmp_path / "a", folder, {"record": str(from_png)})
    assert LiveLoop(load_live_config(cfg)).run() == 0
    src = {"uri": f"mcap:{tmp_path / 'robot.mcap'}", "left": "/left/image_raw", "right": "/right/image_raw",
           "pace": "fast"}
    cfg = _config(tmp_path / "b", folder, {"record": str(from_mcap)}, source=src)
    assert LiveLoop(load_live_config(cfg)).run() == 0
    a = [m for _, m in read_log(from_png)["/edgecal/pose_json"]]
    b = [m for _, m in read_log(from_mcap)["/edgecal/pose_json"]]
    assert len(a) == len(b) == N_FRAMES
    for x, y in zip(a, b):
        assert x["stamp_ns"] == y["stamp_ns"] and x["valid"] and y["valid"]
        assert x["pose"] == y["pose"] and x["covariance"] == y["covariance"]      # bit for bit
        assert x["quality"]["corners_both"] == y["quality"]["corners_both"]


def test_a_killed_daemon_leaves_a_readable_log(sequence: tuple[Path, dict], tmp_path: Path) -> None:
    folder, _ = sequence
    out = tmp_path / "killed.mcap"
    cfg = _config(tmp_path, folder, {"record": {"path": str(out), "flush_s": 0.2}})
    doc = yaml.safe_load(cfg.read_text())
    doc["source"]["loop"] = True
    doc["loop"]["stop_at_end"] = False
    cfg.write_text(yaml.safe_dump(doc))
    env = {**os.environ, "NUMBA_NUM_THREADS": "1"}
    proc = subprocess.Popen([sys.executable, "-m", "edgecal", "run", "--config", str(cfg)], env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        assert wait_until(lambda: out.exists() and len(read_log(out).get("/edgecal/pose", [])) >= 8, 90.0)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
    log = read_log(out)                                 # no summary, no footer: read as far as it goes
    poses = log["/edgecal/pose"]
    assert len(poses) >= 8 and len(log["/edgecal/status"]) >= 1
    stamps = [t for t, _ in poses]
    assert stamps == sorted(stamps) or len(set(stamps)) > 1
    # edgecal's own reader takes it too (the images topics are absent, the listing works).
    from edgecal.drivers.mcap_source import McapLog
    assert McapLog(out).topics()["/edgecal/pose"].count >= 8
    # A restart never overwrites it: the next run writes killed.1.mcap.
    cfg2 = _config(tmp_path, folder, {"record": str(out)})
    assert LiveLoop(load_live_config(cfg2)).run() == 0
    assert numbered(out, 1).exists() and len(read_log(out)["/edgecal/pose"]) == len(poses)


def test_log_rotates_by_size(tmp_path: Path) -> None:
    base = tmp_path / "r.mcap"
    w = McapLogWriter(base, max_bytes=20_000, flush_s=0.0)
    for i in range(400):
        w.write_json("/edgecal/status", "edgecal.status", {"i": i, "pad": "x" * 200}, i)
    w.close()
    assert len(w.files) >= 3 and w.files[0] == base and w.files[1] == tmp_path / "r.1.mcap"
    got = []
    for f in w.files:
        with f.open("rb") as fh:
            assert make_reader(fh).get_summary() is not None       # every finished part is complete
        got += [m["i"] for _, m in read_log(f)["/edgecal/status"]]
    assert got == list(range(400))
    with pytest.raises(InputError, match="exists"):
        McapLogWriter(base)


class _Failing(Sink):
    name = "failing"

    def __init__(self) -> None:
        self.calls = 0

    def frame(self, out: FrameOutput) -> None:
        self.calls += 1
        raise OSError("disk full")

    def status(self, message: dict) -> None:
        raise OSError("disk full")

    def close(self) -> None:
        pass


class _Collecting(_Failing):
    name = "collecting"

    def frame(self, out: FrameOutput) -> None:
        self.calls += 1


def test_a_failing_sink_does_not_stop_the_others() -> None:
    bad, good = _Failing(), _Collecting()
    for _ in range(3):
        fan_out([bad, good], "frame", None)
    assert bad.failures == 3 and good.calls == 3 and good.failures == 0


@pytest.mark.parametrize("publish, field", [
    ({"record": "poses.txt"}, "publish.record"),
    ({"record": {"path": "p.mcap", "max_mb": 0}}, "publish.record.max_mb"),
    ({"record": {"path": "p.mcap", "size": 3}}, "publish.record.size"),
    ({"frame_id": "my rig"}, "publish.frame_id"),
    ({"child_frame_id": "rig"}, "publish.child_frame_id"),
    ({"stamp": "gps"}, "publish.stamp"),
    ({"foxglove": {"host": "0.0.0.0"}}, "publish.foxglove.host"),
    ({"foxglove": {"port": 70000}}, "publish.foxglove.port"),
    ({"foxglove": {"rate": 3}}, "publish.foxglove.rate"),
])
def test_bad_output_fields_are_named(sequence: tuple[Path, dict], tmp_path: Path, publish: dict, field: str) -> None:
    folder, _ = sequence
    cfg = _config(tmp_path, folder, publish)
    with pytest.raises(ConfigError, match=f"field '{field}'"):
        load_live_config(cfg)


def test_reload_moves_the_log_and_keeps_the_old_one_on_a_bad_path(sequence: tuple[Path, dict], tmp_path: Path) -> None:
    import threading
    folder, _ = sequence
    first, second = tmp_path / "first.mcap", tmp_path / "second.mcap"
    cfg = _config(tmp_path, folder, {"record": {"path": str(first), "flush_s": 0.1}})
    doc = yaml.safe_load(cfg.read_text())
    doc["source"]["loop"] = True
    doc["loop"]["stop_at_end"] = False
    cfg.write_text(yaml.safe_dump(doc))
    loop = LiveLoop(load_live_config(cfg))
    th = threading.Thread(target=loop.run)
    th.start()
    try:
        assert wait_until(lambda: first.exists() and len(read_log(first).get("/edgecal/pose", [])) >= 2, 60.0)
        doc["publish"]["record"] = {"path": "/proc/no/such/dir/x.mcap"}      # cannot be created: kept running
        cfg.write_text(yaml.safe_dump(doc))
        loop.request_reload()
        assert wait_until(lambda: loop.stats.reload_failures == 1, 20.0)
        doc["publish"]["record"] = {"path": str(second), "flush_s": 0.1}
        cfg.write_text(yaml.safe_dump(doc))
        loop.request_reload()
        assert wait_until(lambda: second.exists() and len(read_log(second).get("/edgecal/pose", [])) >= 2, 60.0)
    finally:
        loop.request_stop()
        th.join(20)
    assert not th.is_alive()
    with first.open("rb") as f:                        # the first log was finished when it was replaced
        assert make_reader(f).get_summary() is not None
