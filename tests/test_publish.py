"""The pose stream: message schema, a publisher that never blocks, `edgecal listen`."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
import zmq

from edgecal.commands import listen
from edgecal.errors import ConfigError, InputError, PublishError
from edgecal.pose import Pose
from edgecal.publish import (
    PosePublisher,
    check_endpoint,
    decode,
    encode,
    is_local_endpoint,
    pose_message,
    status_message,
)
from edgecal.publish.outputs import LoopOutputs
from edgecal.publish.publisher import PublishSettings
from edgecal.publish.subscriber import MessageCollector, PoseSubscriber


def run_listen(argv: list[str]) -> int:
    """Run `edgecal listen ARGV` through its own argument parser."""
    import argparse
    parser = argparse.ArgumentParser()
    listen.add_parser(parser.add_subparsers())
    return listen.run(parser.parse_args(["listen", *argv]))


def free_endpoint() -> str:
    """A tcp endpoint on a free localhost port."""
    import socket
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp://127.0.0.1:{s.getsockname()[1]}"


def a_pose() -> Pose:
    return Pose(np.eye(3), np.array([0.1, -0.2, 1.0]), np.eye(6) * 1e-8, "stereo", True, "", 0.12, 60, 55, 50,
                ("front", "left"))


def test_pose_message_round_trip() -> None:
    msg = decode(encode(pose_message(a_pose(), 7, 1_000_000, 13_000_000)))
    assert msg["version"] == 1 and msg["type"] == "pose" and msg["seq"] == 7
    assert msg["latency_ns"] == 12_000_000
    assert msg["pose"]["position_m"] == [0.1, -0.2, 1.0]
    assert msg["pose"]["orientation_xyzw"] == [0.0, 0.0, 0.0, 1.0]
    assert len(msg["covariance"]) == 36 and msg["covariance"][0] == 1e-8
    assert msg["valid"] and msg["quality"]["boards"] == ["front", "left"]


def test_pose_message_builds_the_latency_basis_and_how_the_boards_were_found() -> None:
    # The live loop's whole message comes from pose_message: nothing is patched into it afterwards.
    msg = decode(encode(pose_message(a_pose(), 7, 1_000_000, 13_000_000, capture_ns=4_000_000,
                                     latency_from="receive", detection="tracked")))
    assert msg["stamp_ns"] == 1_000_000 and msg["latency_ns"] == 9_000_000 and msg["latency_from"] == "receive"
    assert msg["quality"]["detection"] == "tracked"
    plain = pose_message(a_pose(), 7, 1_000_000, 13_000_000)
    assert plain["latency_ns"] == 12_000_000 and plain["latency_from"] == "capture"
    assert "detection" not in plain["quality"]
    with pytest.raises(ValueError, match="latency_from"):
        pose_message(a_pose(), 7, 0, 1, latency_from="device")
    with pytest.raises(ValueError, match="detection"):
        pose_message(a_pose(), 7, 0, 1, detection="guessed")


def test_invalid_pose_message_has_nulls_not_nan() -> None:
    body = encode(pose_message(Pose.invalid("no board detected"), 1, 0, 5))
    assert b"NaN" not in body
    msg = decode(body)
    assert msg["valid"] is False and msg["pose"] is None and msg["covariance"] is None
    assert msg["reason"] == "no board detected"


def test_status_message() -> None:
    msg = decode(encode(status_message("running", {"fps": 29.99712, "dropped_frames": 3,
                                                   "latency_ms": {"median": 12.0, "p99": 20.5}}, 99)))
    assert msg["type"] == "status" and msg["fps"] == 29.997 and msg["latency_ms"]["p99"] == 20.5


def test_endpoint_must_be_local_unless_allowed() -> None:
    assert is_local_endpoint("tcp://127.0.0.1:5560") and is_local_endpoint("tcp://localhost:1")
    assert is_local_endpoint("ipc:///tmp/x") and is_local_endpoint("tcp://[::1]:5560")
    assert not is_local_endpoint("tcp://*:5560") and not is_local_endpoint("tcp://0.0.0.0:5560")
    with pytest.raises(ConfigError, match="allow_remote"):
        check_endpoint("tcp://*:5560", allow_remote=False)
    assert check_endpoint("tcp://*:5560", allow_remote=True)
    with pytest.raises(ConfigError, match="port"):
        check_endpoint("tcp://127.0.0.1", allow_remote=False)
    with pytest.raises(ConfigError):
        check_endpoint("http://127.0.0.1:80", allow_remote=False)


def test_publisher_never_blocks_on_a_subscriber_that_stops_reading() -> None:
    endpoint = free_endpoint()
    body = {"filler": "x" * 4000}
    with PosePublisher(endpoint, hwm=4) as pub, PoseSubscriber(endpoint, receive_hwm=1, receive_buffer=4096) as sub:
        deadline = time.monotonic() + 5
        while sub.receive_frames(0.01) is None:   # wait until the subscription has reached the publisher
            pub.send_status(body)
            assert time.monotonic() < deadline
        # The subscriber now stops reading. 20,000 messages of 4 kB (80 MB) overflow every buffer:
        # a blocking send would hang here; a non-blocking one drops and returns.
        t0 = time.monotonic()
        results = [pub.send_pose(body) for _ in range(20_000)]
        elapsed = time.monotonic() - t0
        assert elapsed < 10.0
        assert results.count(False) == pub.send_failures
        # The subscriber wakes up: it gets at most a few buffers' worth, the rest were dropped for it.
        received = 0
        while sub.receive_frames(0.2) is not None:
            received += 1
        assert received < 20_000 // 2


def test_bind_to_a_taken_port_is_a_publish_error() -> None:
    endpoint = free_endpoint()
    with PosePublisher(endpoint):
        from edgecal.errors import PublishError
        with pytest.raises(PublishError, match="cannot bind"):
            PosePublisher(endpoint)


def test_listen_prints_the_stream(capsys: pytest.CaptureFixture) -> None:
    endpoint = free_endpoint()
    stop = threading.Event()

    def publish() -> None:
        with PosePublisher(endpoint) as pub:
            seq = 0
            while not stop.is_set():
                pub.send_pose(pose_message(a_pose(), seq, time.monotonic_ns() - 5_000_000, time.monotonic_ns()))
                pub.send_pose(pose_message(Pose.invalid("no board detected"), seq, 0, 1))
                seq += 1
                time.sleep(0.01)

    th = threading.Thread(target=publish)
    th.start()
    try:
        assert run_listen([endpoint, "--count", "2", "--timeout", "5"]) == 0
    finally:
        stop.set()
        th.join()
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 2
    assert any("stereo xyz_m [+0.1000 -0.2000 +1.0000]" in line for line in lines)
    assert any("INVALID (no board detected)" in line for line in lines)


def test_listen_times_out_without_publisher(capsys: pytest.CaptureFixture) -> None:
    assert run_listen([free_endpoint(), "--timeout", "0.3"]) == 1


def test_listen_survives_messages_it_does_not_expect(capsys: pytest.CaptureFixture) -> None:
    """Another publisher on the port, another schema, damaged bytes: each is skipped with a short note."""
    endpoint = free_endpoint()
    good = encode(pose_message(a_pose(), 7, time.monotonic_ns() - 5_000_000, time.monotonic_ns()))
    junk = [[b"pose"], [b"pose", b"\xff\xfe"], [b"pose", b"not json"], [b"pose", b"[1, 2]"],
            [b"pose", b"{\"type\": \"pose\"}"], [b"pose", b"{\"type\": \"pose\", \"seq\": 1, \"latency_ns\": \"x\"}"],
            [b"status", b"{\"type\": \"status\", \"latency_ms\": 5}"], [b"pose", b"x" * 100_000, b"extra"],
            [b"pose", b"[" * 100_000]]
    stop = threading.Event()

    def publish() -> None:
        ctx = zmq.Context()
        sock = ctx.socket(zmq.PUB)
        sock.bind(endpoint)
        while not stop.is_set():
            for frames in junk:
                sock.send_multipart(frames)
            sock.send_multipart([b"pose", good])
            time.sleep(0.02)
        sock.close(linger=0)
        ctx.term()

    th = threading.Thread(target=publish)
    th.start()
    try:
        assert run_listen([endpoint, "--count", "6", "--timeout", "5"]) == 0
    finally:
        stop.set()
        th.join()
    out, err = capsys.readouterr()
    lines = out.splitlines()
    assert len(lines) == 6
    assert any("stereo xyz_m [+0.1000 -0.2000 +1.0000]" in line for line in lines)
    assert any(line.startswith("unrecognised 'pose' message") for line in lines)
    assert "skipped a message that is not [topic, JSON object]" in err
    assert max(len(line) for line in (out + err).splitlines()) < 300


def test_connections_beyond_max_connections_are_shut_and_the_watcher_ends_with_the_publisher() -> None:
    endpoint = free_endpoint()
    ctx = zmq.Context()
    subs = []
    with PosePublisher(endpoint, max_connections=2) as pub:
        assert any(t.name == "publish-connections" for t in threading.enumerate())
        subs = [PoseSubscriber(endpoint, context=ctx) for _ in range(5)]
        deadline = time.monotonic() + 10
        while pub.refused_connections < 3 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert pub.refused_connections >= 3
        time.sleep(0.5)                        # the two held ones have subscribed by now
        for _ in range(20):
            pub.send_status({"n": 1})
        receiving = sum(1 for s in subs if s.receive_frames(0.5) is not None)
        assert receiving == 2
    # close() stops the thread that watched the connections (it ends on ZeroMQ's MONITOR_STOPPED event)
    assert not any(t.name == "publish-connections" and t.is_alive() for t in threading.enumerate())
    for s in subs:
        s.close()
    ctx.term()


def test_subscriber_takes_only_its_topics_and_a_collector_keeps_what_was_queued_at_close() -> None:
    endpoint = free_endpoint()
    with pytest.raises(InputError, match="not a ZeroMQ endpoint"):
        PoseSubscriber("tcp://no-port-here")
    with PosePublisher(endpoint, hwm=100) as pub, PoseSubscriber(endpoint, ("pose",)) as sub:
        collector = MessageCollector(endpoint)
        deadline = time.monotonic() + 5
        while sub.receive(0.01) is None:               # until both subscriptions have reached the publisher
            pub.send_pose({"type": "pose", "seq": -1})
            assert time.monotonic() < deadline
        assert collector.wait_for(lambda: bool(collector.of("pose")), 5)
        pub.send_status({"type": "status", "n": 1})    # not a topic this subscriber took
        for seq in range(3):
            pub.send_pose({"type": "pose", "seq": seq})
        seqs = []
        while (msg := sub.receive(0.5)) is not None:
            seqs.append(msg["seq"])
        assert [seq for seq in seqs if seq >= 0] == [0, 1, 2]      # the status was not taken
        messages = collector.close(drain_s=0.2)
    assert [m.get("seq", "status") for m in messages if m.get("seq") != -1] == ["status", 0, 1, 2]
    assert not any(t.name == "subscriber" and t.is_alive() for t in threading.enumerate())


def _reaches(outputs: LoopOutputs, endpoint: str) -> bool:
    """Whether a status sent through ``outputs`` reaches a subscriber of ``endpoint``."""
    with PoseSubscriber(endpoint) as sub:
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline:
            outputs.send("status", {"type": "status"})
            if sub.receive(0.05) is not None:
                return True
    return False


def test_loop_outputs_keep_the_running_stream_when_a_reload_cannot_bind() -> None:
    first, taken, second = free_endpoint(), free_endpoint(), free_endpoint()
    outputs = LoopOutputs()
    running = PublishSettings(endpoint=first)
    outputs.bind(running)
    try:
        with PosePublisher(taken), pytest.raises(PublishError, match="cannot bind"):
            outputs.reconfigure(PublishSettings(endpoint=taken), running, None)
        assert outputs.publisher is not None and outputs.publisher.endpoint == first and _reaches(outputs, first)
        # The same endpoint with other settings: closed and bound again.
        assert outputs.reconfigure(PublishSettings(endpoint=first, hwm=8), running, None) == []
        assert _reaches(outputs, first)
        outputs.reconfigure(PublishSettings(endpoint=second), PublishSettings(endpoint=first, hwm=8), None)
        assert outputs.publisher is not None and outputs.publisher.endpoint == second and _reaches(outputs, second)
        assert outputs.counters() == {"refused_connections": 0}
    finally:
        outputs.close()
    assert outputs.publisher is None and outputs.all == []
