"""`edgecal run` in a subprocess keeps running whatever a reload brings: a broken config on SIGHUP is logged
with its field, reported (briefly) in the status messages, and the old config keeps publishing valid poses."""

from __future__ import annotations

import copy
import random
import signal
import subprocess
import time
from pathlib import Path

import pytest
import yaml

from edgecal.config import packaged_config_path
from edgecal.errors import MESSAGE_MAX_CHARS
from edgecal.publish.subscriber import MessageCollector

from .live_fixtures import ALIAS_BOMB, NotifySocket, bad_rigs, free_endpoint, render_robot, start_daemon


@pytest.fixture(scope="module")
def robot(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict]:
    folder = tmp_path_factory.mktemp("robot")
    return folder, render_robot(folder, 3, seed=5)


def live_doc(folder: Path, endpoint: str) -> dict:
    """The shipped configs/robot.yaml, pointed at the rendered sequence and a free port."""
    doc = yaml.safe_load(packaged_config_path("robot.yaml").read_text())
    doc["source"] = {**doc["source"], "uri": f"replay:{folder}"}
    doc["rig"] = str(folder / "rig.yaml")
    doc["publish"]["endpoint"] = endpoint
    doc["loop"]["status_period_s"] = 0.2
    return doc


class Daemon:
    """A running `edgecal run` with a subscriber and the notify socket, and a way to reload it."""

    def __init__(self, cfg: Path, doc: dict, tmp_path: Path) -> None:
        self.cfg, self.endpoint = cfg, doc["publish"]["endpoint"]
        cfg.write_text(yaml.safe_dump(doc))
        self.sub = MessageCollector(self.endpoint)
        self.notify = NotifySocket(tmp_path / "notify.sock")
        self.log = tmp_path / "run.log"
        self.proc = start_daemon(cfg, self.notify, self.log)
        assert self.notify.wait_for("READY=1", 90), self.log.read_text()
        assert self.sub.wait_for(lambda: len(self.sub.of("pose")) >= 2, 30), self.log.read_text()

    def notified(self, line: str) -> int:
        """How many notify messages held ``line``."""
        return sum(1 for m in list(self.notify.received) if line in m.splitlines())

    def reload(self, text: str | bytes) -> None:
        """Write the config and SIGHUP; return once the daemon has handled it (its READY=1 after RELOADING=1)."""
        reloading, ready = self.notified("RELOADING=1"), self.notified("READY=1")
        self.cfg.write_bytes(text if isinstance(text, bytes) else text.encode())
        self.proc.send_signal(signal.SIGHUP)
        for line, before in (("RELOADING=1", reloading), ("READY=1", ready)):
            deadline = time.monotonic() + 20
            while self.notified(line) <= before:
                assert time.monotonic() < deadline, self.log.read_text()[-2000:]
                time.sleep(0.002)

    def last_status(self) -> dict:
        n = len(self.sub.of("status"))
        assert self.sub.wait_for(lambda: len(self.sub.of("status")) > n, 5)
        return self.sub.of("status")[-1]

    def publishes_valid_poses(self, count: int = 2) -> bool:
        n = len(self.sub.of("pose"))
        return self.sub.wait_for(lambda: len(self.sub.of("pose")) >= n + count, 20) and \
            all(m["valid"] for m in self.sub.of("pose")[n:])

    def stop(self) -> str:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self.sub.close()
        self.notify.close()
        return self.log.read_text()


def test_broken_reloads_keep_the_running_config(robot: tuple[Path, dict], tmp_path: Path) -> None:
    folder, truth = robot
    good = live_doc(folder, free_endpoint())
    rigs = bad_rigs(truth["rig"], folder / "rig.yaml", tmp_path)
    cases = [(f"endpoint {e}", {**good, "publish": {**good["publish"], "endpoint": e}}, "publish.endpoint")
             for e in ("tcp://127.0.0.1:5560x", "tcp://127.0.0.1:99999", "tcp://127.0.0.1:abc", "tcp://127.0.0.1:*")]
    cases += [(f"rig {name}", {**good, "rig": str(path)}, "rig") for name, path in rigs.items()]
    cases += [("replay path missing", {**good, "source": {**good["source"], "uri": f"replay:{tmp_path}/none"}},
               "source")]
    daemon = Daemon(tmp_path / "live.yaml", good, tmp_path)
    failures = 0
    try:
        for what, doc, field in cases:
            daemon.reload(yaml.safe_dump(doc))
            failures += 1
            assert daemon.proc.poll() is None, what
            status = daemon.last_status()
            assert status["reload_failures"] == failures, what
            assert status["message"].startswith("reload failed, keeping the running config"), (what, status)
            assert f"field '{field}'" in status["message"], (what, status["message"])
            assert daemon.publishes_valid_poses(), what

        # An alias bomb: the message quotes a few dozen characters of it, not 40 MB.
        rest = yaml.safe_dump({k: v for k, v in good.items() if k != "pose"})
        daemon.reload(f"{rest}pose: {{max_rms_px: {ALIAS_BOMB}}}\n")
        failures += 1
        status = daemon.last_status()
        assert "field 'pose.max_rms_px' must be a number" in status["message"]
        assert len(status["message"]) <= MESSAGE_MAX_CHARS and status["reload_failures"] == failures

        # A config that validates but whose source does not open (its preload is refused at open()): the
        # new source is tried, then the old one comes back.
        daemon.reload(yaml.safe_dump({**good, "source": {**good["source"], "preload_max_mb": 0.001}}))
        assert daemon.sub.wait_for(lambda: "back to the previous source" in daemon.sub.of("status")[-1]["message"],
                                   10)
        failures += 1
        assert daemon.publishes_valid_poses()
        assert daemon.last_status()["reload_failures"] == failures

        # A good reload clears the message.
        daemon.reload(yaml.safe_dump(good))
        assert daemon.sub.wait_for(lambda: daemon.sub.of("status")[-1]["message"] == "", 5)
        assert daemon.publishes_valid_poses()
    finally:
        text = daemon.stop()
    assert daemon.proc.returncode == 0, text[-3000:]
    assert "Traceback" not in text
    assert max(len(line) for line in text.splitlines()) < 1000
    assert "field 'rig'" in text and "field 'publish.endpoint'" in text


def mutations(doc: dict, rng: random.Random, n: int) -> list[bytes]:
    """``n`` broken or odd variants of the config ``doc``: a field's type, range or presence changed, the text
    truncated, bytes replaced by random binary."""
    text = yaml.safe_dump(doc).encode()
    paths = []

    def walk(node: object, path: tuple) -> None:
        if isinstance(node, dict):
            for k, v in node.items():
                paths.append(path + (k,))
                walk(v, path + (k,))

    walk(doc, ())
    values = [None, True, False, 0, -1, 1, 2**63, -1e300, 1e-300, float("nan"), float("inf"), "", "x" * 5000,
              "tcp://127.0.0.1:5560x", "replay:/nonexistent", [], [1, 2], {}, {"a": 1}, "\x00", "📷", 99999, 0.5]
    out: list[bytes] = []
    while len(out) < n:
        kind = rng.random()
        if kind < 0.15:
            out.append(text[: rng.randrange(len(text))])
        elif kind < 0.25:
            data = bytearray(text)
            for _ in range(rng.randint(1, 20)):
                data[rng.randrange(len(data))] = rng.randrange(256)
            out.append(bytes(data))
        elif kind < 0.3:
            out.append(bytes(rng.randrange(256) for _ in range(rng.randint(0, 300))))
        else:
            mutated = copy.deepcopy(doc)
            path = rng.choice(paths)
            parent = mutated
            for k in path[:-1]:
                parent = parent[k]
            if kind < 0.45:
                del parent[path[-1]]
            elif kind < 0.5:
                parent[path[-1] + "_typo"] = parent.pop(path[-1])
            else:
                parent[path[-1]] = rng.choice(values)
            out.append(yaml.safe_dump(mutated, allow_unicode=True).encode())
    return out


@pytest.fixture(scope="module")
def still_robot(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One frame, replayed in a loop: a robot that stands still, tracked in every frame (cheap), so that the
    daemon's time goes to the reloads."""
    folder = tmp_path_factory.mktemp("still")
    render_robot(folder, 1, seed=5)
    return folder


def test_reload_fuzz(still_robot: Path, tmp_path: Path) -> None:
    """300 random mutations of the shipped config, each sent as a reload to one daemon (the good config is
    restored after each one it accepted): it never ends, and publishes valid poses on every check."""
    folder = still_robot
    good = live_doc(folder, free_endpoint())
    good_text = yaml.safe_dump(good)
    daemon = Daemon(tmp_path / "live.yaml", good, tmp_path)
    rng = random.Random(10)
    accepted = checks = 0
    t0 = time.monotonic()
    try:
        for i, variant in enumerate(mutations(good, rng, 300)):
            before = daemon.log.read_text().count(" reloaded")
            daemon.reload(variant)
            assert daemon.proc.poll() is None, variant[:300]
            if daemon.log.read_text().count(" reloaded") > before or i % 25 == 24:
                accepted += daemon.log.read_text().count(" reloaded") > before
                daemon.reload(good_text)
                checks += 1
                assert daemon.publishes_valid_poses(), f"after mutation {i}: {variant[:300]!r}"
        assert daemon.publishes_valid_poses()
    finally:
        elapsed = time.monotonic() - t0
        text = daemon.stop()
        statuses = daemon.sub.of("status")
    assert daemon.proc.returncode == 0, text[-3000:]
    assert "Traceback" not in text, text[text.find("Traceback") - 300:][:3000]
    assert max(len(line) for line in text.splitlines()) < 1000
    assert max(len(m["message"]) for m in statuses) <= MESSAGE_MAX_CHARS
    assert statuses[-1]["reload_failures"] >= 200
    print(f"300 mutated reloads in {elapsed:.1f} s: {accepted} accepted, {checks} checks of the good config")
