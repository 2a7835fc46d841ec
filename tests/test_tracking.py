"""Tracking: pose extrapolation, corner prediction, verification of predicted corners, the tracker's state.

Everything runs on a rendered robot sequence (edgecal.synth) whose true poses and corners are exact.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from edgecal.detection.detector import detect
from edgecal.detection.subpixel import nearest_spacing
from edgecal.detection.tracking import (
    MAX_MOTION_RESIDUAL_PX,
    near_window,
    search_near,
    track_boards,
    verify_boards,
)
from edgecal.detection.types import CornerPrediction
from edgecal.drivers.base import Frame, StereoFrame
from edgecal.pose import Pose, estimate_pose
from edgecal.pose.predict import (
    MAX_EXTRAPOLATION,
    MIN_FACING_COS,
    camera_from_rig,
    extrapolate_pose,
    facing_cos,
    predict_corners,
)
from edgecal.stream import LiveLoop, load_live_config
from edgecal.stream.frame_pipeline import FramePipeline
from edgecal.stream.tracker import BoardTracker, TrackingSettings, confirmed_fraction

from .live_fixtures import free_endpoint, render_robot, write_config

N_FRAMES = 3


@pytest.fixture(scope="module")
def robot(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict, object]:
    """A rendered robot sequence, its truth and its live config (the renderer's true rig)."""
    folder = tmp_path_factory.mktemp("robot")
    truth = render_robot(folder, N_FRAMES)
    cfg = load_live_config(write_config(folder / "live.yaml", folder, free_endpoint()))
    return folder, truth, cfg


def truth_corners(frame: dict, side: str) -> dict[tuple[str, int, int], np.ndarray]:
    """(board, col, row) -> true pixel of every corner the renderer saw in one image."""
    return {(b["name"], int(i[0]), int(i[1])): np.array(c) for b in frame[f"boards_{side}"]
            for i, c in zip(b["ids"], b["corners"])}


def pose_of(frame: dict) -> tuple[np.ndarray, np.ndarray]:
    return np.array(frame["R_rig_robot"]), np.array(frame["t_rig_robot_m"])


def test_extrapolation_is_exact_for_constant_velocity() -> None:
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    R0 = Rotation.from_euler("xyz", [10, -20, 30], degrees=True).as_matrix()
    t0, v = np.array([0.1, -0.2, 1.0]), np.array([0.3, 0.1, -0.2])          # m, m/s
    w = 0.9                                                                   # rad/s about ``axis``

    def at(s: float) -> tuple[np.ndarray, np.ndarray]:
        return Rotation.from_rotvec(w * s * axis).as_matrix() @ R0, t0 + v * s

    ns = 10**9
    (Ra, ta), (Rb, tb) = at(0.0), at(1 / 30)
    R, t = extrapolate_pose(Ra, ta, 0, Rb, tb, ns // 30, 3 * ns // 30)
    R_true, t_true = at(3 / 30)
    assert np.abs(t - t_true).max() < 1e-9
    assert np.linalg.norm(Rotation.from_matrix(R @ R_true.T).as_rotvec()) < 1e-9
    # A long gap is extrapolated no further than MAX_EXTRAPOLATION intervals.
    _, t_far = extrapolate_pose(Ra, ta, 0, Rb, tb, ns // 30, ns)
    assert np.allclose(t_far, tb + MAX_EXTRAPOLATION * (tb - ta))
    # Stamps that do not advance: the last pose as it is.
    R_same, t_same = extrapolate_pose(Ra, ta, 0, Rb, tb, ns // 30, ns // 30)
    assert np.allclose(R_same, Rb) and np.allclose(t_same, tb)


def test_predicted_corners_match_the_rendered_truth(robot) -> None:
    _folder, truth, cfg = robot
    frame = truth["frames"][0]
    R, t = pose_of(frame)
    for side in ("left", "right"):
        preds = {p.board.name: p for p in predict_corners(R, t, cfg.cameras, side, cfg.target)}
        seen = truth_corners(frame, side)
        assert preds, f"nothing predicted in the {side} image"
        for p in preds.values():
            for (c, r), xy in zip(p.ids, p.xy):
                key = (p.board.name, int(c), int(r))
                if key in seen:
                    assert np.linalg.norm(xy - seen[key]) < 0.05, key
        # Every rendered board is predicted unless it is seen closer to edge-on than MIN_FACING_COS.
        R_c, t_c = camera_from_rig(cfg.cameras, side, R, t)
        for name in {k[0] for k in seen}:
            facing = facing_cos(cfg.target.board(name), R_c, t_c)
            assert (name in preds) == (facing >= MIN_FACING_COS), (side, name, facing)
            if name in preds:
                rendered = sum(k[0] == name for k in seen)
                assert len(preds[name].ids) >= 0.9 * rendered


def left_view(robot) -> tuple:
    """The robot sequence's frame 1, left camera: (config, frame truth, grey image, the boards' corners
    predicted from the true pose)."""
    folder, truth, cfg = robot
    frame = truth["frames"][1]
    image = cv2.imread(str(folder / frame["left"]), cv2.IMREAD_GRAYSCALE)
    return cfg, frame, image, predict_corners(*pose_of(frame), cfg.cameras, "left", cfg.target)


def test_tracking_confirms_displaced_predictions_to_subpixel(robot) -> None:
    cfg, frame, image, preds = left_view(robot)
    # The prediction of a moving robot is a few pixels off: shift every board by 2.5 px.
    shifted = [CornerPrediction(p.board, p.ids, p.xy + np.array([2.0, -1.5])) for p in preds]
    found = track_boards(image, shifted)
    seen = truth_corners(frame, "left")
    errors = [np.linalg.norm(xy - seen[(d.board, int(c), int(r))]) for d in found
              for (c, r), xy in zip(d.ids, d.corners)]
    assert confirmed_fraction(preds, found) > 0.6
    assert np.median(errors) < 0.05 and max(errors) < 0.3
    assert all(d.board in {p.board.name for p in preds} for d in found)


def test_tracked_corners_are_refined_as_the_searched_ones(robot) -> None:
    # Verification's cornerSubPix corners then go through the full search's refiner (the saddle and the
    # X-junction fits): the same corners as the search's, and as close to the truth. (With cornerSubPix
    # alone they were 0.018 px off the search's (median) and 4x further from the truth on this render.)
    cfg, frame, image, preds = left_view(robot)
    searched = {(d.board, int(c), int(r)): xy for d in detect(image, cfg.target)
                for (c, r), xy, ok in zip(d.ids, d.corners, d.usable()) if ok}
    tracked = {(d.board, int(c), int(r)): (xy, cov) for d in track_boards(image, [
        CornerPrediction(p.board, p.ids, p.xy + np.array([0.3, -0.2])) for p in preds]) for (c, r), xy, cov in
        zip(d.ids, d.corners, d.covariance)}
    seen = truth_corners(frame, "left")
    common = sorted(set(searched) & set(tracked))
    assert len(common) > 0.8 * len(searched)
    apart = np.array([np.linalg.norm(tracked[k][0] - searched[k]) for k in common])
    err_tracked = np.array([np.linalg.norm(tracked[k][0] - seen[k]) for k in common])
    err_searched = np.array([np.linalg.norm(searched[k] - seen[k]) for k in common])
    assert np.median(apart) < 0.003
    assert np.sqrt(np.mean(err_tracked ** 2)) < 1.1 * np.sqrt(np.mean(err_searched ** 2))
    assert all(np.all(np.linalg.eigvalsh(tracked[k][1]) > 0) for k in common)


def test_tracking_rejects_boards_that_are_not_there(robot) -> None:
    cfg, frame, image, preds = left_view(robot)
    # Ids off by one column: every corner lands on a real corner, but the square colours are inverted.
    off_by_one = [CornerPrediction(p.board, p.ids + np.array([1, 0]), p.xy) for p in preds]
    assert track_boards(image, off_by_one) == []
    # Labels one square off diagonally: (c, r) predicted on the real corner (c + 1, r + 1). The colours
    # agree and most corners are confirmed; the real corners beyond the board's sides give it away.
    slipped = []
    for p in preds:
        at = {(int(c), int(r)): xy for (c, r), xy in zip(p.ids, p.xy)}
        keep = [(c - 1, r - 1) for (c, r) in at if c >= 1 and r >= 1]
        slipped.append(CornerPrediction(p.board, np.array(keep), np.array([at[(c + 1, r + 1)] for c, r in keep])))
    assert all(len(s.ids) >= 0.5 * s.board.n_corners for s in slipped)
    assert track_boards(image, slipped) == []
    # A blank image, and random noise (nothing like a chessboard where the predictions fall).
    assert track_boards(np.full_like(image, 128), preds) == []
    noise = np.random.default_rng(1).integers(0, 255, image.shape, dtype=np.uint8)
    assert track_boards(noise, preds) == []


def test_a_board_whose_confirmed_corners_frame_no_squares_is_not_kept_but_found_in_place(robot) -> None:
    """Every other corner of a board blotted out (as noise leaves a hard frame's confirmed corners
    scattered): its confirmed corners frame no square, so the colour check cannot decide and the board is
    not kept, but with the others placed by the board's motion the colours match: it is in place (no search
    around it is worth it). With its ids one column off (the colours inverted) it is not."""
    cfg, frame, image, preds = left_view(robot)
    # the board seen most squarely (its squares' shorter side longest): the blots leave its squares' middles
    board = max(preds, key=lambda p: np.median(nearest_spacing(p.xy)))
    square = float(np.median(np.linalg.norm(np.diff(board.xy, axis=0), axis=1)))    # along its rows
    blotted = image.copy()
    for (c, r), xy in zip(board.ids, board.xy):
        if (c + r) % 2 == 0:
            cv2.circle(blotted, (int(round(xy[0])), int(round(xy[1]))), int(0.5 * square), 128, -1)
    tracked = verify_boards(blotted, preds)
    assert {d.board for d in tracked.detections} == {p.board.name for p in preds} - {board.board.name}
    assert tracked.in_place == {board.board.name}
    assert [d.board for d in track_boards(blotted, preds)] == [d.board for d in tracked.detections]
    # in the untouched image every board is kept: none is left in place only
    assert verify_boards(image, preds).in_place == frozenset()
    off_by_one = [CornerPrediction(board.board, board.ids + np.array([1, 0]), board.xy)]
    assert verify_boards(blotted, off_by_one) == verify_boards(blotted, [])


def test_tracked_pose_is_as_accurate_as_the_searched_one(robot) -> None:
    folder, truth, cfg = robot
    f0, f1, f2 = truth["frames"]
    tracker = BoardTracker(cfg.target, cfg.cameras, TrackingSettings())
    for f in (f0, f1):                       # the two latest poses: the truth itself
        R, t = pose_of(f)
        tracker.update(Pose(R, t, np.eye(6), "stereo", True), f["stamp_ns"])
    left_pred, right_pred = tracker.predict(f2["stamp_ns"])
    images = [cv2.imread(str(folder / f2[s]), cv2.IMREAD_GRAYSCALE) for s in ("left", "right")]
    left, right = track_boards(images[0], left_pred), track_boards(images[1], right_pred)
    pose = estimate_pose(left, right, cfg.target, cfg.cameras, cfg.pose)
    assert pose.valid, pose.reason
    R_true, t_true = pose_of(f2)
    assert 1000 * np.linalg.norm(pose.t_m - t_true) < 0.3
    assert np.degrees(np.linalg.norm(Rotation.from_matrix(pose.R @ R_true.T).as_rotvec())) < 0.05


def test_tracker_predicts_only_from_a_recent_valid_pose(robot) -> None:
    _folder, truth, cfg = robot
    f0 = truth["frames"][0]
    R, t = pose_of(f0)
    tracker = BoardTracker(cfg.target, cfg.cameras, TrackingSettings(max_gap_s=0.1))
    assert tracker.predict(f0["stamp_ns"]) is None                 # nothing seen yet
    tracker.update(Pose(R, t, np.eye(6), "stereo", True), f0["stamp_ns"])
    assert tracker.predict(f0["stamp_ns"] + 33_000_000) is not None
    assert tracker.predict(f0["stamp_ns"] + 200_000_000) is None   # a gap longer than max_gap_s
    tracker.update(Pose.invalid("no board detected"), f0["stamp_ns"] + 33_000_000)
    assert tracker.predict(f0["stamp_ns"] + 66_000_000) is None    # an invalid pose forgets the motion
    tracker.update(Pose(R, t, np.eye(6), "stereo", True), f0["stamp_ns"] + 100)
    tracker.update(Pose(R, t, np.eye(6), "stereo", True), f0["stamp_ns"])     # back in time: a replay looped
    assert len(tracker._poses) == 1
    off = BoardTracker(cfg.target, cfg.cameras, TrackingSettings(enabled=False))
    off.update(Pose(R, t, np.eye(6), "stereo", True), f0["stamp_ns"])
    assert off.predict(f0["stamp_ns"] + 1) is None


def test_loop_tracks_and_searches_again_when_the_robot_jumps(robot, tmp_path: Path) -> None:
    """Frames 0, 1, 2 of the sequence, then frame 0 moved by a quarter of the image (the robot jumps): the
    loop searches frame 0, tracks 1 and 2, finds that the prediction for the jump does not hold, and
    searches that frame. (Frame 0 as it was is too close to the prediction: the search around the
    predicted corners finds its boards, and the frame is rightly tracked.)"""
    folder, _truth, _cfg = robot
    jump = tmp_path / "jump"
    for side in ("left", "right"):
        (jump / side).mkdir(parents=True)
        for k, src in enumerate((0, 1, 2, 0)):
            image = cv2.imread(str(folder / side / f"{src:06d}.png"), cv2.IMREAD_GRAYSCALE)
            if k == 3:
                image = np.roll(image, -image.shape[1] // 4, axis=1)
            cv2.imwrite(str(jump / side / f"{k:06d}.png"), image)
    (jump / "rig.yaml").write_bytes((folder / "rig.yaml").read_bytes())
    cfg = write_config(tmp_path / "live.yaml", jump, free_endpoint(),
                       source_extra={"pace": "fast", "latest_only": False}, loop={"stop_at_end": True})
    loop = LiveLoop(load_live_config(cfg))
    assert loop.run() == 0
    # (the moved frame's pose need not be valid: the move cuts a board and breaks the rig's geometry)
    assert loop.stats.frames == 4 and loop.stats.poses_valid >= 3
    assert loop.stats.tracked_frames == 2


def test_tracking_recovers_corners_a_scaled_prediction_misses_at_first(robot) -> None:
    """The robot came closer than predicted: each board's predictions are 8 % too small about its centre,
    so its outer corners are more than a quarter square off. The motion fitted to the inner corners finds them."""
    cfg, frame, image, preds = left_view(robot)
    shrunk = [CornerPrediction(p.board, p.ids, p.xy.mean(axis=0) + 0.92 * (p.xy - p.xy.mean(axis=0))) for p in preds]
    seen = truth_corners(frame, "left")
    found = {d.board: d for d in track_boards(image, shrunk)}
    for p in preds:
        far = np.linalg.norm(0.08 * (p.xy - p.xy.mean(axis=0)), axis=1)
        assert far.max() > 4.0                   # a first pass alone could not confirm these
        d = found[p.board.name]
        assert len(d.ids) == len(p.ids), p.board.name
        errors = [np.linalg.norm(xy - seen[(d.board, int(c), int(r))]) for (c, r), xy in zip(d.ids, d.corners)]
        # Within the motion check's bound (MAX_MOTION_RESIDUAL_PX); the pose's outlier test sees the rest.
        assert np.median(errors) < 0.05 and max(errors) < MAX_MOTION_RESIDUAL_PX


def test_search_near_finds_the_boards_around_their_prediction(robot) -> None:
    cfg, frame, image, preds = left_view(robot)
    # a lost track's prediction is some pixels off: the window still holds the boards
    moved = [CornerPrediction(p.board, p.ids, p.xy + np.array([6.0, -4.0])) for p in preds]
    x0, y0, x1, y1 = near_window(moved, image.shape)
    assert (x1 - x0) * (y1 - y0) < 0.4 * image.size
    near = search_near(image, moved, cfg.target)
    full = detect(image, cfg.target)
    assert sorted(d.board for d in near) == sorted(d.board for d in full)
    seen = truth_corners(frame, "left")
    errors = [np.linalg.norm(xy - seen[(d.board, int(c), int(r))]) for d in near
              for (c, r), xy in zip(d.ids, d.corners)]
    assert np.median(errors) < 0.05
    # the same corners as the whole image's search (its smoothing follows the noise of the window)
    by_board = {d.board: d for d in full}
    for d in near:
        assert np.array_equal(d.ids, by_board[d.board].ids)
        assert np.abs(d.corners - by_board[d.board].corners).max() < 0.1
    # a window that would cover most of the image is no use: the caller searches the image
    spread = [CornerPrediction(preds[0].board, preds[0].ids[:2], np.array([[20.0, 20.0], [1260.0, 780.0]]))]
    assert near_window(spread, image.shape) is None and search_near(image, spread, cfg.target) is None


def _stereo_frame(left: np.ndarray, right: np.ndarray, stamp_ns: int, seq: int) -> StereoFrame:
    return StereoFrame(Frame(left, stamp_ns, stamp_ns, seq, "left"), Frame(right, stamp_ns, stamp_ns, seq, "right"))


def test_a_board_hidden_from_verification_is_searched_for_around_its_prediction_not_in_the_whole_image(robot):
    """Frame 2 with the largest boards painted over in both images: verification confirms another board in
    each image, less than 0.6 of the corners the last frame found. The hidden boards are searched for where
    they must be (and not found); the frame stays tracked on the others, with its pose as accurate, instead
    of a full search of both images (which finds no more)."""
    folder, truth, cfg = robot
    pipeline = FramePipeline(cfg.target, cfg.cameras, cfg.detector, cfg.pose, TrackingSettings())
    try:
        images = [[cv2.imread(str(folder / f[s]), cv2.IMREAD_GRAYSCALE) for s in ("left", "right")]
                  for f in truth["frames"]]
        results = [pipeline.process(_stereo_frame(*images[k], truth["frames"][k]["stamp_ns"], k)) for k in (0, 1)]
        assert [r.tracked for r in results] == [False, True]
        found = [{d.board for d in dets} for dets in results[1].detections]
        # the boards seen in both images, largest first, hidden while each image keeps one and until what is
        # left is less than TrackingSettings' 0.6 of the corners found
        corners = {d.board: len(d.ids) for dets in results[1].detections for d in dets}
        total = sum(len(d.ids) for dets in results[1].detections for d in dets)
        hide: list[str] = []
        for name in sorted(found[0] & found[1], key=lambda n: -corners[n]):
            kept = sum(len(d.ids) for dets in results[1].detections for d in dets if d.board not in hide)
            if kept < 0.6 * total or not all(f - set(hide) - {name} for f in found):
                break
            hide.append(name)
        kept = sum(len(d.ids) for dets in results[1].detections for d in dets if d.board not in hide)
        assert hide and kept < 0.6 * total
        f2 = truth["frames"][2]
        painted = []
        for side, image in zip(("left", "right"), images[2]):
            image = image.copy()
            for b in f2[f"boards_{side}"]:
                if b["name"] in hide:
                    hull = cv2.convexHull(np.array(b["corners"], dtype=np.float32)).astype(np.int32)
                    cv2.fillConvexPoly(image, hull, 128)
                    cv2.polylines(image, [hull], True, 128, thickness=int(0.3 * _square_px(b["corners"])) + 8)
            painted.append(image)
        result = pipeline.process(_stereo_frame(*painted, f2["stamp_ns"], 2))
        assert result.tracked and result.pose.valid, result.pose.reason
        assert all(d.board not in hide for dets in result.detections for d in dets)
        R_true, t_true = pose_of(f2)
        assert 1000 * np.linalg.norm(result.pose.t_m - t_true) < 1.0
        # the whole image searched instead: no more boards than verification kept
        searched = [{d.board for d in detect(im, cfg.target)} for im in painted]
        assert all(not (s & set(hide)) for s in searched)
    finally:
        pipeline.close()


def _square_px(corners: list) -> float:
    xy = np.array(corners, dtype=float)
    return float(np.median(np.linalg.norm(np.diff(xy, axis=0), axis=1)))


def test_the_warm_up_board_has_cut_outer_squares_and_is_found_to_subpixel() -> None:
    """The live loop's (and bench/detect.py's) warm-up image exercises the rim refinement: its outer
    squares are cut, its corners still found where they were drawn."""
    from edgecal.stream.frame_pipeline import warm_up_image
    from edgecal.targets import planar_target

    image = warm_up_image((640, 480), 9, 6)
    square = 40                                                    # warm_up_image's largest square
    x0, y0 = (640 - 10 * square) // 2, (480 - 7 * square) // 2
    assert image[y0 + square // 10, x0 + square // 10] > 150      # the outer black square is cut short
    (det,) = detect(image, planar_target(9, 6, 30.0))
    assert det.complete
    drawn = np.array([x0 + (1 + det.ids[:, 0]) * square, y0 + (1 + det.ids[:, 1]) * square]).T - 0.5
    assert np.abs(det.corners - drawn).max() < 0.1


def test_the_motion_checks_median_is_numpys() -> None:
    """board_motion's median (a short-array shortcut) gives np.median's number, bit for bit."""
    from edgecal.detection.tracking import _median

    rng = np.random.default_rng(2)
    for n in range(1, 41):
        v = rng.standard_normal(n) * 10.0 ** rng.uniform(-3, 3)
        assert _median(v) == float(np.median(v))
    assert np.isnan(_median(np.array([1.0, np.nan, 2.0]))) and np.isnan(_median(np.zeros(0)))
