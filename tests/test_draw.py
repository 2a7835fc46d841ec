"""`detect --draw` overlays: by default what a user checks (outline, first corner, row direction, ids, name,
"not found" with the near-miss note); the detector's debug layers only with --debug."""

import cv2
import numpy as np
import pytest

from edgecal import detect_debug
from edgecal.cli import main
from edgecal.detection.draw import FIRST, board_outline, draw_overlay
from edgecal.detection.types import DetectionDebug
from edgecal.synth.scenes import planar_view
from edgecal.targets import parse_board_spec


@pytest.fixture(scope="module")
def view():
    v = planar_view(1, photometric="clean", background="clutter")
    return v.image, detect_debug(v.image, parse_board_spec("9x6"))


def _changed(a, b):
    return np.any(a != b, axis=2)


def test_default_overlay_draws_the_board_not_the_debug_layers(view):
    grey, debug = view
    assert len(debug.detections) == 1 and len(debug.candidates) > 54  # clutter gives candidates off the board
    plain = cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR)
    default, full = draw_overlay(grey, debug), draw_overlay(grey, debug, show_debug=True)
    outline = board_outline(debug.detections[0])
    assert len(outline) == 4  # a complete board: its four extreme corners
    # away from the board (and its labels) the default picture is the image itself; --debug draws there
    mask = np.zeros(grey.shape, np.uint8)
    hull = cv2.convexHull(outline.astype(np.float32)).astype(np.int32)
    cv2.fillConvexPoly(mask, hull, 1)
    far = cv2.dilate(mask, np.ones((81, 81), np.uint8)) == 0
    assert not _changed(default, plain)[far].any()
    assert _changed(full, plain)[far].sum() > 50
    # the first corner is ringed in the first-corner colour
    det = debug.detections[0]
    c0 = det.corners[[i for i, (c, r) in enumerate(det.ids) if (c, r) == (0, 0)][0]]
    x, y = int(round(c0[0])), int(round(c0[1]))
    patch = default[y - 12:y + 13, x - 12:x + 13].reshape(-1, 3)
    assert np.sum(np.all(patch == FIRST, axis=1)) > 10


def test_a_miss_says_not_found_and_why():
    grey = np.full((480, 640), 128, np.uint8)
    quiet = draw_overlay(grey, DetectionDebug(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros((0, 4)), np.zeros(0)))
    noted = draw_overlay(grey, DetectionDebug(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros((0, 4)), np.zeros(0),
                                              notes=["found a 9x6 grid; the target says 8x6 inner corners"]))
    assert _changed(quiet, cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR))[:45, :200].sum() > 500   # the banner
    assert _changed(noted, quiet)[48:80].sum() > 500                                         # the note below it
    assert not _changed(noted, quiet)[100:].any()


def test_cli_debug_flag(view, tmp_path, capsys):
    grey, _ = view
    cv2.imwrite(str(tmp_path / "v.png"), grey)
    assert main(["detect", "--board", "9x6", "--draw", str(tmp_path / "a"), str(tmp_path / "v.png")]) == 0
    assert main(["detect", "--board", "9x6", "--draw", str(tmp_path / "b"), "--debug", str(tmp_path / "v.png")]) == 0
    capsys.readouterr()
    a, b = cv2.imread(str(tmp_path / "a" / "v_detect.png")), cv2.imread(str(tmp_path / "b" / "v_detect.png"))
    assert a.shape == b.shape and _changed(a, b).sum() > 50
