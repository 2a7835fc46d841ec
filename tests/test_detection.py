"""The detector, step by step and end to end, on images edgecal renders itself (exact ground truth)."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys

import cv2
import numpy as np
import pytest

import edgecal
from edgecal.detection.candidates import prepare_image
from edgecal.detection.completion import grid_may_continue
from edgecal.detection.grouping import CROSS_RATIO_EQUAL_STEPS, cross_ratio, group_grids
from edgecal.detection.params import DetectorParams, params_from_mapping
from edgecal.detection.probe import (
    EDGE_ACROSS_RAY,
    EDGE_MAGNITUDE,
    M_FIRST_SIGN,
    probe_accepts,
    probe_candidates,
    probe_profile_reference,
    probe_profiles,
    ring_prefilter,
    ring_prefilter_radii,
)
from edgecal.errors import ConfigError, InputError
from edgecal.scoring import FoundGrid, corner_rms, score_image
from edgecal.synth.camera import camera_from_fov
from edgecal.synth.panels import panels_from_target
from edgecal.synth.photometric import CLEAN, Photometric
from edgecal.synth.scenes import multi_view, negative_view, planar_view
from edgecal.synth.truth import ground_truth_from_mapping
from edgecal.synth.view import render_view
from edgecal.targets import Board, Target, planar_target


def _score(view, detections):
    truth = ground_truth_from_mapping(view.truth, "rendered")
    return score_image([FoundGrid(d.corners, d.ids, d.grid) for d in detections], truth)


def _corner_image(angle_deg: float, size: int = 41, blur: float = 1.0) -> np.ndarray:
    """An ideal X-corner at the image centre whose border lines run at angle and angle + 90 degrees."""
    import cv2

    ss = 8
    n = size * ss
    c = (size - 1) / 2.0
    ys, xs = (np.mgrid[0:n, 0:n] + 0.5) / ss - 0.5 - c
    a = math.radians(angle_deg)
    u = xs * math.cos(a) + ys * math.sin(a)
    v = -xs * math.sin(a) + ys * math.cos(a)
    hi = np.where((u > 0) == (v > 0), 200.0, 40.0)
    img = cv2.resize(hi, (size, size), interpolation=cv2.INTER_AREA)
    return cv2.GaussianBlur(img, (0, 0), blur).astype(np.uint8)


# --- Eq. (1): the probe kernel against its plain-Python reference -------------------------------------

@pytest.mark.parametrize("mode", [EDGE_MAGNITUDE, EDGE_ACROSS_RAY])
def test_probe_profile_matches_reference(mode: int) -> None:
    view = planar_view(3, size=(320, 240), cols=5, rows=4, square_px=25.0)
    smooth, gx, gy = prepare_image(view.image)
    # incl. rays leaving the image, and the last points inside and outside the kernel's unchecked path
    pts = np.vstack([view.corners()[:3], [[5.0, 5.0], [318.5, 100.2], [11.0, 120.0], [307.0, 120.0]]])
    radii = np.array([10.0, 7.5, 12.0, 10.0, 10.0, 10.0, 10.0])
    kernel = probe_profiles(gx, gy, pts, radii, 48, 1.5, mode)
    for i, (x, y) in enumerate(pts):
        ref = probe_profile_reference(gx, gy, x, y, radii[i], 48, 1.5, mode)
        np.testing.assert_allclose(kernel[i], ref, rtol=1e-4, atol=1e-4)


# --- Eq. (2)-(5): directions, 180-degree test and sign alternation -----------------------------------

@pytest.mark.parametrize("angle", [0.0, 17.0, 33.0, 45.0, 71.0])
def test_probe_finds_the_four_border_directions(angle: float) -> None:
    img = _corner_image(angle)
    smooth, gx, gy = prepare_image(img)
    p = DetectorParams()
    ok, dirs, meas = probe_candidates(gx, gy, smooth, np.array([[20.0, 20.0]]), np.array([10.0]), 64, 1.5,
                                      EDGE_ACROSS_RAY, math.radians(30), 0.7, 12.0, 1.6)
    assert ok[0]
    expected = np.radians(angle + np.arange(4) * 90.0)
    # each true direction has a found one within 1.5 degrees (compared on the circle)
    diff = np.abs((dirs[0][None, :] - expected[:, None] + math.pi) % (2 * math.pi) - math.pi)
    assert diff.min(axis=1).max() < math.radians(1.5), np.degrees(diff.min(axis=1))
    assert meas[0, M_FIRST_SIGN] != 0.0
    assert p.sign_fraction == 0.70


def test_probe_rejects_edges_l_corners_and_flat_areas() -> None:
    import cv2

    img = np.full((41, 41), 40, np.uint8)
    img[:, 20:] = 200  # a straight edge through the centre
    l_corner = np.full((41, 41), 40, np.uint8)
    l_corner[20:, 20:] = 200  # one bright quadrant: an L-corner
    flat = np.full((41, 41), 120, np.uint8)
    t_junction = np.full((41, 41), 40, np.uint8)
    t_junction[20:, :] = 200
    t_junction[20:, 20:] = 120
    for name, im in (("edge", img), ("L", l_corner), ("flat", flat), ("T", t_junction)):
        im = cv2.GaussianBlur(im, (0, 0), 1.0)
        smooth, gx, gy = prepare_image(im)
        ok, _d, _m = probe_candidates(gx, gy, smooth, np.array([[20.0, 20.0]]), np.array([10.0]), 64, 1.5,
                                      EDGE_ACROSS_RAY, math.radians(30), 0.7, 12.0, 1.6)
        assert not ok[0], name


def test_probe_and_prefilter_over_radii_match_one_call_per_radius() -> None:
    """probe_accepts and ring_prefilter_radii (the first pass, one call) accept exactly the points that
    probe_candidates and ring_prefilter accept at one of the radii, called once per radius: on the
    candidates of a rendered board with clutter, some accepted only at the third radius."""
    view = planar_view(8, photometric="normal")
    smooth, gx, gy = prepare_image(view.image)
    rng = np.random.default_rng(4)
    h, w = smooth.shape
    pts = np.concatenate([view.corners(0), rng.uniform([0, 0], [w - 1, h - 1], (300, 2)),
                          view.corners(0) + rng.normal(0.0, 1.5, (len(view.corners(0)), 2))])
    radii = np.array([10.0, 5.0, 20.0])
    args = (32, 1.5, EDGE_ACROSS_RAY, math.radians(30), 0.7, 12.0, 1.6)
    per_radius = [probe_candidates(gx, gy, smooth, pts, np.full(len(pts), r), *args)[0] for r in radii]
    assert (np.any(per_radius[1:], axis=0) & ~per_radius[0]).any()
    np.testing.assert_array_equal(probe_accepts(gx, gy, smooth, pts, radii, *args), np.any(per_radius, axis=0))
    rings = [ring_prefilter(smooth, pts, np.full(len(pts), r), 12.0) for r in radii]
    assert (np.any(rings[1:], axis=0) & ~rings[0]).any()
    np.testing.assert_array_equal(ring_prefilter_radii(smooth, pts, radii, 12.0), np.any(rings, axis=0))


def test_ring_prefilter_without_symmetry_keeps_points_off_a_corner() -> None:
    """Without its symmetry test the ring pre-filter (what completion tests its predictions with) keeps
    points a third of the ring's radius off an X-corner, which the symmetric test drops; neither keeps
    points in a board's margin or on a square's edge."""
    view = planar_view(3, size=(640, 480), square_px=(35.0, 45.0))
    smooth = prepare_image(view.image, 0.8)[0]
    corners = view.corners()
    spacing = np.median(np.linalg.norm(np.diff(corners[:9], axis=0), axis=1))
    r = 0.6 * spacing
    rng = np.random.default_rng(2)
    angle = rng.uniform(0, 2 * np.pi, len(corners))
    off = corners + (r / 3) * np.stack([np.cos(angle), np.sin(angle)], axis=1)
    radii = np.full(len(corners), r)
    loose = ring_prefilter(smooth, off, radii, 12.0, False)
    strict = ring_prefilter(smooth, off, radii, 12.0)
    assert loose.mean() > 0.9 and strict.mean() < loose.mean() - 0.3, (loose.mean(), strict.mean())
    ids = view.ids()
    first, second = corners[ids[:, 1] == 0], corners[ids[:, 1] == 1]
    margin = 2 * first - second  # one line beyond the board's first row: its margin
    edge = 0.5 * (first[:-1] + first[1:])  # half way between corners: on a square's edge
    for pts in (margin, edge):
        assert not ring_prefilter(smooth, pts, np.full(len(pts), r), 12.0, False).any()


# --- Eq. (6)-(8): grouping and the cross-ratio ---------------------------------------------------------

def test_cross_ratio_is_projective_invariant() -> None:
    assert cross_ratio(0, 1, 2, 3) == pytest.approx(CROSS_RATIO_EQUAL_STEPS)
    rng = np.random.default_rng(1)
    for _ in range(20):
        a, b, c, d = rng.normal(size=4)
        if abs(c * 0 + d) < 0.1 or abs(c * 3 + d) < 0.1 or (c * 0 + d) * (c * 3 + d) < 0:
            continue
        x = [(a * t + b) / (c * t + d) for t in (0.0, 1.0, 2.0, 3.0)]
        assert cross_ratio(*x) == pytest.approx(CROSS_RATIO_EQUAL_STEPS, rel=1e-9)
    assert abs(cross_ratio(0, 1, 3, 4) - CROSS_RATIO_EQUAL_STEPS) / CROSS_RATIO_EQUAL_STEPS > 0.05


def _grid_points(cols: int, rows: int, step: float = 20.0, angle: float = 0.3) -> tuple[np.ndarray, np.ndarray]:
    ca, sa = math.cos(angle), math.sin(angle)
    pts, dirs = [], []
    for r in range(rows):
        for c in range(cols):
            pts.append((50 + step * (c * ca - r * sa), 50 + step * (c * sa + r * ca)))
            dirs.append(np.sort(np.mod(angle + np.arange(4) * math.pi / 2, 2 * math.pi)))
    return np.array(pts), np.array(dirs)


def test_grouping_labels_a_whole_grid_and_drops_an_intruder_on_a_line() -> None:
    pts, dirs = _grid_points(6, 4)
    # A false point on row 0 between columns 2 and 3 (on the line, wrong spacing): Eq. (8) must reject it.
    intruder = pts[2] + 0.45 * (pts[3] - pts[2])
    pts2 = np.vstack([pts, intruder])
    dirs2 = np.vstack([dirs, dirs[0]])
    spacing = np.full(len(pts2), 20.0)
    spacing[-1] = 9.0
    score = np.ones(len(pts2))
    score[-1] = 2.0  # the intruder seeds the walk: the worst case
    labels, _ = group_grids(pts2, dirs2, spacing, score, 10.0, 40.0, 0.05)
    main = labels[:-1, 0]
    assert len(set(main)) == 1 and main[0] >= 0
    uv = labels[:-1, 1:] - labels[:-1, 1:].min(axis=0)
    assert sorted(map(tuple, uv)) == sorted((c, r) for r in range(4) for c in range(6)) or \
        sorted(map(tuple, uv)) == sorted((r, c) for r in range(4) for c in range(6))
    assert labels[-1, 0] != main[0]


# --- End to end on rendered views ----------------------------------------------------------------------

@pytest.mark.parametrize("square_px,cols,rows,size,seed", [
    (8.0, 9, 6, (640, 480), 1),
    (20.0, 9, 6, (640, 480), 2),
    (60.0, 9, 6, (1280, 800), 3),
    (150.0, 4, 3, (1280, 800), 4),
])
def test_detects_boards_from_8_to_150_px_squares(square_px: float, cols: int, rows: int, size, seed: int) -> None:
    view = planar_view(seed, size=size, cols=cols, rows=rows, square_px=square_px)
    dets = edgecal.detect(view.image, planar_target(cols, rows))
    score = _score(view, dets)
    assert score.n_found == 1 and score.false_boards == 0
    # cols + rows is odd: the colour fixes the numbering, so ids equal the truth exactly.
    if (cols + rows) % 2 == 1:
        assert score.matches[0].symmetry == "identity"
    assert corner_rms(score.found_errors()) < 0.15


def test_corner_rms_on_clean_renders_is_below_005_px() -> None:
    errors = []
    for seed in range(3):
        view = planar_view(seed, size=(640, 480), square_px=(30.0, 45.0), photometric=CLEAN,
                           background="uniform", tilt_max_deg=35.0)
        dets = edgecal.detect(view.image, planar_target(9, 6))
        score = _score(view, dets)
        assert score.n_found == 1
        errors.append(score.found_errors())
    assert corner_rms(np.concatenate(errors)) <= 0.05


def test_no_board_on_negatives_is_a_normal_empty_result() -> None:
    for seed in range(3):
        view = negative_view(seed)
        assert edgecal.detect(view.image, planar_target(9, 6)) == []
        assert edgecal.detect(view.image, planar_target(3, 3)) == []


def test_several_boards_of_different_sizes_in_one_image() -> None:
    view = multi_view(11, size=(1280, 800), n_boards=3, square_px=(18.0, 30.0))
    boards = [Board(b["name"], b["cols"], b["rows"], b["square_mm"]) for b in view.truth["target"]["boards"]]
    dets = edgecal.detect(view.image, Target("multi", tuple(boards)))
    score = _score(view, dets)
    assert score.n_found == len(boards) and score.false_boards == 0
    assert {d.board for d in dets} == {b.name for b in boards}


def test_a_board_size_mistake_is_explained() -> None:
    view = planar_view(5, size=(640, 480), square_px=30.0)
    debug = edgecal.detect_debug(view.image, planar_target(10, 7))
    assert debug.detections == []
    assert any("found a 9x6 grid; the target says 10x7" in n for n in debug.notes), debug.notes


def test_colour_input_and_debug_output() -> None:
    import cv2

    view = planar_view(6, size=(640, 480), square_px=30.0)
    bgr = cv2.cvtColor(view.image, cv2.COLOR_GRAY2BGR)
    debug = edgecal.detect_debug(bgr, planar_target(9, 6))
    assert len(debug.detections) == 1
    det = debug.detections[0]
    assert det.corners.shape == (54, 2) and det.ids.shape == (54, 2) and det.quality.shape == (54,)
    assert np.all((det.quality >= 0) & (det.quality <= 1))
    assert len(debug.accepted) >= 54 and debug.directions.shape == (len(debug.accepted), 4)


# --- Bad input -----------------------------------------------------------------------------------------

def test_bad_arrays_are_input_errors() -> None:
    target = planar_target(9, 6)
    with pytest.raises(InputError, match="dtype float64"):
        edgecal.detect(np.zeros((10, 10)), target)
    with pytest.raises(InputError, match="empty"):
        edgecal.detect(np.zeros((0, 0), np.uint8), target)
    with pytest.raises(InputError, match="shape"):
        edgecal.detect(np.zeros((4, 4, 2), np.uint8), target)
    assert edgecal.detect(np.zeros((3, 3), np.uint8), target) == []


def test_params_file_is_validated_by_field() -> None:
    with pytest.raises(ConfigError, match="sign_fraction"):
        params_from_mapping({"sign_fraction": 1.5}, "x.yaml")
    with pytest.raises(ConfigError, match="probe_radius_pxx"):
        params_from_mapping({"probe_radius_pxx": 3}, "x.yaml")
    assert params_from_mapping({"probe_radius_px": 12}, "x.yaml").probe_radius_px == 12.0


def _cli(*args: str, cwd=None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "edgecal", *args], capture_output=True, text=True, cwd=cwd)


def test_cli_missing_package_is_one_line(tmp_path) -> None:
    """An environment without one of edgecal's packages (here matplotlib, which only calibrate's report
    draws with, made unimportable by a stand-in on PYTHONPATH) gives every command one line naming the
    package and what to do, exit 2, not a traceback from building the parser."""
    stand_in = tmp_path / "site" / "matplotlib"
    stand_in.mkdir(parents=True)
    (stand_in / "__init__.py").write_text("raise ModuleNotFoundError(\"No module named 'matplotlib'\", "
                                          "name='matplotlib')\n")
    image = tmp_path / "notes.png"
    image.write_text("not an image\n")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path / "site"), *sys.path])}
    res = subprocess.run([sys.executable, "-m", "edgecal", "detect", "--board", "9x6", str(image)],
                         capture_output=True, text=True, env=env)
    assert res.returncode == 2 and "Traceback" not in res.stderr, res.stderr
    assert len(res.stderr.strip().splitlines()) == 1 and "'matplotlib'" in res.stderr


def test_cli_detect_prints_json_lines_and_draws(tmp_path) -> None:
    import cv2

    view = planar_view(7, size=(640, 480), square_px=30.0)
    img = tmp_path / "board.png"
    cv2.imwrite(str(img), view.image)
    neg = tmp_path / "empty.png"
    cv2.imwrite(str(neg), negative_view(1).image)
    res = _cli("detect", "--board", "9x6", str(img), str(neg), "--draw", str(tmp_path / "draw"))
    assert res.returncode == 0, res.stderr
    lines = [json.loads(x) for x in res.stdout.splitlines()]
    assert [len(x["boards"]) for x in lines] == [1, 0]
    assert lines[0]["size"] == [640, 480] and len(lines[0]["boards"][0]["corners"]) == 54
    assert (tmp_path / "draw" / "board_detect.png").is_file()
    # a second run refuses to overwrite the overlays
    again = _cli("detect", "--board", "9x6", str(img), "--draw", str(tmp_path / "draw"))
    assert again.returncode == 2 and "already exists" in again.stderr and "Traceback" not in again.stderr


@pytest.mark.parametrize("args,needle", [
    (["detect", "--board", "9x6", "missing.png"], "missing.png: image file not found"),
    (["detect", "--board", "nine", "x.png"], "--board 'nine'"),
    (["detect", "--target", "nope.yaml", "x.png"], "nope.yaml: config file not found"),
])
def test_cli_bad_input_is_one_line_and_exit_2(tmp_path, args, needle) -> None:
    res = _cli(*args, cwd=tmp_path)
    assert res.returncode == 2
    assert needle in res.stderr and "Traceback" not in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1


@pytest.mark.parametrize("content", [
    b"\x89PNG\r\n\x1a\n garbage after a PNG signature",   # OpenCV's PNG reader logs its own errors
    b"P5\n640 480\n255\ntruncated",                          # ... and so does its PGM reader
])
def test_cli_broken_image_is_one_line_without_opencv_log(tmp_path, content) -> None:
    bad = tmp_path / "broken.png"
    bad.write_bytes(content)
    res = _cli("detect", "--board", "9x6", str(bad))
    assert res.returncode == 2 and "broken.png: not a readable image" in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1, res.stderr


def test_cli_unreadable_image_and_bad_target_field(tmp_path) -> None:
    bad = tmp_path / "bad.png"
    bad.write_bytes(b"not an image")
    res = _cli("detect", "--board", "9x6", str(bad))
    assert res.returncode == 2 and "not a readable image" in res.stderr
    target = tmp_path / "t.yaml"
    target.write_text("name: t\nboards:\n  - name: a\n    inner_corners: [9, 6]\n    square_mm: -3\n")
    res = _cli("detect", "--target", str(target), str(bad))
    assert res.returncode == 2 and "boards[0].square_mm" in res.stderr and "Traceback" not in res.stderr


def test_cli_draw_folder_that_cannot_be_made_is_one_line(tmp_path) -> None:
    """/proc takes no new folders (for root too, whom the permission check lets through): one line, exit 2."""
    image = tmp_path / "grey.png"
    image.write_bytes(cv2.imencode(".png", np.zeros((40, 50), np.uint8))[1].tobytes())
    res = _cli("detect", "--board", "9x6", "--draw", "/proc/edgecal-no-such/overlays", str(image))
    assert res.returncode == 2 and "Traceback" not in res.stderr, res.stderr
    assert len(res.stderr.strip().splitlines()) == 1 and "/proc/edgecal-no-such" in res.stderr


# --- A board inside a larger grid; several boards of one size ------------------------------------------

@pytest.mark.parametrize("cols,rows", [(8, 6), (6, 6), (9, 5)])
def test_a_board_inside_a_larger_grid_is_not_the_asked_board(cols: int, rows: int) -> None:
    """A 9x6 board asked as a smaller one: no detection (a sub-grid would start at an arbitrary square),
    and the note says what was seen. Seed 11 is a view where grouping alone gives an exact 8x6 sub-grid."""
    for seed in (11, 3, 7):
        view = planar_view(seed, size=(640, 480), square_px=(15.0, 40.0))
        debug = edgecal.detect_debug(view.image, planar_target(cols, rows))
        assert debug.detections == [], (seed, [d.grid for d in debug.detections])
        assert any(f"found a 9x6 grid; the target says {cols}x{rows}" in n for n in debug.notes), debug.notes


@pytest.mark.parametrize("tilt_x_deg, tilt_y_deg", [(-30.0, 20.0), (20.0, 40.0), (35.0, -30.0)])
def test_a_narrow_margin_before_a_dark_background_does_not_grow_the_board(tilt_x_deg: float,
                                                                          tilt_y_deg: float) -> None:
    """A 5x4 board whose white margin is 0.3 of a square, then a dark background: the probe confirms every
    other point of the margin's line (those next to a black square). Taken as a new row they made a 5x5
    grid that matched no board (the robot sequences' 5x4 board was missed in 114 of 120 images)."""
    target, view = _narrow_margin_view(tilt_x_deg, tilt_y_deg)
    debug = edgecal.detect_debug(view.image, target)
    assert len(debug.detections) == 1, debug.notes
    (det,) = debug.detections
    truth = {tuple(i): c for i, c in zip(view.ids(), view.corners())}
    err = [np.linalg.norm(c - truth[tuple(i)]) for i, c in zip(det.ids.tolist(), det.corners)]
    assert len(err) == 20 and max(err) < 0.1


def _narrow_margin_view(tilt_x_deg: float, tilt_y_deg: float):
    """A 5x4 board whose white margin is 0.3 of a square, then a dark background (see below)."""
    target = planar_target(5, 4, 30.0)
    board = target.boards[0]
    panels = panels_from_target(target, margin_mm=0.3 * board.square_mm)
    R = cv2.Rodrigues(np.array([math.radians(tilt_x_deg), math.radians(tilt_y_deg), 0.3]))[0]
    t = -R @ board.centre_mm + np.array([0.0, 0.0, 700.0])
    return target, render_view(camera_from_fov((640, 480), 60.0), panels, R, t, background=0.3,
                               photometric=Photometric(blur_sigma=0.7, noise_sigma=1.0), rng=1)


def test_grid_may_continue_tells_a_sub_grid_from_a_whole_board() -> None:
    """completion.grid_may_continue on true corners: a whole board has its margin beyond it (also a narrow
    margin before a dark background, whose rings alternate), the 8x6 and 9x5 parts of a 9x6 board have a
    line of corners beyond them, on the full- and on the half-resolution image."""
    view = planar_view(3, size=(640, 480), square_px=(35.0, 45.0))
    _target, narrow = _narrow_margin_view(-30.0, 20.0)
    p = DetectorParams()
    for scale in (1.0, 0.5):
        grids = []
        for v in (view, narrow):
            image = v.image if scale == 1.0 else cv2.pyrDown(v.image)
            smooth = prepare_image(image, 0.8)[0]
            grid = {tuple(i): scale * c for i, c in zip(v.ids().tolist(), v.corners())}
            grids.append((grid, smooth))
        (whole, smooth), (narrow_grid, narrow_smooth) = grids
        assert not grid_may_continue(whole, smooth, p), scale
        if scale == 1.0:  # (its 10 px squares at half resolution: the detector does not ask there)
            assert not grid_may_continue(narrow_grid, narrow_smooth, p)
        part = {k: c for k, c in whole.items() if k[0] < 8}
        assert grid_may_continue(part, smooth, p), scale
        part = {k: c for k, c in whole.items() if k[1] > 0}
        assert grid_may_continue(part, smooth, p), scale


@pytest.mark.parametrize("cols,rows", [(8, 6), (9, 5)])
def test_a_board_of_large_squares_inside_a_larger_grid_is_not_the_asked_board(cols: int, rows: int) -> None:
    """As above with squares large enough that the full-resolution window leaves out the lines beyond a
    board where half resolution sees none (detector._refine_at_full_resolution)."""
    for seed in (11, 3, 7, 12):
        view = planar_view(seed, size=(1280, 800), square_px=(50.0, 70.0))
        debug = edgecal.detect_debug(view.image, planar_target(cols, rows))
        assert debug.detections == [], (seed, [d.grid for d in debug.detections])
        assert any(f"found a 9x6 grid; the target says {cols}x{rows}" in n for n in debug.notes), debug.notes


def test_three_boards_of_one_size_are_all_returned_and_numbered() -> None:
    view = multi_view(2, size=(1280, 800), grids=((7, 5),) * 3, square_px=(18.0, 30.0))
    assert len(view.truth["target"]["boards"]) == 3
    debug = edgecal.detect_debug(view.image, planar_target(7, 5))
    score = _score(view, debug.detections)
    assert len(debug.detections) == 3 and score.false_boards == 0
    # every truth board found (names aside: the three are copies of the one asked board)
    truth = ground_truth_from_mapping(view.truth, "rendered")
    grid_score = score_image([FoundGrid(d.corners, d.ids, d.grid) for d in debug.detections], truth, "grid")
    assert grid_score.n_found == 3
    assert [d.copy for d in debug.detections] == [0, 1, 2]
    # numbered by position: centroids top to bottom
    ys = [d.corners[:, 1].mean() for d in debug.detections]
    assert ys == sorted(ys)
    # a note never says a grid of the asked size does not match the target
    assert not any("found a 7x5 grid; the target says 7x5" in n for n in debug.notes), debug.notes


def test_cli_detect_json_carries_the_size_note(tmp_path) -> None:
    import cv2

    view = planar_view(11, size=(640, 480), square_px=(15.0, 40.0))
    img = tmp_path / "board.png"
    cv2.imwrite(str(img), view.image)
    res = _cli("detect", "--board", "8x6", str(img))
    assert res.returncode == 0, res.stderr
    record = json.loads(res.stdout)
    assert record["boards"] == []
    assert any("found a 9x6 grid; the target says 8x6" in n for n in record["notes"])
    assert "found a 9x6 grid; the target says 8x6" in res.stderr


def _bigger_board_views(folder, n: int = 6) -> list[str]:
    """``n`` rendered 640x480 views of a 9x6 board written to ``folder``; returns the paths."""
    import cv2

    folder.mkdir()
    paths = []
    for seed in range(n):
        view = planar_view(20 + seed, size=(640, 480), square_px=(20.0, 35.0), tilt_max_deg=30.0)
        paths.append(str(folder / f"{seed:02d}.png"))
        cv2.imwrite(paths[-1], view.image)
    return paths


def test_capture_and_calibrate_refuse_a_sub_grid_alike(tmp_path, capsys, caplog) -> None:
    """capture --board 8x6 on 9x6 frames shows no board and the note; calibrate --board 8x6 fails saying why
    instead of calibrating on sub-grids (exit non-zero, no rig written)."""
    from edgecal.cli import main

    paths = _bigger_board_views(tmp_path / "imgs")
    assert main(["capture", f"replay:{tmp_path / 'imgs'}?pace=fast", "--frames", "2", "--board", "8x6",
                 "--json"]) == 0
    rows = [json.loads(line) for line in capsys.readouterr().out.splitlines() if line.startswith("{")]
    assert len(rows) == 2 and all(r["boards"] == [] for r in rows)
    assert all(any("found a 9x6 grid; the target says 8x6" in n for n in r["notes"]) for r in rows)
    out = tmp_path / "rig.yaml"
    rc = main(["calibrate", "--board", "8x6", "--square-mm", "25", "--left", *paths, "--out", str(out)])
    err = capsys.readouterr().err
    assert rc != 0 and not out.exists() and "Traceback" not in err
    assert "found a 9x6 grid; the target says 8x6" in caplog.text
    assert main(["calibrate", "--board", "9x6", "--square-mm", "25", "--left", *paths, "--out", str(out)]) == 0


# --- Candidate thinning: ChESS filter and de-duplication -------------------------------------------------

@pytest.mark.parametrize("layout", ["dense", "frame", "line", "clusters"])
def test_dedupe_in_order_matches_a_plain_greedy_pass(layout: str) -> None:
    """Whatever the hash grid's cells (radius-sized on dense points, far larger on a frame's sparse ones or
    along a line), the kept points are the greedy pass's."""
    from edgecal.detection.candidates import dedupe_in_order

    rng = np.random.default_rng(4)
    if layout == "dense":
        pts = rng.uniform(0, 40, size=(400, 2))
    elif layout == "frame":
        pts = rng.uniform(0, 1, size=(300, 2)) * [1280, 800]
        pts[150:] = pts[:150] + rng.uniform(-1.2, 1.2, size=(150, 2))  # near-duplicates across the frame
    elif layout == "line":
        pts = np.c_[np.round(rng.uniform(0, 900, 300) * 2) / 2, np.full(300, 7.0)]
    else:
        pts = np.concatenate([rng.normal(c, 1.0, size=(60, 2)) for c in ((10, 10), (600, 400), (1200, 20))])
    kept: list[int] = []
    for i, p in enumerate(pts):
        if all(np.hypot(*(p - pts[j])) > 1.5 for j in kept):
            kept.append(i)
    assert dedupe_in_order(pts, 1.5).tolist() == kept


def test_chess_filter_keeps_board_corners_and_drops_noise() -> None:
    from edgecal.detection.candidates import (
        chess_filter,
        chess_ring,
        chess_thresholds,
        estimate_noise_sigma,
        smooth_image,
        smoothing_sigma,
    )
    from edgecal.detection.detector import CHESS_RADII_PX
    from edgecal.synth.scenes import hard_view

    rings = np.array([np.stack(chess_ring(r)) for r in CHESS_RADII_PX], dtype=np.int64)
    kept = total = 0
    for seed in range(3):
        view = hard_view(seed, size=(640, 480))
        noise = estimate_noise_sigma(view.image)
        sigma = smoothing_sigma(noise)
        smooth = smooth_image(view.image, sigma)
        thr = chess_thresholds(CHESS_RADII_PX, noise, sigma, 0.9999, 6.0)
        corners = np.rint(view.corners())
        kept += int(chess_filter(smooth, corners, rings, thr).sum())
        total += len(corners)
    assert kept >= 0.97 * total, (kept, total)
    rng = np.random.default_rng(1)
    noise_img = np.clip(128 + 8 * rng.standard_normal((240, 320)), 0, 255).astype(np.uint8)
    sigma = smoothing_sigma(estimate_noise_sigma(noise_img))
    smooth = smooth_image(noise_img, sigma)
    thr = chess_thresholds(CHESS_RADII_PX, estimate_noise_sigma(noise_img), sigma, 0.9999, 6.0)
    pts = np.stack(np.meshgrid(np.arange(10, 310, 3), np.arange(10, 230, 3)), axis=-1).reshape(-1, 2).astype(float)
    assert chess_filter(smooth, pts, rings, thr).mean() < 0.01


def test_half_resolution_noise_is_the_float_pyramid_estimate() -> None:
    """half_resolution_noise_sigma's one strided pass over the full-resolution image gives, at every sample,
    the Laplacian-like mask of cv2.pyrDown's float image, and the noise of white noise (where the uint8
    pyramid's estimate / 0.273 says about half), also when JPEG has removed the pixel-level noise."""
    from edgecal.detection.candidates import (
        HALF_NOISE_GAIN,
        _half_noise_responses,
        estimate_noise_sigma,
        half_resolution_noise_sigma,
    )
    from edgecal.synth.photometric import Photometric, apply_photometric

    rng = np.random.default_rng(3)
    grey = np.clip(128 + 20 * rng.standard_normal((83, 101)), 0, 255).astype(np.uint8)
    half = cv2.pyrDown(grey.astype(np.float32)).astype(np.float64)
    mask = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float64)
    stride = 6  # even: every sample's centre (x + 4, y + 4) is a half-resolution pixel
    got = _half_noise_responses(grey, stride) / 256.0
    want = [abs((half[cy - 1:cy + 2, cx - 1:cx + 2] * mask).sum())
            for y in range(0, 83 - 8, stride) for x in range(0, 101 - 8, stride)
            for cy, cx in [((y + 4) // 2, (x + 4) // 2)]]
    assert got == pytest.approx(want, abs=1e-3)
    # the 1-D kernel on full-resolution pixels: pyrDown's binomial at the mask's three half-resolution taps
    taps = np.convolve([1.0, 0.0, -2.0, 0.0, 1.0], np.array([1.0, 4.0, 6.0, 4.0, 1.0]) / 16.0)
    assert HALF_NOISE_GAIN == pytest.approx((taps ** 2).sum())

    radiance = np.full((480, 640), 0.5, np.float32)
    white = apply_photometric(radiance, Photometric(noise_sigma=5.0), rng)
    assert half_resolution_noise_sigma(white) == pytest.approx(5.0, rel=0.1)
    assert estimate_noise_sigma(white) == pytest.approx(5.0, rel=0.1)
    assert estimate_noise_sigma(cv2.pyrDown(white)) / 0.273 < 3.0  # what the detector took before
    jpeg = apply_photometric(radiance, Photometric(noise_sigma=5.0, jpeg_quality=70), rng)
    assert estimate_noise_sigma(jpeg) < 2.0                  # pixel-level noise removed
    assert half_resolution_noise_sigma(jpeg) > 3.5           # the noise at a corner's scale stays


def test_full_search_thresholds_use_the_image_noise() -> None:
    """A noisy frame without a board is searched at full resolution with thresholds for its noise (it had
    about half of it, and ~6x the candidates on bench/live.py's hard frames) and the smoothing it was tuned
    with (noise_half / 0.273)."""
    from edgecal.detection.candidates import estimate_noise_sigma, smoothing_sigma
    from edgecal.detection.detector import DEFAULT_PARAMS, SMOOTHING_NOISE_PER_HALF_NOISE, _search
    from edgecal.synth.photometric import Photometric, apply_photometric

    rng = np.random.default_rng(4)
    radiance = np.clip(0.5 + 0.2 * cv2.GaussianBlur(rng.standard_normal((480, 640)).astype(np.float32), (0, 0), 6),
                       0.05, 0.95)
    grey = apply_photometric(radiance, Photometric(noise_sigma=6.0), rng)
    debug, level = _search(grey, planar_target(9, 6), DEFAULT_PARAMS)
    assert not debug.detections
    assert level.noise_sigma == pytest.approx(6.0, rel=0.15)
    half_noise = estimate_noise_sigma(cv2.pyrDown(grey))
    assert level.smoothing_sigma == smoothing_sigma(half_noise * SMOOTHING_NOISE_PER_HALF_NOISE)


def test_ids_do_not_depend_on_the_grid_labels() -> None:
    """assign_ids gives a board's ids (handedness and colour decide) whichever of the lattice's eight
    symmetries its grid labels came in; grid_is_regular passes the board and fails it with two corners
    swapped (a zig-zag)."""
    from edgecal.detection.candidates import smooth_image
    from edgecal.detection.ordering import _SYMMETRIES, assign_ids, grid_is_regular

    view = planar_view(11, size=(640, 480))
    board = planar_target(9, 6).boards[0]
    det = edgecal.detect(view.image, planar_target(9, 6))[0]
    smooth = smooth_image(view.image)
    for m in _SYMMETRIES:
        uv = det.ids @ m.T + 7  # any labels: rotated or mirrored, offset
        np.testing.assert_array_equal(assign_ids(uv, det.corners, smooth, board), det.ids)
    assert grid_is_regular(det.corners, det.ids, 9, 6, 0.1)
    swapped = det.corners.copy()
    swapped[[10, 11]] = swapped[[11, 10]]
    assert not grid_is_regular(swapped, det.ids, 9, 6, 0.1)


def test_hole_prediction_matches_per_hole_homographies() -> None:
    """The batched local homographies of grid completion agree with cv2.findHomography hole by hole."""
    import cv2

    from edgecal.detection.completion import predict_holes

    rng = np.random.default_rng(2)
    h_true = np.array([[30.0, 4.0, 100.0], [-3.0, 28.0, 80.0], [0.002, -0.001, 1.0]])
    grid = {}
    for u in range(9):
        for v in range(6):
            q = h_true @ np.array([u, v, 1.0])
            # a gentle radial bend, so that local and global homographies differ
            xy = q[:2] / q[2]
            xy = xy + 1e-6 * np.sum((xy - 250.0) ** 2) * (xy - 250.0)
            grid[(u, v)] = xy + rng.normal(0, 0.02, 2)
    holes = [(0, 0), (4, 3), (8, 5), (5, 0)]
    for hole in holes:
        del grid[hole]
    del grid[(1, 0)]  # (0, 0) then has too few neighbours in its ring and needs the 5x5 patch
    del grid[(1, 1)]
    preds, keys, spacing = predict_holes(grid, holes)
    assert keys == holes
    for (u, v), p, sp in zip(keys, preds, spacing):
        for reach in (1, 2):
            near = [(a, b) for (a, b) in grid if abs(a - u) <= reach and abs(b - v) <= reach]
            if len(near) >= 4 and len({a for a, _ in near}) > 1 and len({b for _, b in near}) > 1:
                break
        h, _ = cv2.findHomography(np.array(near, float), np.array([grid[k] for k in near]), 0)
        q = h @ np.array([u, v, 1.0])
        assert np.linalg.norm(p - q[:2] / q[2]) < 0.05
        assert 20.0 < sp < 40.0


def test_completion_fills_fisheye_rim_holes_along_the_grid_lines() -> None:
    """Holes on the outer line of a board seen near the rim of a 190-degree fisheye: the local homographies
    there miss them by a quarter of a square (~9.5 px: the squares shrink too fast), from where their
    refinement does not reach the corner, so completion stalled with two holes left; the grid lines through
    them, bent as they are, still lead to the corners."""
    from edgecal.detection.completion import complete_grid, predict_holes
    from edgecal.detection.detector import DEFAULT_PARAMS
    from edgecal.detection.levels import Level

    target = planar_target(6, 7, 30.0)
    board = target.boards[0]
    camera = camera_from_fov((752, 480), 190.0, (0.0, 0.0, 0.0, 0.0), (0.0, 0.0), 1.0, "fisheye")
    R = cv2.Rodrigues(np.array([0.0, 0.0, 0.05]))[0]
    view = render_view(camera, panels_from_target(target), R, -R @ board.centre_mm + np.array([0.0, 0.0, 80.0]),
                       background=0.2, photometric=Photometric(blur_sigma=0.8, noise_sigma=1.0), rng=0)
    truth = {(int(c), int(r)): p for (c, r), p in zip(view.ids(0), view.corners(0))}
    holes = [(2, 6), (3, 6), (2, 5)]
    grid = {k: v for k, v in truth.items() if k not in holes}
    preds, keys, spacing = predict_holes(grid, holes[:2])
    assert min(np.linalg.norm(p - truth[k]) / s for p, k, s in zip(preds, keys, spacing)) > 0.24
    done = complete_grid(grid, Level(view.image), 40, DEFAULT_PARAMS)
    assert set(done) == set(truth)
    assert max(np.linalg.norm(done[k] - truth[k]) for k in holes) < 0.3


@pytest.mark.parametrize("seed", [1, 3])
def test_completion_confirms_a_noisy_last_line_from_a_local_homography(seed: int) -> None:
    """A board of 11 px squares, low contrast and noise, whose grid lacks its last column and whose corners are
    0.6 px off (noisy small squares): extrapolated along its own row from three corners (x 3, -3, 1) each new
    corner is predicted 1.3-5.3 px off, beyond the refinement's and the ring pre-filter's reach, so the line
    was never confirmed; the homography of the corners within two labels averages their noise."""
    from edgecal.detection.completion import complete_grid, dense_labels, line_predictions, predict_holes
    from edgecal.detection.detector import DEFAULT_PARAMS
    from edgecal.detection.levels import Level

    target = planar_target(9, 6, 20.0)
    board = target.boards[0]
    R = cv2.Rodrigues(np.array([0.3, 0.2, 0.1]))[0]
    view = render_view(camera_from_fov((640, 480), 60.0), panels_from_target(target), R,
                       -R @ board.centre_mm + np.array([0.0, 0.0, 1000.0]), background=0.3,
                       photometric=Photometric(blur_sigma=1.0, noise_sigma=4.0, black_level=80, white_level=160),
                       rng=seed)
    truth = {(int(c), int(r)): p for (c, r), p in zip(view.ids(0), view.corners(0))}
    rng = np.random.default_rng(seed)
    grid = {k: v + rng.normal(0.0, 0.6, 2) for k, v in truth.items() if k[0] < 8}
    line = [(8, r) for r in range(6)]
    # along each row from columns 7, 6, 5 (outward step (1, 0), the last of line_predictions' four)
    along_row = line_predictions(*dense_labels(grid), np.array(line))[0][:, 3]
    misses = np.linalg.norm(along_row - np.array([truth[k] for k in line]), axis=1)
    assert (misses > 2.0).sum() >= 4
    preds, keys, _spacing = predict_holes(grid, line)
    assert keys == line
    assert np.median([np.linalg.norm(p - truth[k]) for p, k in zip(preds, keys)]) < 0.5 * np.median(misses)
    done = complete_grid(grid, Level(view.image), 40, DEFAULT_PARAMS)
    assert set(done) == set(truth)
    assert max(np.linalg.norm(done[k] - truth[k]) for k in line) < 0.35


def _bloomed(view) -> np.ndarray:
    """An overexposed copy of a render whose white squares bleed a pixel into the black ones (as on a real
    sensor), so that neighbouring black squares no longer touch at their corners."""
    import cv2

    img = view.image.astype(np.float32)
    img = np.clip((img - img.min()) / (np.percentile(img, 60) - img.min()) * 255 * 1.3, 0, 255)
    return cv2.dilate(img, np.ones((3, 3), np.uint8)).astype(np.uint8)


def test_an_overexposed_board_with_bloomed_corners_is_found() -> None:
    for seed in (1, 2, 5):  # views where the black squares come apart at the corners
        view = planar_view(seed, size=(640, 480), square_px=(25.0, 40.0), photometric="clean",
                           background="uniform")
        debug = edgecal.detect_debug(_bloomed(view), planar_target(9, 6))
        truth = ground_truth_from_mapping(view.truth, "bloomed")
        score = score_image([FoundGrid(d.corners, d.ids, d.grid) for d in debug.detections], truth, "grid")
        assert score.n_found == 1 and score.false_boards == 0, seed
        assert corner_rms(score.found_errors()) < 0.5
        assert any("overexposed" in n for n in debug.notes)


@pytest.mark.parametrize("photometric,gain,rms_max", [("clean", 0.6, 0.008), ("normal", 0.9, 0.024)])
def test_saddle_fit_beats_cornersubpix_alone(photometric: str, gain: float, rms_max: float) -> None:
    """The default final refiner (cornerSubPix, then the saddle fit) against cornerSubPix alone, same boards;
    and its RMS itself (the earlier 5x5 fit gave 0.0096 px on these clean and 0.025 px on these normal
    renders, the 11x11 fit 0.0069 and 0.022)."""
    errors: dict[str, list[np.ndarray]] = {"saddle": [], "cornersubpix": []}
    for seed in range(4):
        view = planar_view(seed, size=(640, 480), square_px=(20.0, 45.0), photometric=photometric,
                           background="uniform")
        for refiner in errors:
            dets = edgecal.detect(view.image, planar_target(9, 6), DetectorParams(subpixel_refiner=refiner))
            score = _score(view, dets)
            assert score.n_found == 1
            errors[refiner].append(score.found_errors())
    rms = {k: corner_rms(np.concatenate(v)) for k, v in errors.items()}
    assert rms["saddle"] < gain * rms["cornersubpix"], rms
    assert rms["saddle"] <= rms_max, rms


def test_refiner_choice_is_validated() -> None:
    with pytest.raises(ConfigError, match="subpixel_refiner"):
        params_from_mapping({"subpixel_refiner": "magic"}, "x.yaml")
    assert params_from_mapping({"subpixel_refiner": "cornersubpix"}, "x.yaml").subpixel_refiner == "cornersubpix"
