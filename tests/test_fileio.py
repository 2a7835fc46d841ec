"""Every output is written atomically with the umask's permissions, survives a killed writer, and
refuses cleanly (one line, exit 2, before any work) where it cannot be written."""

from __future__ import annotations

import os
import random
import shutil
import signal
import stat
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from edgecal.config import packaged_config_path
from edgecal.errors import InputError
from edgecal.fileio import (
    TEMP_SUFFIX,
    remove_stale_temps,
    supports_unnamed_temporaries,
    write_atomic_set,
)

from .unprivileged import run_cli, shared_folder

BOX = str(packaged_config_path("targets/box-100mm.yaml"))


def cli(*args: str, umask: int = 0o022, cwd: Path | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "edgecal", *args], capture_output=True, text=True, timeout=600,
                          cwd=cwd, preexec_fn=lambda: os.umask(umask))


def one_error_line(res: subprocess.CompletedProcess) -> str:
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("edgecal: error: "), res.stderr
    return lines[0]


def modes(folder: Path) -> dict[str, int]:
    return {str(p.relative_to(folder)): stat.S_IMODE(p.stat().st_mode) for p in folder.rglob("*") if p.is_file()}


@pytest.fixture(scope="module")
def box_pair(tmp_path_factory):
    d = tmp_path_factory.mktemp("box")
    res = cli("render", "box", "--out", str(d), "--size", "800x600", "--photometric", "clean")
    assert res.returncode == 0, res.stderr
    return d / "box_000_L.png", d / "box_000_R.png"


@pytest.mark.parametrize("umask", [0o022, 0o027])
def test_every_output_gets_the_umask_permissions(tmp_path, box_pair, umask):
    """rig.yaml, camera_info, report, renders, overlays and recordings: 0666 minus the umask, not 0600."""
    left, right = box_pair
    steps = [
        ("render", "planar", "--out", str(tmp_path / "render"), "--count", "2"),
        ("calibrate", "--target", BOX, "--left", str(left), "--right", str(right),
         "--out", str(tmp_path / "rig.yaml"), "--report", str(tmp_path / "report")),
        ("detect", "--board", "9x6", "--draw", str(tmp_path / "overlays"), str(tmp_path / "render")),
        ("record", f"replay:{tmp_path / 'render'}", "--out", str(tmp_path / "recording")),
    ]
    for args in steps:
        res = cli(*args, umask=umask)
        assert res.returncode == 0, (args, res.stderr)
    found = modes(tmp_path)
    for name in ("rig.yaml", "rig.left.camera_info.yaml", "rig.right.camera_info.yaml", "report/summary.txt",
                 "report/overlay_left.png", "render/planar_000.png", "render/planar_000.json",
                 "overlays/planar_000_detect.png", "recording/manifest.json", "recording/frames/000000.png"):
        assert found.get(name) == 0o666 & ~umask, (name, oct(found.get(name, 0)))
    assert set(found.values()) == {0o666 & ~umask}, {k: oct(v) for k, v in found.items()}
    assert not [n for n in found if TEMP_SUFFIX in n]


WRITER = textwrap.dedent("""
    import sys
    from pathlib import Path
    from edgecal.fileio import write_atomic
    out = Path(sys.argv[1])
    size = 8 << 20
    write_atomic(out / "same.bin", bytes([0]) * size)
    print("ready", flush=True)
    i = 0
    while True:
        i += 1
        data = bytes([i % 251]) * size
        write_atomic(out / "same.bin", data)           # replaces a file
        write_atomic(out / f"new_{i:05d}.bin", data)   # creates one
""")


def _whole(path: Path) -> bool:
    data = path.read_bytes()
    return len(data) == 8 << 20 and data.count(data[:1]) == len(data)


NEXT_WRITER = "import sys; from edgecal.fileio import write_atomic; write_atomic(sys.argv[1], bytes(16))"


def test_killed_writer_leaves_no_temporary_and_no_half_file(tmp_path):
    rng = random.Random(3)
    leftovers = 0
    for _ in range(8):
        proc = subprocess.Popen([sys.executable, "-c", WRITER, str(tmp_path)], stdout=subprocess.PIPE, text=True)
        assert proc.stdout.readline().strip() == "ready"
        # mid-write: one 8 MB file takes several ms to write and fsync, the moves microseconds
        subprocess.run(["sleep", f"{rng.uniform(0.02, 0.3):.3f}"])
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        names = os.listdir(tmp_path)
        for name in names:
            if name.endswith(TEMP_SUFFIX):
                leftovers += 1
            else:
                assert _whole(tmp_path / name), name
        assert not [n for n in names if n.startswith(".") and not n.endswith(TEMP_SUFFIX)], names
        # whatever a killed writer left named is removed by the next writer into the folder
        subprocess.run([sys.executable, "-c", NEXT_WRITER, str(tmp_path / "probe.bin")], check=True)
        assert not [n for n in os.listdir(tmp_path) if n.startswith(".")]
        (tmp_path / "probe.bin").unlink()
    if supports_unnamed_temporaries(tmp_path):
        # a temporary has a name only between the two system calls that move it onto an existing file
        assert leftovers <= 1
    # else (no O_TMPFILE here, e.g. overlayfs before Linux 6.6): named temporaries, swept as checked above


def test_stale_temporaries_of_dead_writers_are_removed(tmp_path):
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True,
                          text=True).stdout.strip()
    stale = tmp_path / f".rig.yaml.{dead}-0123abcd{TEMP_SUFFIX}"
    live = tmp_path / f".rig.yaml.{os.getpid()}-0123abcd{TEMP_SUFFIX}"
    other = tmp_path / ".hidden-but-not-ours"
    for p in (stale, live, other):
        p.write_bytes(b"x")
    assert remove_stale_temps(tmp_path) == [stale]
    assert live.exists() and other.exists() and not stale.exists()


def test_a_set_is_written_all_or_nothing(tmp_path):
    (tmp_path / "rig.yaml").write_text("old")
    (tmp_path / "blocker").write_text("a file where a folder should be")
    with pytest.raises(InputError, match="blocker"):
        write_atomic_set({tmp_path / "rig.yaml": b"new", tmp_path / "blocker" / "rig.left.camera_info.yaml": b"x"})
    assert (tmp_path / "rig.yaml").read_text() == "old"
    assert sorted(os.listdir(tmp_path)) == ["blocker", "rig.yaml"]
    write_atomic_set({tmp_path / "rig.yaml": b"new", tmp_path / "rig.left.camera_info.yaml": b"info"})
    assert (tmp_path / "rig.yaml").read_text() == "new"


def test_calibrate_refuses_an_output_path_under_a_file_before_working(tmp_path):
    """A parent that is a regular file fails even for root; refused before the images are even read."""
    blocker = tmp_path / "blocker"
    blocker.write_text("not a folder")
    not_an_image = tmp_path / "L.png"
    not_an_image.write_text("the images would be refused if they were read first")
    for out, report in ((blocker / "rig.yaml", None), (tmp_path / "rig.yaml", blocker / "report")):
        args = ["calibrate", "--target", BOX, "--left", str(not_an_image), "--out", str(out)]
        res = cli(*args, *(["--report", str(report)] if report else []))
        line = one_error_line(res)
        assert res.returncode == 2 and "blocker is a file, not a folder" in line, line


def test_read_only_output_folders_are_refused_before_working():
    """calibrate --out/--report, record, detect --draw and render into a folder this user cannot write."""
    root = shared_folder()
    try:
        ro = root / "read-only"
        ro.mkdir()
        not_an_image = root / "L.png"
        not_an_image.write_text("the images would be refused if they were read first")
        not_an_image.chmod(0o644)
        ro.chmod(0o555)
        frames = root / "frames"
        frames.mkdir()
        (frames / "000000.png").write_bytes(b"not read either")
        cases = [
            ["calibrate", "--target", BOX, "--left", str(not_an_image), "--out", str(ro / "rig.yaml")],
            ["calibrate", "--target", BOX, "--left", str(not_an_image), "--out", str(root / "rig.yaml"),
             "--report", str(ro / "report")],
            ["detect", "--board", "9x6", "--draw", str(ro / "overlays"), str(not_an_image)],
            ["record", f"replay:{frames}", "--out", str(ro / "recording")],
            ["render", "planar", "--out", str(ro / "render")],
        ]
        for args in cases:
            res = run_cli(args, cache=root)
            line = one_error_line(res)
            assert res.returncode == 2 and "permission denied" in line and str(ro) in line, (args, line)
        assert not list(ro.iterdir())
    finally:
        shutil.rmtree(root, ignore_errors=True)
