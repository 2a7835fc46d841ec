"""The live loop end to end: a replayed rendered robot sequence, the real detector, a real subscriber."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from edgecal.errors import ConfigError
from edgecal.pose import Pose
from edgecal.publish import pose_message
from edgecal.publish.subscriber import MessageCollector
from edgecal.stream import LiveLoop, load_live_config
from edgecal.stream.frame_pipeline import grey_image
from edgecal.stream.loop import default_source_factory

from .live_fixtures import (
    free_endpoint,
    pose_errors,
    render_robot,
    run_in_thread,
    run_loop_until,
    wait_until,
    write_config,
)

N_FRAMES = 4


@pytest.fixture(scope="module")
def sequence(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict]:
    folder = tmp_path_factory.mktemp("robot")
    return folder, render_robot(folder, N_FRAMES)


def test_loop_publishes_poses_matching_truth(sequence: tuple[Path, dict], tmp_path: Path) -> None:
    folder, truth = sequence
    endpoint = free_endpoint()
    cfg = write_config(tmp_path / "live.yaml", folder, endpoint,
                       source_extra={"pace": "fast", "loop": True, "latest_only": False})
    # every frame's pose seen, and a status message
    sub = run_loop_until(cfg, endpoint, lambda s: {m["seq"] % N_FRAMES for m in s.of("pose")} == set(range(N_FRAMES))
                         and len(s.of("status")) >= 1)
    # The published message is pose_message's, whole: the loop adds or patches no field.
    built = pose_message(Pose.invalid("-"), 0, 0, 0, capture_ns=0, latency_from="receive", detection="searched")
    for msg in sub.of("pose"):
        assert list(msg) == list(built) and list(msg["quality"]) == list(built["quality"])
        assert msg["version"] == 1 and msg["valid"], msg["reason"]
        assert msg["quality"]["mode"] == "stereo"
        assert msg["latency_ns"] > 0 and msg["latency_from"] == "receive"
        err_mm, err_deg = pose_errors(msg, truth)
        assert err_mm < 1.0 and err_deg < 0.1    # the targets on clean renders: 1 mm, 0.1 deg
        cov = np.array(msg["covariance"]).reshape(6, 6)
        assert np.allclose(cov, cov.T) and np.all(np.linalg.eigvalsh(cov) > 0)
    status = sub.of("status")[-1]
    assert status["frames"] >= N_FRAMES and status["corrupt_frames"] == 0
    # Every pass of the looping replay is searched at its first frame and tracked after it.
    assert 0 < status["tracked_frames"] < status["frames"]
    assert set(status["latency_ms"]) == {"median", "p99"}


def test_loop_survives_corrupt_frames(sequence: tuple[Path, dict], tmp_path: Path) -> None:
    """A truncated PNG and a frame of the wrong size: each is counted and published as invalid, the loop goes on."""
    folder, _ = sequence
    bad = tmp_path / "bad"
    for side in ("left", "right"):
        (bad / side).mkdir(parents=True)
        for k in range(3):
            (bad / side / f"{k:06d}.png").write_bytes((folder / side / f"{k:06d}.png").read_bytes())
    (bad / "rig.yaml").write_bytes((folder / "rig.yaml").read_bytes())
    # frame 1: the left PNG is cut off; frame 2: the right image is half size.
    data = (bad / "left" / "000001.png").read_bytes()
    (bad / "left" / "000001.png").write_bytes(data[: len(data) // 3])
    import cv2
    small = cv2.imread(str(bad / "right" / "000002.png"), cv2.IMREAD_UNCHANGED)[::2, ::2]
    cv2.imwrite(str(bad / "right" / "000002.png"), small)
    endpoint = free_endpoint()
    cfg = write_config(tmp_path / "live.yaml", bad, endpoint, source_extra={"pace": "fast", "latest_only": False},
                       loop={"stop_at_end": True})
    import yaml
    doc = yaml.safe_load(cfg.read_text())
    doc["publish"]["hwm"] = 100         # the few messages of this run are never dropped at the send queue
    cfg.write_text(yaml.safe_dump(doc))
    sub = MessageCollector(endpoint)

    def open_when_subscribed(spec):
        # The loop publishes status while its source opens: once one has arrived, the subscription is in
        # place and no pose can be lost to ZeroMQ's slow joiner.
        assert sub.wait_for(lambda: len(sub.of("status")) >= 1, 30)
        return default_source_factory(spec)

    loop = LiveLoop(load_live_config(cfg), source_factory=open_when_subscribed)
    try:
        assert loop.run() == 0       # a clean stop lets the last messages leave the socket (CLOSE_LINGER_S)
        assert sub.wait_for(lambda: any(m["state"] == "stopping" for m in sub.of("status")), 5)
    finally:
        sub.close()
    assert loop.stats.corrupt_frames == 2
    poses = {m["seq"]: m for m in sub.of("pose")}
    assert poses[0]["valid"] and poses[0]["quality"]["mode"] == "stereo"
    assert 1 not in poses                           # the unreadable file never became a frame
    # The half-size right image is refused; the left camera alone still gives the pose (PnP).
    assert poses[2]["quality"]["mode"] == "mono-left" and poses[2]["quality"]["corners_right"] == 0
    assert poses[2]["valid"], poses[2]["reason"]
    assert loop.stats.errors == 0


def test_both_images_corrupt_give_an_invalid_pose(sequence: tuple[Path, dict], tmp_path: Path) -> None:
    """Frame 0 is fine (a config whose first frame is not the rig's size is refused at load); frame 1 is half size."""
    import cv2
    folder, _ = sequence
    bad = tmp_path / "bad"
    for side in ("left", "right"):
        (bad / side).mkdir(parents=True)
        (bad / side / "000000.png").write_bytes((folder / side / "000000.png").read_bytes())
        small = cv2.imread(str(folder / side / "000001.png"), cv2.IMREAD_UNCHANGED)[::2, ::2]
        cv2.imwrite(str(bad / side / "000001.png"), small)
    (bad / "rig.yaml").write_bytes((folder / "rig.yaml").read_bytes())
    endpoint = free_endpoint()
    cfg = write_config(tmp_path / "live.yaml", bad, endpoint, source_extra={"loop": True, "latest_only": False})
    sub = MessageCollector(endpoint)
    loop = LiveLoop(load_live_config(cfg))
    th, _ = run_in_thread(loop)
    try:
        assert sub.wait_for(lambda: any(m["seq"] % 2 == 1 for m in sub.of("pose")), 10)
    finally:
        loop.request_stop()
        th.join(10)
        sub.close()
    msg = next(m for m in sub.of("pose") if m["seq"] % 2 == 1)
    assert not msg["valid"] and msg["pose"] is None
    assert msg["reason"].startswith("corrupt frame: left image is 640x400") and "right image" in msg["reason"]
    assert all(m["valid"] for m in sub.of("pose") if m["seq"] % 2 == 0)
    assert loop.stats.corrupt_frames == loop.stats.poses_invalid >= 1
    assert loop.stats.errors == 0


def test_each_image_is_checked_once_into_the_detectors_grey() -> None:
    ok = np.zeros((800, 1280), np.uint8)
    grey, problem = grey_image(ok, (1280, 800), "left")
    assert problem is None and grey is ok                     # already grey: no copy
    grey, problem = grey_image(np.zeros((800, 1280, 3), np.uint8), (1280, 800), "left")
    assert problem is None and grey is not None and grey.shape == (800, 1280) and grey.dtype == np.uint8
    assert grey_image(ok[:10], (1280, 800), "left") == (None, "left image is 1280x10, the rig was calibrated at "
                                                              "1280x800")
    assert "dtype float32" in str(grey_image(ok.astype(np.float32), (1280, 800), "left")[1])
    assert "NoneType" in str(grey_image(None, (1280, 800), "right")[1])
    assert "shape (800, 1280, 2)" in str(grey_image(np.zeros((800, 1280, 2), np.uint8), (1280, 800), "right")[1])


@pytest.mark.parametrize("edit, field", [
    ({"publish": {"endpoint": "tcp://0.0.0.0:5560"}}, "publish.endpoint"),
    ({"pose": {"max_rms_px": -1}}, "pose.max_rms_px"),
    ({"pose": {"triangulation": "magic"}}, "pose.triangulation"),
    ({"pose": {"outlier_sigmas": 1}}, "pose.outlier_sigmas"),
    ({"tracking": {"max_gap_s": 0}}, "tracking.max_gap_s"),
    ({"tracking": {"min_confirmed_fraction": 1.5}}, "tracking.min_confirmed_fraction"),
    ({"tracking": {"enable": True}}, "tracking.enable"),
    ({"loop": {"status_period": 1}}, "loop.status_period"),
    ({"rig": "/nonexistent/rig.yaml"}, "rig"),
    ({"target": "targets/nope.yaml"}, "target"),
    ({"source": {"driver": "replay", "path": "x", "fsp": 3}}, "source.fsp"),
    ({"extra": 1}, "extra"),
    ({"loop": {"latest_frame_wins": False}}, "loop.latest_frame_wins"),
])
def test_bad_config_names_the_field(sequence: tuple[Path, dict], tmp_path: Path, edit: dict, field: str) -> None:
    import yaml
    folder, _ = sequence
    cfg = write_config(tmp_path / "live.yaml", folder, free_endpoint())
    doc = yaml.safe_load(cfg.read_text())
    doc.update(edit)
    cfg.write_text(yaml.safe_dump(doc))
    with pytest.raises(ConfigError, match=f"field '{field}'"):
        load_live_config(cfg)


def test_null_sections_and_files_keep_their_defaults(sequence: tuple[Path, dict], tmp_path: Path) -> None:
    """`detector: null` (as the config's documentation writes it) is the built-in thresholds, like no detector
    field; a null section is its defaults (before, `detector: null` was refused as missing)."""
    import yaml
    folder, _ = sequence
    cfg = write_config(tmp_path / "live.yaml", folder, free_endpoint())
    plain = load_live_config(cfg)
    doc = yaml.safe_load(cfg.read_text())
    doc.update({"detector": None, "pose": None, "tracking": None, "loop": None})
    cfg.write_text(yaml.safe_dump(doc))
    nulls = load_live_config(cfg)
    assert nulls.detector is None and plain.detector is None
    assert (nulls.pose, nulls.tracking) == (plain.pose, plain.tracking)
    assert nulls.loop == type(plain.loop)()
    doc["detector"] = "no-such-detector.yaml"           # named once (it was "field 'detector': FILE: field ...")
    cfg.write_text(yaml.safe_dump(doc))
    with pytest.raises(ConfigError) as err:
        load_live_config(cfg)
    assert str(err.value) == f"{cfg}: field 'detector' names a file that does not exist: 'no-such-detector.yaml'"
    doc["detector"] = str(tmp_path)                      # a folder: said so, not "does not exist"
    cfg.write_text(yaml.safe_dump(doc))
    with pytest.raises(ConfigError, match="field 'detector' names a folder, not a file"):
        load_live_config(cfg)


def test_the_live_source_keeps_only_the_newest_frame_unless_told_otherwise(sequence: tuple[Path, dict],
                                                                         tmp_path: Path) -> None:
    """One latest-frame-wins setting, the source's latest_only: true by default in the live loop."""
    folder, _ = sequence
    cfg = write_config(tmp_path / "live.yaml", folder, free_endpoint())
    assert load_live_config(cfg).source.settings.latest_only
    cfg = write_config(tmp_path / "live.yaml", folder, free_endpoint(), source_extra={"latest_only": False})
    assert not load_live_config(cfg).source.settings.latest_only
    cfg = write_config(tmp_path / "live.yaml", folder, free_endpoint(), loop={"latest_frame_wins": False})
    with pytest.raises(ConfigError, match="field 'loop.latest_frame_wins' is no longer read here: set "
                                          "source.latest_only instead"):
        load_live_config(cfg)


def test_reload_moves_the_endpoint_only_if_it_can_bind(sequence: tuple[Path, dict], tmp_path: Path) -> None:
    import yaml

    from edgecal.publish import PosePublisher
    folder, _ = sequence
    first, taken, second = free_endpoint(), free_endpoint(), free_endpoint()
    cfg = write_config(tmp_path / "live.yaml", folder, first, source_extra={"loop": True})
    doc = yaml.safe_load(cfg.read_text())
    sub1, sub2 = MessageCollector(first), MessageCollector(second)
    blocker = PosePublisher(taken)
    loop = LiveLoop(load_live_config(cfg))
    th, _ = run_in_thread(loop)
    try:
        assert sub1.wait_for(lambda: len(sub1.of("pose")) >= 1)
        cfg.write_text(yaml.safe_dump({**doc, "publish": {"endpoint": taken}}))
        loop.request_reload()
        assert sub1.wait_for(lambda: any("cannot bind" in (m.get("message") or "") for m in sub1.of("status")), 10)
        n = len(sub1.of("pose"))
        assert sub1.wait_for(lambda: len(sub1.of("pose")) > n, 10)     # still publishing on the first one
        cfg.write_text(yaml.safe_dump({**doc, "publish": {"endpoint": second}}))
        loop.request_reload()
        assert sub2.wait_for(lambda: len(sub2.of("pose")) >= 1, 10)
    finally:
        loop.request_stop()
        th.join(10)
        blocker.close()
        sub1.close()
        sub2.close()
    assert loop.stats.reload_failures == 1 and loop.stats.reconnects == 0


def test_abort_releases_camera_and_socket_while_a_frame_is_in_flight(sequence: tuple[Path, dict],
                                                                     tmp_path: Path) -> None:
    """What `edgecal run` does when a frame outlasts the stop grace period after SIGTERM."""
    from edgecal.publish import PosePublisher
    folder, _ = sequence
    endpoint = free_endpoint()
    cfg = write_config(tmp_path / "live.yaml", folder, endpoint, source_extra={"loop": True})
    sub = MessageCollector(endpoint)
    loop = LiveLoop(load_live_config(cfg))
    th, result = run_in_thread(loop)
    try:
        assert sub.wait_for(lambda: len(sub.of("pose")) >= 1)
        loop.request_stop()
        loop.abort()
        PosePublisher(endpoint).close()      # the port is free at once
        n = len(sub.of("pose"))
        th.join(10)
    finally:
        sub.close()
    assert not th.is_alive() and result == [0]
    assert len(sub.of("pose")) == n and sub.of("status")[-1]["state"] == "stopping"
    assert loop.stats.errors == 0


def test_a_source_of_only_unreadable_frames_is_not_read_in_a_spin(sequence: tuple[Path, dict],
                                                                   tmp_path: Path) -> None:
    """Every file broken (or no descriptors left to open them): counted, but read at most ~20 times a second
    once no frame has come for a second (it was ~100,000 a second)."""
    folder, _ = sequence
    bad = tmp_path / "bad"
    for side in ("left", "right"):
        (bad / side).mkdir(parents=True)
        (bad / side / "000000.png").write_bytes((folder / side / "000000.png").read_bytes())
        (bad / side / "000001.png").write_bytes(b"not a png")
    (bad / "rig.yaml").write_bytes((folder / "rig.yaml").read_bytes())
    (bad / "left" / "000000.png").write_bytes(b"not a png either")   # every pair has an unreadable image
    cfg = write_config(tmp_path / "live.yaml", bad, free_endpoint(),
                       source_extra={"pace": "fast", "loop": True, "latest_only": False})
    loop = LiveLoop(load_live_config(cfg))
    th, result = run_in_thread(loop)
    try:
        assert wait_until(lambda: loop.stats.corrupt_frames > 0, 30)
        time.sleep(1.2)
        before = loop.stats.corrupt_frames
        time.sleep(1.0)
        per_second = loop.stats.corrupt_frames - before
    finally:
        loop.request_stop()
        th.join(10)
    assert result == [0] and loop.stats.frames == 0
    assert 0 < per_second < 40, per_second
