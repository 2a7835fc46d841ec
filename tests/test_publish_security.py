"""The pose stream against the network: CURVE keys (required beyond loopback, enforced here on 127.0.0.1
where a config gives them), and a flood of idle TCP connections that must not starve a real subscriber."""

from __future__ import annotations

import os
import resource
import signal
import socket
import stat
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import yaml
import zmq

from edgecal.cli import main
from edgecal.errors import ConfigError
from edgecal.publish.subscriber import MessageCollector, PoseSubscriber
from edgecal.stream import LiveLoop, load_live_config

from .live_fixtures import free_endpoint, render_robot, stop_daemon, wait_until, write_config


@pytest.fixture(scope="module")
def robot(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("robot")
    render_robot(folder, 3, seed=5)
    return folder


@pytest.fixture(scope="module")
def keys(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """server, laptop (allowed) and stranger (not allowed) key pairs made by `edgecal keys`."""
    folder = tmp_path_factory.mktemp("keys")
    for name in ("server", "laptop", "stranger"):
        assert main(["keys", str(folder), "--name", name]) == 0
    (folder / "clients").mkdir()
    (folder / "clients" / "laptop.key").write_bytes((folder / "laptop.key").read_bytes())
    return folder


def curve_config(path: Path, robot: Path, endpoint: str, keys: Path, **publish: object) -> Path:
    cfg = write_config(path, robot, endpoint, source_extra={"loop": True})
    doc = yaml.safe_load(cfg.read_text())
    doc["publish"] = {"endpoint": endpoint, "curve": {"server_key": str(keys / "server.key_secret"),
                                                      "client_keys": str(keys / "clients")}, **publish}
    cfg.write_text(yaml.safe_dump(doc))
    return cfg


def test_keys_command_writes_a_pair_the_secret_readable_by_its_owner_only(keys: Path,
                                                                         capsys: pytest.CaptureFixture) -> None:
    assert stat.S_IMODE((keys / "server.key_secret").stat().st_mode) == 0o600
    assert stat.S_IMODE((keys / "server.key").stat().st_mode) & 0o077 != 0o077
    assert main(["keys", str(keys), "--name", "server"]) == 2          # never clobbers without --force
    assert "exists" in capsys.readouterr().err


def test_curve_stream_lets_in_known_subscribers_only(robot: Path, keys: Path, tmp_path: Path,
                                                     capsys: pytest.CaptureFixture) -> None:
    endpoint = free_endpoint()
    loop = LiveLoop(load_live_config(curve_config(tmp_path / "live.yaml", robot, endpoint, keys)))
    th = threading.Thread(target=loop.run)
    th.start()
    keyless = MessageCollector(endpoint)
    try:
        # The allowed key: poses arrive, decrypted.
        assert main(["listen", endpoint, "--key", str(keys / "laptop.key_secret"), "--server-key",
                     str(keys / "server.key"), "--topic", "pose", "--count", "2", "--timeout", "30"]) == 0
        out = capsys.readouterr().out
        assert out.count("pose #") == 2 and "stereo" in out
        # A key the publisher does not hold, and no key at all: nothing.
        assert main(["listen", endpoint, "--key", str(keys / "stranger.key_secret"), "--server-key",
                     str(keys / "server.key"), "--timeout", "2"]) == 1
        assert "pose #" not in capsys.readouterr().out
        assert keyless.messages == []
    finally:
        loop.request_stop()
        th.join(10)
        keyless.close()


def test_listen_key_errors_are_one_line(keys: Path, capsys: pytest.CaptureFixture) -> None:
    endpoint = free_endpoint()
    assert main(["listen", endpoint, "--key", str(keys / "laptop.key_secret")]) == 2
    assert main(["listen", endpoint, "--key", str(keys / "laptop.key"), "--server-key", str(keys / "server.key")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and "--server-key" in err[0] and "only a public key" in err[1]


@pytest.mark.parametrize("publish, field", [
    ({"endpoint": "tcp://0.0.0.0:5560", "allow_remote": True}, "publish.curve"),
    ({"endpoint": "tcp://0.0.0.0:5560", "allow_remote": True,
      "curve": {"server_key": "KEYS/server.key", "client_keys": "KEYS/clients"}}, "publish.curve.server_key"),
    ({"endpoint": "tcp://0.0.0.0:5560", "allow_remote": True,
      "curve": {"server_key": "KEYS/server.key_secret", "client_keys": "KEYS/none"}}, "publish.curve.client_keys"),
    ({"endpoint": "tcp://127.0.0.1:5560", "curve": {"server_key": "KEYS/server.key_secret"}},
     "publish.curve.client_keys"),
])
def test_remote_binding_requires_curve_keys(robot: Path, keys: Path, tmp_path: Path, publish: dict,
                                            field: str) -> None:
    cfg = write_config(tmp_path / "live.yaml", robot, free_endpoint())
    doc = yaml.safe_load(cfg.read_text())
    doc["publish"] = yaml.safe_load(yaml.safe_dump(publish).replace("KEYS", str(keys)))
    cfg.write_text(yaml.safe_dump(doc))
    with pytest.raises(ConfigError, match=f"field '{field}'"):
        load_live_config(cfg)


def test_remote_binding_with_keys_is_accepted(robot: Path, keys: Path, tmp_path: Path) -> None:
    cfg = curve_config(tmp_path / "live.yaml", robot, "tcp://0.0.0.0:5560", keys, allow_remote=True)
    config = load_live_config(cfg)
    assert config.publish.curve is not None and len(config.publish.curve.clients) == 1


FLOOD = 1100          # idle TCP connections, more than the 1024 file descriptors the daemon gets here


def _raise_fd_limit(need: int) -> None:
    """Let this test process open ``need`` descriptors (skip when the hard limit does not allow it)."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if hard < need:
        pytest.skip(f"the test needs {need} file descriptors (hard limit {hard})")
    resource.setrlimit(resource.RLIMIT_NOFILE, (max(soft, need), hard))


def _start_daemon_with_1024_fds(cfg: Path, log: Path) -> subprocess.Popen:
    """A real daemon on ``cfg`` with the 1024-descriptor soft limit a service gets by default."""
    def limit_fds() -> None:
        resource.setrlimit(resource.RLIMIT_NOFILE, (1024, 1024))

    return subprocess.Popen([sys.executable, "-m", "edgecal", "run", "--config", str(cfg)],
                            env={**os.environ, "NUMBA_NUM_THREADS": "1"}, stdout=log.open("wb"),
                            stderr=subprocess.STDOUT, preexec_fn=limit_fds)  # noqa: PLW1509


def test_idle_connections_cannot_starve_a_subscriber(robot: Path, tmp_path: Path) -> None:
    """1,100 TCP connections that never speak ZeroMQ, against a daemon limited to 1024 file descriptors (the
    soft limit a service gets by default): a real subscriber that connects during the flood receives poses,
    and after publish.handshake_timeout_s the daemon has dropped them (its descriptors back under 100)."""
    _raise_fd_limit(FLOOD + 200)
    endpoint = free_endpoint()
    port = int(endpoint.rsplit(":", 1)[1])
    cfg = write_config(tmp_path / "live.yaml", robot, endpoint, source_extra={"loop": True})
    log = tmp_path / "run.log"
    proc = _start_daemon_with_1024_fds(cfg, log)
    flood: list[socket.socket] = []
    sub = None
    try:
        first = MessageCollector(endpoint)
        assert first.wait_for(lambda: len(first.of("pose")) >= 1, 90), log.read_text()
        first.close()
        for i in range(FLOOD):          # 250 a second: the daemon accepts them all (none wait in the backlog)
            c = socket.socket()
            c.setblocking(False)
            try:
                c.connect(("127.0.0.1", port))
            except BlockingIOError:
                pass
            flood.append(c)
            if i % 50 == 49:
                time.sleep(0.2)
        sub = MessageCollector(endpoint)  # while the flood is held open
        assert sub.wait_for(lambda: len(sub.of("pose")) >= 3, 20), log.read_text()[-2000:]
        assert all(m["valid"] for m in sub.of("pose"))
        # Once the handshake timeout has passed, the idle connections are gone from the daemon.
        def fds() -> int:
            return len(os.listdir(f"/proc/{proc.pid}/fd"))

        assert wait_until(lambda: fds() < 100, 10), f"{fds()} descriptors open with {FLOOD} idle connections held"
        assert proc.poll() is None
    finally:
        for c in flood:
            c.close()
        if sub is not None:
            sub.close()
        stop_daemon(proc)
    assert proc.returncode == 0, log.read_text()[-2000:]


ZMTP_FLOOD = 1_100


def test_subscribers_that_complete_the_handshake_cannot_take_the_descriptors(robot: Path, tmp_path: Path) -> None:
    """1,100 real ZeroMQ subscribers (each finishes the handshake at once and stays connected) against a daemon
    limited to 1024 file descriptors: it holds publish.max_connections of them and shuts the rest at accept,
    so its descriptors stay bounded, the subscriber connected before the flood keeps receiving poses, and a
    reload - which must open files - still works while the flood goes on."""
    _raise_fd_limit(2 * ZMTP_FLOOD + 300)    # a ZeroMQ socket here holds its connection and a mailbox descriptor
    endpoint = free_endpoint()
    cfg = write_config(tmp_path / "live.yaml", robot, endpoint, source_extra={"loop": True})
    doc = yaml.safe_load(cfg.read_text())
    doc["publish"]["max_connections"] = 32
    cfg.write_text(yaml.safe_dump(doc))
    log = tmp_path / "run.log"
    proc = _start_daemon_with_1024_fds(cfg, log)
    ctx = zmq.Context()
    ctx.MAX_SOCKETS = ZMTP_FLOOD + 100
    flood: list[PoseSubscriber] = []
    first = MessageCollector(endpoint)
    try:
        assert first.wait_for(lambda: len(first.of("pose")) >= 1, 90), log.read_text()
        for i in range(ZMTP_FLOOD):
            # A refused one comes back after 1 s (ZeroMQ's default is 0.1 s: 11,000 reconnects a second, which
            # the daemon's watcher thread does not outpace on this shared 2-core machine; README, "Pose stream").
            flood.append(PoseSubscriber(endpoint, context=ctx, reconnect_interval_s=1.0))
            if i % 100 == 99:
                time.sleep(0.1)

        def fds() -> int:
            return len(os.listdir(f"/proc/{proc.pid}/fd"))

        time.sleep(3.0)                       # every flood socket has connected (and been refused) by now
        held = []
        for _ in range(5):                    # while the refused ones keep reconnecting
            held.append(fds())
            time.sleep(0.2)
        # 32 held, ~20 of the daemon's own, and the refused ones between accept and ZeroMQ closing them.
        assert max(held) < 300, f"{held} descriptors open with {ZMTP_FLOOD} subscribers connecting"
        n = len(first.of("pose"))
        assert first.wait_for(lambda: len(first.of("pose")) >= n + 3, 20), log.read_text()[-2000:]
        # A reload opens the config, the rig and the target files: it needs descriptors the flood did not get.
        doc["pose"] = {"max_rms_px": 0.9}
        cfg.write_text(yaml.safe_dump(doc))
        n_status = len(first.of("status"))
        proc.send_signal(signal.SIGHUP)
        assert wait_until(lambda: b"reloaded" in log.read_bytes(), 20), log.read_text()[-2000:]
        assert first.wait_for(lambda: len(first.of("status")) > n_status + 1, 10)
        assert first.of("status")[-1]["reload_failures"] == 0 and first.of("status")[-1]["refused_connections"] > 0
        assert b"refusing pose-stream connections" in log.read_bytes()
        assert proc.poll() is None
        for s in flood:
            s.close()
        flood.clear()
        late = MessageCollector(endpoint)  # the flood has gone: a newcomer gets in again
        try:
            assert late.wait_for(lambda: len(late.of("pose")) >= 2, 20), log.read_text()[-2000:]
        finally:
            late.close()
    finally:
        for s in flood:
            s.close()
        ctx.term()
        first.close()
        stop_daemon(proc)
    assert proc.returncode == 0, log.read_text()[-2000:]
