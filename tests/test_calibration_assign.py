"""Detections are assigned to the right boards and orientations by geometry; symmetric targets warn."""

import numpy as np

from edgecal.calibration.assign import assign, assign_stereo, rotate_ids, symmetry_warnings
from edgecal.calibration.types import RigidTransform
from edgecal.detection.types import Detection
from edgecal.synth.corners import cube_box_target, project_target, stereo_truth
from edgecal.targets import Board, Target

SIZE = (640, 480)


def _detections(cs, target, wrong_names=True, rotate=None):
    """Detections as a detector that cannot tell same-size boards apart would return them."""
    out = []
    rotate = rotate or {}
    for b in target.boards:
        idx = [i for i, k in enumerate(cs.keys) if k[0] == b.name]
        ids = np.array([cs.keys[i][1:] for i in idx])
        deg = rotate.get(b.name, 0)
        if deg:  # the detector numbered this grid from the other end
            ids = rotate_ids(ids, b.cols, b.rows, (360 - deg) % 360)
        name = target.boards[0].name if wrong_names else b.name
        out.append(Detection(name, cs.image_px[idx], ids, np.ones(len(idx)), (b.cols, b.rows)))
    return out[::-1]


def test_rotate_ids_are_rotations():
    ids = np.array([[0, 0], [3, 0], [0, 4]])
    r90 = rotate_ids(ids, 4, 5, 90)
    np.testing.assert_array_equal(r90, [[4, 0], [4, 3], [0, 0]])
    np.testing.assert_array_equal(rotate_ids(rotate_ids(ids, 4, 5, 90), 5, 4, 270), ids)
    np.testing.assert_array_equal(rotate_ids(rotate_ids(ids, 4, 5, 180), 4, 5, 180), ids)


def test_same_size_boards_are_told_apart_by_geometry():
    t = cube_box_target()
    cam, _, pose, _ = stereo_truth()
    cs = project_target(t, cam, pose, SIZE, 0.1)
    a = assign(_detections(cs, t), t)
    truth = dict(zip(cs.keys, map(tuple, cs.image_px)))
    got = dict(zip(a.corners.keys, map(tuple, a.corners.image_px)))
    assert got == truth
    assert a.rms_px < 0.5


def test_even_board_orientation_is_resolved():
    # 4x4 boards look the same turned by 90/180/270 degrees: geometry must pick the orientation
    t = cube_box_target(inner_corners=(4, 4), square_mm=18.0)
    t = Target("box-odd-one", (t.boards[0], t.boards[1], Board("right", 5, 4, 14.0, t.boards[2].origin_mm,
                                                               t.boards[2].x_axis, t.boards[2].y_axis)))
    cam, _, pose, _ = stereo_truth()
    cs = project_target(t, cam, pose, SIZE, 0.05)
    dets = _detections(cs, t, wrong_names=False, rotate={"top": 90, "front": 180})
    a = assign(dets, t)
    assert dict(zip(a.corners.keys, map(tuple, a.corners.image_px))) == dict(zip(cs.keys, map(tuple, cs.image_px)))


def test_symmetric_target_warns_and_names_a_board():
    t = cube_box_target(inner_corners=(4, 4), square_mm=18.0)
    warnings = symmetry_warnings(t)
    assert warnings and "symmetric" in warnings[0] and "different size" in warnings[0]
    assert symmetry_warnings(cube_box_target()) == []  # odd boards: the colours fix the orientation


def test_stereo_assignment_labels_both_images_alike_on_a_symmetric_target():
    t = cube_box_target(inner_corners=(4, 4), square_mm=18.0)
    cl, cr, pl, rig = stereo_truth()
    pr = RigidTransform.from_rt(rig.rotation @ pl.rotation, rig.rotation @ pl.tvec + rig.tvec)
    left, right = project_target(t, cl, pl, SIZE), project_target(t, cr, pr, SIZE)
    a_l, a_r = assign_stereo(_detections(left, t), _detections(right, t), t)
    # whichever symmetric labelling the left gets, the right must use the same one for the same corners
    lk = dict(zip(a_l.corners.keys, map(tuple, a_l.corners.image_px)))
    rk = dict(zip(a_r.corners.keys, map(tuple, a_r.corners.image_px)))
    true_l = {tuple(p): k for k, p in zip(left.keys, left.image_px)}
    true_r = {tuple(p): k for k, p in zip(right.keys, right.image_px)}
    relabel = {true_l[p]: k for k, p in lk.items()}   # true key -> assigned key (left)
    for k, p in rk.items():
        assert relabel[true_r[p]] == k


def test_nothing_of_the_target_gives_none():
    assert assign([], cube_box_target()) is None
