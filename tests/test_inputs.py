"""Bad inputs give one line naming the file (and the node or field) and exit 2, never a traceback:
unreadable files ("permission denied"), broken rig files, mistyped recording manifests, impossible
numeric options, and images too big to decode (refused from the header)."""

from __future__ import annotations

import json
import os
import shutil
import struct
import subprocess
import sys
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from edgecal.cli import main
from edgecal.config import packaged_config_path
from edgecal.imageheader import image_size

from .unprivileged import run_cli, shared_folder

BOX = str(packaged_config_path("targets/box-100mm.yaml"))


def one_error_line(text: str) -> str:
    lines = text.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("edgecal: error: "), text
    return lines[0]


def run_main(capsys, *args: str) -> tuple[int, str]:
    """The CLI in-process: its exit code and its error line (a traceback would fail the test)."""
    try:
        rc = main(list(args))
    except SystemExit as exc:  # argparse
        rc = exc.code
    return rc, capsys.readouterr().err


# --- a stereo rig.yaml to break node by node -------------------------------------------------------

K = np.array([[800.0, 0, 640], [0, 800, 400], [0, 0, 1]])


def rig_nodes() -> dict[str, object]:
    return {"image_size": [1280, 800], "camera_matrix_left": K, "dist_coeffs_left": np.zeros((1, 5)),
            "camera_matrix_right": K, "dist_coeffs_right": np.zeros((1, 5)), "R": np.eye(3),
            "T": np.array([[-0.1], [0.0], [0.0]])}


def write_rig(path: Path, nodes: dict[str, object]) -> Path:
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    for name, value in nodes.items():
        if isinstance(value, list):
            fs.startWriteStruct(name, cv2.FileNode_SEQ | cv2.FileNode_FLOW)
            for v in value:
                fs.write("", v)
            fs.endWriteStruct()
        else:
            fs.write(name, value)
    fs.release()
    return path


def live_config(folder: Path, rig: Path) -> Path:
    frames = folder / "frames"
    frames.mkdir(exist_ok=True)
    cv2.imwrite(str(frames / "000000.png"), np.zeros((8, 8), np.uint8))
    cfg = folder / "live.yaml"
    cfg.write_text(f"source: {{driver: replay, path: {frames}}}\nrig: {rig}\ntarget: targets/robot-3boards.yaml\n")
    return cfg


def _with(**changes):
    nodes = rig_nodes()
    nodes.update(changes)
    return nodes


NAN_K = K.copy()
NAN_K[0, 0] = np.nan
BROKEN_RIGS = {
    "text": ("hello, this is not a calibration\n", "not an OpenCV YAML/XML calibration file"),
    "binary": (b"\x89\x00\xff\xfe" * 64, "not an OpenCV YAML/XML calibration file"),
    "no nodes": ("%YAML:1.0\n---\nsomething_else: 1\n", "node 'image_size' is missing"),
    "no camera": ("%YAML:1.0\n---\nimage_size: [1280, 800]\n", "node 'camera_matrix' is missing"),
    "scalar matrix": (_with(camera_matrix_left=5.0), "node 'camera_matrix_left' must be an OpenCV matrix"),
    "nan focal": (_with(camera_matrix_left=NAN_K), "node 'camera_matrix_left' holds NaN"),
    "zero focal": (_with(camera_matrix_right=np.diag([0.0, 800, 1])), "node 'camera_matrix_right' must have "
                                                                     "positive focal lengths (fx 0"),
    "negative focal": (_with(camera_matrix_left=np.diag([-800.0, 800, 1])), "positive focal lengths (fx -800"),
    "1x9 matrix": (_with(camera_matrix_left=K.reshape(1, 9)), "'camera_matrix_left' must be a 3x3 matrix (is 1x9)"),
    "last row": (_with(camera_matrix_left=np.diag([800.0, 800, 2])), "[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]"),
    "7 coefficients": (_with(dist_coeffs_left=np.array([[0, 0, 0, 0, 0, 0.1, 0]])),
                       "'dist_coeffs_left' has 7 numbers; the radtan model has 5"),
    "NaN coefficient": (_with(dist_coeffs_right=np.array([[0, np.nan, 0, 0, 0]])), "'dist_coeffs_right' holds NaN"),
    "2x5 coefficients": (_with(dist_coeffs_right=np.zeros((2, 5))), "'dist_coeffs_right' must be a row"),
    "not a rotation": (_with(R=np.diag([1.0, 1, -1])), "node 'R' is not a rotation matrix"),
    "R shape": (_with(R=np.eye(4)), "node 'R' must be a 3x3 matrix (is 4x4)"),
    "zero baseline": (_with(T=np.zeros((3, 1))), "node 'T' is zero"),
    "T nan": (_with(T=np.array([[np.nan], [0], [0]])), "node 'T' holds NaN"),
    "image size": (_with(image_size=[1280]), "node 'image_size' must be [width, height]"),
    "negative size": (_with(image_size=[1280, -800]), "node 'image_size' must be [width, height]"),
    "P1 shape": (_with(P1=np.eye(3)), "node 'P1' must be a 3x4 matrix (is 3x3)"),
}


@pytest.mark.parametrize("case", list(BROKEN_RIGS))
def test_a_broken_rig_file_is_one_line_naming_file_and_node(tmp_path, capsys, case):
    content, expected = BROKEN_RIGS[case]
    rig = tmp_path / "rig.yaml"
    if isinstance(content, dict):
        write_rig(rig, content)
    elif isinstance(content, bytes):
        rig.write_bytes(content)
    else:
        rig.write_text(content)
    rc, err = run_main(capsys, "run", "--config", str(live_config(tmp_path, rig)), "--check")
    line = one_error_line(err)
    assert rc == 2 and str(rig) in line and expected in line, line


def test_a_good_rig_still_loads(tmp_path):
    from edgecal.calibration.io import load_rig
    rig = load_rig(write_rig(tmp_path / "rig.yaml", _with(P1=np.hstack([K, np.zeros((3, 1))]))))
    assert rig.is_stereo and rig.image_size == (1280, 800) and rig.extra["P1"].shape == (3, 4)
    assert np.allclose(rig.stereo.t_right_left_m, [-0.1, 0, 0])


def test_load_rig_errors_are_edgecal_errors(tmp_path):
    """The daemon's reload relies on this: every problem of a rig file is an EdgecalError."""
    from edgecal.calibration.io import load_rig
    from edgecal.errors import EdgecalError
    for case, (content, _expected) in BROKEN_RIGS.items():
        rig = tmp_path / f"{case}.yaml"
        if isinstance(content, dict):
            write_rig(rig, content)
        elif isinstance(content, bytes):
            rig.write_bytes(content)
        else:
            rig.write_text(content)
        with pytest.raises(EdgecalError, match="node|OpenCV"):
            load_rig(rig)


# --- permission denied, as an unprivileged user ---------------------------------------------------

def test_unreadable_inputs_say_permission_denied():
    root = shared_folder()
    try:
        image = root / "board.png"
        cv2.imwrite(str(image), np.full((60, 80), 128, np.uint8))
        target = root / "target.yaml"
        shutil.copy(BOX, target)
        config = root / "calibration.yaml"
        config.write_text("acceptance:\n  max_rms_px: 1.0\n")
        rig = write_rig(root / "rig.yaml", rig_nodes())
        live = live_config(root, rig)
        rec = _recording(root / "rec", {})
        log = root / "log.mcap"
        log.write_bytes(b"\x89MCAP0\r\n")
        corners = root / "rig.corners.csv"
        corners.write_text("# edgecal corners\n")
        for p in root.rglob("*"):
            p.chmod(0o755 if p.is_dir() else 0o644)
        cases = [
            (image, ["detect", "--board", "9x6", str(image)]),
            (target, ["detect", "--target", str(target), str(image)]),
            (config, ["calibrate", "--target", BOX, "--left", str(image), "--out", str(root / "out.yaml"),
                      "--config", str(config)]),
            (rig, ["run", "--config", str(live), "--check"]),
            (live, ["run", "--config", str(live), "--check"]),
            (root / "frames" / "000000.png", ["capture", f"replay:{root / 'frames'}", "--frames", "1"]),
            (root / "frames", ["detect", "--board", "9x6", str(root / "frames")]),
            (rec / "manifest.json", ["capture", f"replay:{rec}", "--frames", "1"]),
            (log, ["capture", f"mcap:{log}?topic=/camera/image_raw", "--frames", "1"]),
            (corners, ["calibrate", "--target", BOX, "--corners", str(corners), "--out", str(root / "o.yaml")]),
        ]
        for unreadable, args in cases:
            unreadable.chmod(0o000)
            try:
                res = run_cli(args, cache=root)
            finally:
                unreadable.chmod(0o755 if unreadable.is_dir() else 0o644)
            line = one_error_line(res.stderr)
            assert res.returncode == 2, (args, res.stderr)
            assert str(unreadable) in line and "permission denied" in line, line
    finally:
        shutil.rmtree(root, ignore_errors=True)


# --- capture of a recording whose manifest has wrong types ----------------------------------------

def _recording(folder: Path, entry: dict) -> Path:
    (folder / "frames").mkdir(parents=True)
    cv2.imwrite(str(folder / "frames" / "000000.png"), np.zeros((8, 8), np.uint8))
    frame = {"file": "frames/000000.png", "stamp_ns": 0, "seq": 0, "camera_id": "cam"}
    frame.update(entry)
    (folder / "manifest.json").write_text(json.dumps({"format": "edgecal-recording", "version": 1,
                                                      "layout": "mono", "frames": [frame]}))
    return folder


@pytest.mark.parametrize("entry, expected", [
    ({"stamp_ns": "abc"}, "frames[0].stamp_ns must be an integer"),
    ({"seq": 1.5}, "frames[0].seq must be an integer"),
    ({"file": 5}, "frames[0].file must be a file name"),
    ({"camera_id": 7}, "frames[0].camera_id must be a string"),
    ({"exposure_us": "long"}, "frames[0].exposure_us must be a number"),
])
def test_capture_on_a_mistyped_manifest_is_one_line(tmp_path, entry, expected):
    rec = _recording(tmp_path / "rec", entry)
    res = subprocess.run([sys.executable, "-m", "edgecal", "capture", f"replay:{rec}", "--frames", "1"],
                         capture_output=True, text=True, timeout=120)
    line = one_error_line(res.stderr)
    assert res.returncode == 2 and "manifest.json" in line and expected in line, line


# --- numeric options -------------------------------------------------------------------------------

@pytest.mark.parametrize("value", ["nan", "inf", "-inf", "0", "-1", "abc"])
@pytest.mark.parametrize("command", [
    ["calibrate", "--board", "9x6", "--left", "L.png", "--out", "rig.yaml", "--square-mm"],
    ["detect", "--board", "9x6", "img.png", "--square-mm"],
    ["capture", "replay:nowhere", "--frames"],
    ["record", "replay:nowhere", "--out", "rec", "--seconds"],
    ["render", "planar", "--out", "out", "--count"],
    ["render", "planar", "--out", "out", "--square-px"],
    ["detect", "--board", "9x6", "img.png", "--max-pixels"],
])
def test_impossible_numbers_are_refused_by_the_parser(tmp_path, capsys, monkeypatch, command, value):
    monkeypatch.chdir(tmp_path)
    rc, err = run_main(capsys, *command, value)
    last = err.strip().splitlines()[-1]
    assert rc == 2 and "error: argument" in last and command[-1] in last, err
    assert "Traceback" not in err and not list(tmp_path.iterdir())


def test_square_mm_nan_used_to_reach_the_solver(tmp_path):
    """The reported traceback: calibrate --square-mm nan with real board images."""
    for i in range(3):
        img = np.full((480, 640), 255, np.uint8)
        cv2.imwrite(str(tmp_path / f"v{i}.png"), img)
    res = subprocess.run([sys.executable, "-m", "edgecal", "calibrate", "--board", "9x6", "--square-mm", "nan",
                          "--left", str(tmp_path), "--out", str(tmp_path / "rig.yaml")],
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 2 and "Traceback" not in res.stderr
    assert "argument --square-mm: expected a finite number, got 'nan'" in res.stderr


# --- max_pixels: refused from the header, before decoding ------------------------------------------

def png_of_zeros(width: int, height: int) -> bytes:
    """A valid 8-bit grey PNG of zeros, compressed row by row (never holds the pixels in memory)."""
    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))
    z = zlib.compressobj(9)
    row = bytes(width + 1)  # filter byte 0 + the row
    parts = [z.compress(row) for _ in range(height)]
    idat = b"".join(parts) + z.flush()
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0))
            + chunk(b"IDAT", idat) + chunk(b"IEND", b""))


@pytest.fixture(scope="module")
def huge_png(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("huge") / "huge.png"
    path.write_bytes(png_of_zeros(20000, 20000))
    return path


def test_the_generated_png_is_real(tmp_path):
    small = tmp_path / "small.png"
    small.write_bytes(png_of_zeros(300, 200))
    assert cv2.imread(str(small), cv2.IMREAD_UNCHANGED).shape == (200, 300)


def run_measured(args: list[str]) -> tuple[int, str, int]:
    """The CLI in a subprocess: exit code, stderr and its peak resident memory (MB)."""
    proc = subprocess.Popen([sys.executable, "-m", "edgecal", *args], stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True)
    err = proc.stderr.read()
    _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    return proc.returncode, err, usage.ru_maxrss // 1024


def test_a_huge_png_is_refused_before_decoding(huge_png, tmp_path):
    assert huge_png.stat().st_size < 1 << 20          # 400 MP in under 1 MB
    expected = "20000x20000 is 400 MP, more than max_pixels (67.1 MP); refused before decoding"
    baseline = run_measured(["detect", "--board", "9x6", str(tmp_path / "missing.png")])[2]
    frames = tmp_path / "frames"
    frames.mkdir()
    (frames / "000000.png").symlink_to(huge_png)
    for args in (["detect", "--board", "9x6", str(huge_png)],
                 ["calibrate", "--board", "9x6", "--square-mm", "30", "--left", str(huge_png),
                  "--out", str(tmp_path / "rig.yaml")],
                 ["capture", f"replay:{frames}", "--frames", "1"]):
        rc, err, peak_mb = run_measured(args)
        line = one_error_line(err)
        assert rc == 2 and ".png: " in line and expected in line, line
        # decoding would need 400 MB more than the same command on a missing file
        assert peak_mb < baseline + 100, (args, peak_mb, baseline)


def test_max_pixels_is_settable(tmp_path, capsys):
    img = tmp_path / "vga.png"
    cv2.imwrite(str(img), np.zeros((480, 640), np.uint8))
    rc, err = run_main(capsys, "detect", "--board", "9x6", "--max-pixels", "300000", str(img))
    assert rc == 2 and "640x480 is 0.307 MP, more than max_pixels (0.3 MP)" in one_error_line(err)
    assert run_main(capsys, "detect", "--board", "9x6", "--max-pixels", "307200", str(img))[0] == 0
    from edgecal.drivers import open_source
    from edgecal.errors import InputError
    with open_source(f"replay:{tmp_path}?max_pixels=1000") as src, pytest.raises(InputError, match="max_pixels"):
        src.read()
    with open_source(f"replay:{tmp_path}") as src:
        assert src.read().image.shape == (480, 640)


@pytest.mark.parametrize("ext, shape, dtype", [
    (".png", (23, 37), np.uint8), (".png", (23, 37, 3), np.uint16), (".jpg", (23, 37), np.uint8),
    (".jpg", (23, 37, 3), np.uint8), (".bmp", (23, 37, 3), np.uint8), (".tiff", (23, 37), np.uint16),
    (".tiff", (23, 37, 3), np.uint8), (".pgm", (23, 37), np.uint8), (".ppm", (23, 37, 3), np.uint8),
    (".pam", (23, 37), np.uint8), (".webp", (23, 37, 3), np.uint8),
])
def test_header_sizes_match_what_opencv_encodes(ext, shape, dtype):
    ok, buf = cv2.imencode(ext, np.zeros(shape, dtype))
    assert ok
    assert image_size(buf.tobytes()) == (37, 23)


def test_lossless_webp_header():
    ok, buf = cv2.imencode(".webp", np.zeros((23, 37, 3), np.uint8), [cv2.IMWRITE_WEBP_QUALITY, 101])
    assert ok and image_size(buf.tobytes()) == (37, 23)


def test_unknown_or_truncated_headers_give_none():
    assert image_size(b"") is None
    assert image_size(b"\x89PNG\r\n\x1a\n\x00\x00") is None
    assert image_size(b"GIF89a....") is None


def test_a_video_above_max_pixels_is_refused_at_open(tmp_path):
    from edgecal.drivers import open_source
    from edgecal.errors import InputError
    path = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 25.0, (64, 48))
    for _ in range(3):
        writer.write(np.zeros((48, 64, 3), np.uint8))
    writer.release()
    with pytest.raises(InputError, match=r"clip.avi: 64x48 frames are 0.00307 MP, more than max_pixels \(0.003 MP\)"):
        with open_source(f"replay:{path}?max_pixels=3000"):
            pass
    with open_source(f"replay:{path}?max_pixels=3072") as src:
        assert src.read().image.shape == (48, 64, 3)
