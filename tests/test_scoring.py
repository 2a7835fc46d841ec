"""Scoring functions of edgecal.scoring on small hand-built truth and detection arrays, and the truth reader."""

from __future__ import annotations

import json

import numpy as np
import pytest

from edgecal.errors import InputError
from edgecal.scoring import FoundGrid, corner_rms, grid_is_plausible, grid_symmetries, match_board, score_image
from edgecal.synth.truth import GT_FORMAT, GroundTruth, TruthBoard, load_ground_truth


def grid_ids(cols: int, rows: int) -> np.ndarray:
    """Row-major (col, row) ids."""
    r, c = np.mgrid[0:rows, 0:cols]
    return np.stack([c.ravel(), r.ravel()], axis=1)


def board_xy(ids: np.ndarray, origin=(100.0, 50.0), u=(20.0, 3.0), v=(-4.0, 18.0)) -> np.ndarray:
    """Pixel positions of ids on an affinely distorted grid (spacing about 20 px)."""
    ids = np.asarray(ids, dtype=float)
    return np.asarray(origin) + ids[:, :1] * np.asarray(u) + ids[:, 1:] * np.asarray(v)


def truth_board(cols=5, rows=4, **kw) -> TruthBoard:
    ids = grid_ids(cols, rows)
    return TruthBoard(f"b{cols}x{rows}", cols, rows, ids, board_xy(ids, **kw))


def truth_of(*boards: TruthBoard, exact: bool = True) -> GroundTruth:
    return GroundTruth("img.png", (640, 480), tuple(boards), exact)


def test_identity_detection_is_found_and_rms_is_the_noise():
    tb = truth_board()
    rng = np.random.default_rng(1)
    noise = rng.normal(0, 0.1, tb.corners.shape)
    found = FoundGrid(tb.corners + noise, tb.ids.copy(), (5, 4))
    m = match_board(found, tb)
    assert m is not None and m.found and m.symmetry == "identity"
    assert m.correct.all()
    expected = np.sqrt(np.mean(np.sum(noise ** 2, axis=1)))
    assert corner_rms(m.errors) == pytest.approx(expected)
    s = score_image([found], truth_of(tb))
    assert s.n_found == 1 and s.false_boards == 0 and s.partial == 0


def test_rotated_numbering_is_the_same_board_but_a_mirror_is_not():
    tb = truth_board(5, 4)
    turned = np.stack([4 - tb.ids[:, 0], 3 - tb.ids[:, 1]], axis=1)
    m = match_board(FoundGrid(tb.corners, turned, (5, 4)), tb, policy="board")
    assert m.found and m.symmetry == "rot180"

    mirrored = np.stack([4 - tb.ids[:, 0], tb.ids[:, 1]], axis=1)
    strict = match_board(FoundGrid(tb.corners, mirrored, (5, 4)), tb, policy="board")
    assert strict is not None and not strict.found
    loose = match_board(FoundGrid(tb.corners, mirrored, (5, 4)), tb, policy="grid")
    assert loose.found and loose.symmetry == "flip_cols"


def test_transposed_grid_only_under_grid_policy():
    tb = truth_board(5, 4)
    found = FoundGrid(tb.corners, tb.ids[:, ::-1].copy(), (4, 5))
    assert match_board(found, tb, policy="board") is None
    m = match_board(found, tb, policy="grid")
    assert m.found and m.symmetry == "transpose"


def test_square_board_allows_quarter_turns():
    tb = truth_board(4, 4)
    quarter = np.stack([3 - tb.ids[:, 1], tb.ids[:, 0]], axis=1)
    m = match_board(FoundGrid(tb.corners, quarter, (4, 4)), tb, policy="board")
    assert m.found and m.symmetry == "rot270"  # the inverse map carries the ids back
    names = [n for n, _ in grid_symmetries((4, 4), (4, 4), "board")]
    assert sorted(names) == ["identity", "rot180", "rot270", "rot90"]
    assert [n for n, _ in grid_symmetries((5, 4), (5, 4), "board")] == ["identity", "rot180"]
    assert len(grid_symmetries((5, 4), (4, 5), "grid")) == 4
    with pytest.raises(ValueError):
        grid_symmetries((5, 4), (5, 4), "any")


def test_swapped_neighbours_or_a_missing_corner_is_not_found():
    tb = truth_board()
    ids = tb.ids.copy()
    ids[[6, 7]] = ids[[7, 6]]
    m = match_board(FoundGrid(tb.corners, ids, (5, 4)), tb)
    assert not m.found and int((~m.correct).sum()) == 2

    missing = FoundGrid(tb.corners[1:], tb.ids[1:], (5, 4))
    m = match_board(missing, tb)
    assert not m.found and m.n_named == 19 and m.correct.all()

    far = tb.corners.copy()
    far[3] += (4.0, 0.0)  # still nearest to its own truth corner, but beyond max_error_px
    m = match_board(FoundGrid(far, tb.ids, (5, 4)), tb, max_error_px=3.0)
    assert not m.found
    assert match_board(FoundGrid(far, tb.ids, (5, 4)), tb, max_error_px=5.0).found

    partial = FoundGrid(tb.corners, tb.ids, (5, 4), complete=False)
    assert not match_board(partial, tb).found


def test_false_boards_and_duplicates():
    tb = truth_board()
    good = FoundGrid(tb.corners, tb.ids, (5, 4))
    elsewhere = FoundGrid(tb.corners + (300.0, 300.0), tb.ids, (5, 4))
    s = score_image([elsewhere, good, good], truth_of(tb))
    assert s.n_found == 1 and s.false_boards == 1 and s.partial == 1

    negative = score_image([good], truth_of())
    assert negative.n_truth == 0 and negative.false_boards == 1 and negative.n_found == 0
    assert score_image([], truth_of()).false_boards == 0


def test_multi_board_image_assigns_each_detection_to_its_board():
    a = truth_board(5, 4)
    b = truth_board(3, 3, origin=(400.0, 300.0))
    found = [FoundGrid(b.corners[::-1], b.ids[::-1], (3, 3)), FoundGrid(a.corners, a.ids, (5, 4))]
    s = score_image(found, truth_of(a, b))
    assert s.n_found == 2 and s.false_boards == 0
    assert len(s.found_errors()) == 29 and np.allclose(s.found_errors(), 0.0)
    assert s.misnamed == 0
    named = [FoundGrid(a.corners, a.ids, (5, 4), name=b.name), FoundGrid(b.corners, b.ids, (3, 3), name=b.name)]
    s = score_image(named, truth_of(a, b))
    assert s.n_found == 2 and s.misnamed == 1
    only_one = score_image(found[:1], truth_of(a, b))
    assert only_one.n_found == 1 and only_one.matches[0] is None
    sub = FoundGrid(a.corners[:10], a.ids[:10], (5, 4), complete=False)
    s = score_image([sub], truth_of(a, b))
    assert s.n_found == 0 and s.partial == 1 and s.false_boards == 0


def test_rough_reference_tolerates_a_few_off_corner_points():
    tb = truth_board()
    moved = tb.corners.copy()
    moved[:4] += (9.0, 0.0)  # bad reference points: 4 of 20 still leaves 80 % agreeing
    ref = TruthBoard(tb.name, tb.cols, tb.rows, tb.ids, moved)
    found = [FoundGrid(tb.corners, tb.ids, (5, 4))]
    assert score_image(found, truth_of(ref, exact=True)).n_found == 0
    rough = score_image(found, truth_of(ref, exact=False))
    assert rough.n_found == 1 and len(rough.found_errors()) == 16


def test_corner_rms_of_known_errors():
    assert corner_rms(np.array([3.0, 4.0])) == pytest.approx(np.sqrt(12.5))
    assert np.isnan(corner_rms(np.zeros(0)))


def test_grid_plausibility():
    ids = grid_ids(6, 5)
    xy = board_xy(ids)
    # a mild barrel bend stays plausible
    centre = xy.mean(axis=0)
    r2 = np.sum((xy - centre) ** 2, axis=1, keepdims=True)
    bent = centre + (xy - centre) * (1 - 2e-6 * r2)
    assert grid_is_plausible(FoundGrid(bent, ids, (6, 5)))
    swapped = ids.copy()
    swapped[[8, 14]] = swapped[[14, 8]]
    assert not grid_is_plausible(FoundGrid(xy, swapped, (6, 5)))
    assert not grid_is_plausible(FoundGrid(xy[:-1], ids[:-1], (6, 5)))
    collapsed = xy.copy()
    collapsed[:, 1] = collapsed[:, 0] * 0.5  # all points on one line
    assert not grid_is_plausible(FoundGrid(collapsed, ids, (6, 5)))


def test_load_ground_truth(tmp_path):
    tb = truth_board(3, 2)
    data = {
        "format": GT_FORMAT, "size": [640, 480], "image": "x.png",
        "boards": [{"name": "b", "cols": 3, "rows": 2, "ids": tb.ids.tolist(),
                    "corners": tb.corners.tolist(), "complete": True}],
    }
    p = tmp_path / "x.json"
    p.write_text(json.dumps(data))
    gt = load_ground_truth(p)
    assert gt.size == (640, 480) and gt.exact and len(gt.boards) == 1
    assert gt.boards[0].complete and np.allclose(gt.boards[0].corners, tb.corners)

    p.write_text(json.dumps({**data, "format": "other/1"}))
    with pytest.raises(InputError, match="'format'"):
        load_ground_truth(p)
    del data["boards"][0]["corners"]
    p.write_text(json.dumps(data))
    with pytest.raises(InputError, match=r"boards\[0\]\.corners"):
        load_ground_truth(p)
    with pytest.raises(InputError, match="not found"):
        load_ground_truth(tmp_path / "missing.json")
