"""`calibrate --report DIR`: one self-contained index.html with every figure embedded, the PNGs beside it,
views named by file (skipped ones with the reason), and a real browser renders it."""

import re
import shutil
import subprocess

import cv2
import numpy as np
import pytest

from edgecal.cli import main
from edgecal.synth.handheld import handheld_rig, handheld_sequence

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    """A stereo calibration from 7 rendered pairs and one pair without a board, with its report."""
    d = tmp_path_factory.mktemp("report")
    (d / "left").mkdir()
    (d / "right").mkdir()
    rig = handheld_rig(8, stereo=True)
    for i, f in enumerate(handheld_sequence(8, rig, n_poses=7, hold_frames=1, move_frames=0), start=1):
        cv2.imwrite(str(d / "left" / f"cam0_{i}.png"), f.left.image)
        cv2.imwrite(str(d / "right" / f"cam1_{i}.png"), f.right.image)
    blank = np.full((480, 640), 90, np.uint8)
    cv2.imwrite(str(d / "left" / "cam0_8.png"), blank)
    cv2.imwrite(str(d / "right" / "cam1_8.png"), blank)
    rc = main(["calibrate", "--board", "9x6", "--square-mm", "30", "--left", str(d / "left"), "--right",
               str(d / "right"), "--out", str(d / "rig.yaml"), "--report", str(d / "rep")])
    assert rc == 0
    return d / "rep"


def test_index_html_is_self_contained_and_names_views(report):
    page = (report / "index.html").read_text(encoding="utf-8")
    assert "ACCEPTED" in page and "Acceptance bounds" in page and "± " in page
    # every figure is embedded; nothing is fetched from elsewhere
    sources = re.findall(r'src="([^"]*)"', page)
    assert len(sources) >= 12 and all(s.startswith("data:image/png;base64,") for s in sources)
    assert not re.search(r"<(script|link)\b", page)
    for name in ("view_rms.png", "residuals_left.png", "coverage_right.png", "residual_radius_left.png",
                 "distortion_right.png", "rectified_pair.png", "residual_histogram.png"):
        assert (report / name).stat().st_size > 5000, name  # the PNGs are kept beside the page
    for i in range(1, 8):
        assert f"cam0_{i}.png" in page and (report / f"overlay_left_cam0_{i}.png").is_file()
    assert re.search(r"cam0_8\.png</td>.*?<td>no</td>.*?board not found in either image", page, re.S)
    assert not (report / "overlay_left_cam0_8.png").exists()
    assert "Provenance" in page and "chessboard-9x6" in page


@pytest.mark.skipif(CHROMIUM is None, reason="Chromium is not installed (Debian package chromium)")
def test_a_real_browser_renders_the_report(report, tmp_path):
    shot = tmp_path / "report.png"
    subprocess.run([CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                    "--disable-component-update", "--disable-sync", "--no-first-run",
                    f"--user-data-dir={tmp_path / 'profile'}", "--hide-scrollbars", "--window-size=1200,3000",
                    f"--screenshot={shot}", (report / "index.html").as_uri()],
                   check=True, capture_output=True, timeout=120)
    img = cv2.imread(str(shot))
    assert img is not None and img.shape[:2] == (3000, 1200)
    # the green verdict banner near the top (#2e7d32 in BGR) ...
    top = img[:200].reshape(-1, 3).astype(int)
    assert np.sum(np.all(np.abs(top - [50, 125, 46]) < 12, axis=1)) > 5000
    # ... and figures drawn below it: the page is not a blank or broken render
    assert img[800:].std() > 20
    shutil.copy(shot, report / "screenshot.png")  # for a person to look at
