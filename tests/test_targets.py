"""Target files (configs/targets/*.yaml): the shipped ones load, and every bad field is named in one line."""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest
import yaml

from edgecal.errors import ConfigError
from edgecal.targets import load_target, parse_board_spec

TARGETS = Path(__file__).resolve().parents[1] / "configs" / "targets"
BOARD = {"name": "top", "inner_corners": [4, 5], "square_mm": 14.0,
         "origin_mm": [0, 0, 100], "x_axis": [1, 0, 0], "y_axis": [0, 1, 0]}


def _write(tmp_path: Path, data: dict) -> Path:
    path = tmp_path / "target.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.mark.parametrize("path", sorted(TARGETS.glob("*.yaml")), ids=lambda p: p.stem)
def test_every_shipped_target_loads(path):
    target = load_target(path)
    assert target.boards and target.name
    for b in target.boards:
        assert abs(np.linalg.norm(b.normal) - 1.0) < 1e-3


def test_a_board_entry_becomes_a_board_in_the_target_frame(tmp_path):
    entry = dict(BOARD, x_axis=[0, 1, 0], y_axis=[0, 0, 1])
    target = load_target(_write(tmp_path, {"name": "box", "boards": [entry, {"inner_corners": [3, 2],
                                                                             "square_mm": 10}]}))
    top, second = target.boards
    assert (top.name, top.cols, top.rows, top.square_mm) == ("top", 4, 5, 14.0)
    # corner (col 1, row 2) lies one square along x_axis and two along y_axis from the origin
    np.testing.assert_allclose(top.target_points_mm(np.array([[1, 2]])), [[0.0, 14.0, 128.0]])
    assert second.name == "board1" and np.array_equal(second.origin_mm, np.zeros(3))
    assert target.name == "box"


def test_the_target_name_defaults_to_the_file_stem(tmp_path):
    assert load_target(_write(tmp_path, {"boards": [BOARD]})).name == "target"


@pytest.mark.parametrize("change, field, what", [
    ({"inner_corners": "4x5"}, "boards[0].inner_corners", "must be [cols, rows], two whole numbers (got '4x5')"),
    ({"inner_corners": [4, 5, 6]}, "boards[0].inner_corners", "two whole numbers"),
    ({"inner_corners": [4.0, 5]}, "boards[0].inner_corners", "two whole numbers"),
    ({"inner_corners": [True, 5]}, "boards[0].inner_corners", "two whole numbers"),
    ({"inner_corners": [1, 5]}, "boards[0].inner_corners", "needs at least 2 x 2 inner corners (got 1 x 5)"),
    ({"inner_corners": None}, "boards[0].inner_corners", "is missing"),
    ({"square_mm": -3}, "boards[0].square_mm", "must be greater than 0 (got -3)"),
    ({"square_mm": "x"}, "boards[0].square_mm", "must be a number (got 'x')"),
    ({"origin_mm": [0, 0]}, "boards[0].origin_mm", "must be a list of 3 numbers (got [0, 0])"),
    ({"x_axis": [float("nan"), 0, 0]}, "boards[0].x_axis", "must be a list of 3 numbers"),
    ({"x_axis": [2, 0, 0]}, "boards[0].x_axis", "must be a unit vector (its length is 2.0000)"),
    ({"y_axis": [1, 0, 0]}, "boards[0].y_axis", "must be perpendicular to x_axis"),
    ({"name": ""}, "boards[0].name", "must be a non-empty string"),
    ({"colour": "red"}, "boards[0].colour", "is not a known field (known: name, inner_corners, square_mm"),
])
def test_a_bad_board_field_is_named(tmp_path, change, field, what):
    with pytest.raises(ConfigError) as err:
        load_target(_write(tmp_path, {"name": "t", "boards": [dict(BOARD, **change)]}))
    line = str(err.value)
    assert f"field '{field}' " in line and what in line and "\n" not in line


@pytest.mark.parametrize("data, field, what", [
    ({"name": "t"}, "boards", "is missing"),
    ({"name": "t", "boards": []}, "boards", "must be a non-empty list"),
    ({"name": "t", "boards": [3]}, "boards[0]", "must be a mapping of field: value"),
    ({"name": "t", "boards": [BOARD, copy.deepcopy(BOARD)]}, "boards[1].name", "repeats the board name 'top'"),
    ({"name": "t", "boards": [BOARD], "foo": 1}, "foo", "is not a known field (known: name, boards, description)"),
    ({"name": "t", "boards": [BOARD], "description": ["a", "list"]}, "description", "must be a non-empty string"),
])
def test_a_bad_target_field_is_named(tmp_path, data, field, what):
    with pytest.raises(ConfigError) as err:
        load_target(_write(tmp_path, data))
    assert f"field '{field}' " in str(err.value) and what in str(err.value)


@pytest.mark.parametrize("spec", ["9", "9x", "x6", "9x6x2", "nine by six", "1x6"])
def test_a_bad_board_shorthand_is_refused(spec):
    with pytest.raises(ConfigError, match="--board"):
        parse_board_spec(spec)
