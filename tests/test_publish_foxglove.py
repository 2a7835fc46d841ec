"""The live Foxglove sink, seen by a WebSocket client speaking the Foxglove protocol (loopback only)."""

from __future__ import annotations

import json
import socket
import struct
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from websockets.sync.client import connect

from edgecal.stream import LiveLoop, load_live_config

from .live_fixtures import free_endpoint, render_robot, wait_until, write_config

N_FRAMES = 3


@pytest.fixture(scope="module")
def sequence(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict]:
    folder = tmp_path_factory.mktemp("robot")
    return folder, render_robot(folder, N_FRAMES, seed=13)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class FoxgloveClient:
    """Connects, reads serverInfo and the advertised channels, subscribes to all, collects messages by topic."""

    def __init__(self, port: int) -> None:
        self._connection = connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1"], open_timeout=10)
        self.ws = self._connection.__enter__()
        self.server_info = json.loads(self.ws.recv(timeout=10))
        self.channels: dict[str, dict] = {}
        self.messages: dict[str, list[tuple[int, bytes]]] = {}
        self._by_sub: dict[int, str] = {}
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                m = self.ws.recv(timeout=0.1)
            except TimeoutError:
                continue
            except Exception:  # noqa: BLE001 - the server went away: stop reading
                return
            if isinstance(m, str):
                msg = json.loads(m)
                if msg.get("op") == "advertise":
                    subs = []
                    with self._lock:
                        for ch in msg["channels"]:
                            self.channels[ch["topic"]] = ch
                            sid = len(self._by_sub) + 1
                            self._by_sub[sid] = ch["topic"]
                            subs.append({"id": sid, "channelId": ch["id"]})
                    self.ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
            elif m[0] == 0x01:                      # message data: opcode, subscription id, log time, payload
                sid, log_time = struct.unpack_from("<IQ", m, 1)
                with self._lock:
                    self.messages.setdefault(self._by_sub[sid], []).append((log_time, m[13:]))

    def of(self, topic: str) -> list[tuple[int, bytes]]:
        with self._lock:
            return list(self.messages.get(topic, []))

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5)
        self._connection.__exit__(None, None, None)


def _jpeg_in(payload: bytes) -> np.ndarray | None:
    """The JPEG embedded in a protobuf foxglove.CompressedImage payload, decoded."""
    start, end = payload.find(b"\xff\xd8"), payload.rfind(b"\xff\xd9")
    if start < 0 or end < 0:
        return None
    return cv2.imdecode(np.frombuffer(payload[start:end + 2], np.uint8), cv2.IMREAD_UNCHANGED)


def test_foxglove_server_shows_images_corners_pose_and_status(sequence: tuple[Path, dict], tmp_path: Path) -> None:
    folder, _ = sequence
    port = _free_port()
    cfg = write_config(tmp_path / "live.yaml", folder, free_endpoint(),
                       source_extra={"loop": True, "latest_only": True},
                       loop={"stop_at_end": False, "status_period_s": 0.25})
    doc = yaml.safe_load(cfg.read_text())
    doc["publish"].update({"foxglove": {"port": port, "image_hz": 20, "image_width": 320},
                           "frame_id": "cams", "child_frame_id": "base_link"})
    cfg.write_text(yaml.safe_dump(doc))
    loop = LiveLoop(load_live_config(cfg))
    result: list = []
    th = threading.Thread(target=lambda: result.append(loop.run()))
    th.start()
    client = None
    try:
        assert wait_until(lambda: _connectable(port), 60.0), "the Foxglove server never listened"
        client = FoxgloveClient(port)
        assert client.server_info["op"] == "serverInfo" and client.server_info["name"] == "edgecal"
        topics = {"/edgecal/left/image", "/edgecal/right/image", "/edgecal/left/corners", "/edgecal/right/corners",
                  "/tf", "/edgecal/pose", "/edgecal/status"}
        assert wait_until(lambda: topics <= set(client.channels), 20.0), sorted(client.channels)
        assert client.channels["/edgecal/left/image"]["schemaName"] == "foxglove.CompressedImage"
        assert client.channels["/tf"]["schemaName"] == "foxglove.FrameTransforms"
        assert client.channels["/edgecal/left/corners"]["schemaName"] == "foxglove.ImageAnnotations"
        assert wait_until(lambda: all(client.of(t) for t in topics), 60.0), \
            {t: len(client.of(t)) for t in topics}
    finally:
        loop.request_stop()
        th.join(20)
        if client is not None:
            client.close()
    assert result == [0]
    image = _jpeg_in(client.of("/edgecal/left/image")[-1][1])
    assert image is not None and image.shape[1] == 320 and image.shape[0] == 200      # 1280x800 downscaled
    tf = client.of("/tf")[-1][1]
    assert b"cams" in tf and b"base_link" in tf
    status = json.loads(client.of("/edgecal/status")[-1][1])
    assert status["type"] == "status" and status["state"] in ("running", "stopping")
    assert len(client.of("/edgecal/left/corners")[-1][1]) > 100          # points of the boards' corners
    # Images are rate-limited per camera (20 Hz here), the transforms are not.
    assert len(client.of("/edgecal/left/image")) <= len(client.of("/tf")) + 1


def _connectable(port: int) -> bool:
    with socket.socket() as s:
        s.settimeout(0.2)
        return s.connect_ex(("127.0.0.1", port)) == 0


def test_foxglove_port_in_use_is_one_clear_error(sequence: tuple[Path, dict], tmp_path: Path) -> None:
    from edgecal.errors import PublishError
    from edgecal.publish.foxglove_sink import FoxgloveSink
    from edgecal.publish.sink_settings import FoxgloveSettings, OutputSettings
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        with pytest.raises(PublishError, match=f"cannot serve Foxglove on 127.0.0.1:{port}"):
            FoxgloveSink(FoxgloveSettings(port=port), OutputSettings())


def test_a_slow_client_never_slows_the_sink(sequence: tuple[Path, dict]) -> None:
    """frame() only hands over: with a subscribed client that never reads, frames are dropped, not queued."""
    from edgecal.drivers.base import Frame, StereoFrame
    from edgecal.pose.types import Pose
    from edgecal.publish.foxglove_sink import FoxgloveSink
    from edgecal.publish.sink_settings import FoxgloveSettings, OutputSettings
    from edgecal.publish.sinks import FrameOutput
    folder, _ = sequence
    img = cv2.imread(str(folder / "left" / "000000.png"), cv2.IMREAD_UNCHANGED)
    frame = StereoFrame(Frame(img, 1, 1, 0, "l"), Frame(img, 1, 1, 0, "r"))
    out = FrameOutput(frame, Pose.invalid("test"), {}, ([], []), time.monotonic_ns())
    sink = FoxgloveSink(FoxgloveSettings(port=0, image_hz=1000), OutputSettings())
    try:
        with connect(f"ws://127.0.0.1:{sink.port}", subprotocols=["foxglove.sdk.v1"], open_timeout=10) as ws:
            ws.recv(timeout=5)
            adv = json.loads(ws.recv(timeout=5))
            ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": i + 1, "channelId": c["id"]}
                                                                    for i, c in enumerate(adv["channels"])]}))
            time.sleep(0.3)
            deadline = time.monotonic() + 1.0
            calls = 0
            while time.monotonic() < deadline:            # the client reads nothing meanwhile
                sink.frame(out)
                calls += 1
    finally:
        sink.close()
    assert sink.dropped > 0 and sink.images_sent > 0      # frames replaced in the mailbox, not queued
    assert calls > 100 * sink.images_sent
