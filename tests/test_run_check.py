"""`edgecal run --check` (and a start) on broken inputs: one line naming the field, exit 2, no traceback;
including what would only fail once the loop runs (a replay without frames, a rig that cannot be used)."""

from __future__ import annotations

import copy
import subprocess
import sys
from pathlib import Path

import cv2
import pytest
import yaml

from edgecal.cli import main
from edgecal.errors import QUOTE_MAX_CHARS, quote

from .live_fixtures import ALIAS_BOMB, bad_rigs, free_endpoint, render_robot, write_config, write_rig_yaml


@pytest.fixture(scope="module")
def robot(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict]:
    folder = tmp_path_factory.mktemp("robot")
    return folder, render_robot(folder, 2, seed=5)


def broken_configs(folder: Path, truth: dict, tmp: Path) -> dict[str, tuple[dict, str]]:
    """Config documents that must be refused, each with the field the message must name."""
    good = yaml.safe_load(write_config(tmp / "good.yaml", folder, free_endpoint()).read_text())
    cases: dict[str, tuple[dict, str]] = {}
    for port in ("5560x", "99999", "abc", "*", "0"):
        cases[f"port {port}"] = ({**good, "publish": {"endpoint": f"tcp://127.0.0.1:{port}"}}, "publish.endpoint")
    cases["no port"] = ({**good, "publish": {"endpoint": "tcp://127.0.0.1"}}, "publish.endpoint")
    cases["remote"] = ({**good, "publish": {"endpoint": "tcp://*:5560"}}, "publish.endpoint")
    for name, path in bad_rigs(truth["rig"], folder / "rig.yaml", tmp).items():
        cases[f"rig {name}"] = ({**good, "rig": str(path)}, "rig")
    other = copy.deepcopy(truth["rig"])
    other["left"]["image_size"] = [640, 400]
    cases["rig size differs from the replay's"] = ({**good, "rig": str(write_rig_yaml(other, tmp / "small.yaml"))},
                                                  "rig")
    cases["rig size differs from the cameras'"] = ({**good, "source": {"stereo": {
        "left": {"uri": "v4l2:/dev/video-absent0", "width": 640, "height": 480},
        "right": {"uri": "v4l2:/dev/video-absent1", "width": 640, "height": 480}}}}, "rig")
    cases["replay path missing"] = ({**good, "source": {"driver": "replay", "path": str(tmp / "none")}}, "source")
    empty = tmp / "empty"
    (empty / "left").mkdir(parents=True)
    (empty / "right").mkdir()
    cases["replay without frames"] = ({**good, "source": {"driver": "replay", "path": str(empty)}}, "source")
    cases["replay of single images"] = ({**good, "source": {"driver": "replay", "path": str(folder / "left")}},
                                        "source")
    cases["one camera"] = ({**good, "source": {"uri": "v4l2:/dev/video-absent0"}}, "source")
    return cases


CASES = ("port 5560x", "port 99999", "port abc", "port *", "port 0", "no port", "remote", "rig text file",
         "rig no nodes", "rig bad node", "rig nan focal", "rig zero focal", "rig baseline in mm",
         "rig absurd baseline", "rig size differs from the replay's",
         "rig size differs from the cameras'", "replay path missing", "replay without frames",
         "replay of single images", "one camera")


@pytest.mark.parametrize("case", CASES)
def test_check_refuses_in_one_line(robot: tuple[Path, dict], tmp_path: Path, case: str,
                                   capsys: pytest.CaptureFixture) -> None:
    folder, truth = robot
    doc, field = broken_configs(folder, truth, tmp_path)[case]
    cfg = tmp_path / "live.yaml"
    cfg.write_text(yaml.safe_dump(doc))
    assert main(["run", "--check", "--config", str(cfg)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"field '{field}'" in err[0], err


@pytest.mark.parametrize("case", ["port 5560x", "rig text file", "rig bad node", "replay without frames"])
def test_start_refuses_in_one_line(robot: tuple[Path, dict], tmp_path: Path, case: str) -> None:
    """The same at a real start: exit 2 before any device opens, one line, no traceback."""
    folder, truth = robot
    doc, field = broken_configs(folder, truth, tmp_path)[case]
    cfg = tmp_path / "live.yaml"
    cfg.write_text(yaml.safe_dump(doc))
    res = subprocess.run([sys.executable, "-m", "edgecal", "run", "--config", str(cfg)], capture_output=True,
                         text=True, timeout=120, check=False)
    assert res.returncode == 2, res.stderr
    assert len(res.stderr.strip().splitlines()) == 1 and f"field '{field}'" in res.stderr, res.stderr


def test_check_accepts_the_good_config(robot: tuple[Path, dict], tmp_path: Path,
                                       capsys: pytest.CaptureFixture) -> None:
    folder, _ = robot
    cfg = write_config(tmp_path / "live.yaml", folder, free_endpoint())
    assert main(["run", "--check", "--config", str(cfg)]) == 0
    assert "OK" in capsys.readouterr().out


def test_alias_bomb_is_quoted_short(robot: tuple[Path, dict], tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """A few hundred bytes of YAML aliases expand to gigabytes of repr: the message quotes 80 characters."""
    folder, _ = robot
    cfg = write_config(tmp_path / "live.yaml", folder, free_endpoint())
    cfg.write_text(cfg.read_text() + f"pose: {{max_rms_px: {ALIAS_BOMB}}}\n")
    assert main(["run", "--check", "--config", str(cfg)]) == 2
    err = capsys.readouterr().err.strip()
    assert "field 'pose.max_rms_px' must be a number" in err and len(err) < len(str(cfg)) + 200


def test_quote_caps_every_kind_of_value() -> None:
    deep = yaml.safe_load(ALIAS_BOMB)
    for value in (deep, "x" * 10**6, b"\x00" * 10**6, 10**5000, {str(i): i for i in range(10**4)}, [[[[[1]]]]]):
        assert len(quote(value)) <= QUOTE_MAX_CHARS
    assert quote("abc") == "'abc'" and quote(3.5) == "3.5"


def test_a_huge_key_is_named_short(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    cfg = tmp_path / "live.yaml"
    cfg.write_text(yaml.safe_dump({"k" * 100000: 1}))
    assert main(["run", "--check", "--config", str(cfg)]) == 2
    assert len(capsys.readouterr().err) < 400


def test_image_of_the_replay_is_checked_once(robot: tuple[Path, dict]) -> None:
    """replay_contents reads what --check needs: frame count, layout, first size."""
    from edgecal.drivers.replay import replay_contents
    from edgecal.drivers.spec import parse_uri
    folder, _ = robot
    contents = replay_contents(parse_uri(f"replay:{folder}"))
    h, w = cv2.imread(str(folder / "left" / "000000.png"), cv2.IMREAD_UNCHANGED).shape[:2]
    assert contents.frames == 2 and contents.stereo and contents.image_size == (w, h)
