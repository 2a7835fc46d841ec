"""Calibration and pose targets: one or more planar chessboards placed in a target frame.

A target file (configs/targets/*.yaml) looks like::

    name: box-100mm
    boards:
      - name: top
        inner_corners: [4, 5]      # cols x rows of inner corners
        square_mm: 14.0
        origin_mm: [0, 0, 100]     # 3-D position of inner corner (col 0, row 0) in the target frame
        x_axis: [1, 0, 0]          # unit direction of increasing col
        y_axis: [0, 1, 0]          # unit direction of increasing row

A single flat board may leave out origin_mm/x_axis/y_axis (the board frame is the target frame).
Board-frame object points are (col * square, row * square, 0). The square on the -x,-y side of
corner (0, 0) is black; see docs/conventions.md.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from edgecal.config import ConfigReader, load_yaml_mapping, read_settings, setting
from edgecal.errors import ConfigError, quote


@dataclass(frozen=True)
class Board:
    """One planar chessboard: ``cols`` x ``rows`` inner corners, placed in the target frame (mm)."""

    name: str
    cols: int
    rows: int
    square_mm: float
    origin_mm: np.ndarray = field(default_factory=lambda: np.zeros(3))
    x_axis: np.ndarray = field(default_factory=lambda: np.array([1.0, 0.0, 0.0]))
    y_axis: np.ndarray = field(default_factory=lambda: np.array([0.0, 1.0, 0.0]))

    @property
    def n_corners(self) -> int:
        """Number of inner corners."""
        return self.cols * self.rows

    def ids(self) -> np.ndarray:
        """(col, row) of every corner, row-major (row 0 first), shape (N, 2) int."""
        rows, cols = np.mgrid[0:self.rows, 0:self.cols]
        return np.stack([cols.ravel(), rows.ravel()], axis=1).astype(np.int64)

    def board_points_mm(self, ids: np.ndarray | None = None) -> np.ndarray:
        """Board-frame points (col*s, row*s, 0) in mm for ``ids`` (default: all, row-major)."""
        ids = self.ids() if ids is None else np.asarray(ids, dtype=np.int64).reshape(-1, 2)
        pts = np.zeros((len(ids), 3))
        pts[:, :2] = ids * self.square_mm
        return pts

    def target_points_mm(self, ids: np.ndarray | None = None) -> np.ndarray:
        """Target-frame points in mm for ``ids`` (default: all, row-major)."""
        ids = self.ids() if ids is None else np.asarray(ids, dtype=np.int64).reshape(-1, 2)
        s = self.square_mm
        return (self.origin_mm[None, :] + (ids[:, :1] * s) * self.x_axis[None, :]
                + (ids[:, 1:2] * s) * self.y_axis[None, :])

    @property
    def centre_mm(self) -> np.ndarray:
        """Target-frame centre of the inner-corner grid in mm."""
        s = self.square_mm
        return self.origin_mm + (0.5 * (self.cols - 1) * s) * self.x_axis + (0.5 * (self.rows - 1) * s) * self.y_axis

    @property
    def normal(self) -> np.ndarray:
        """Unit normal x_axis × y_axis (right-handed board frame)."""
        return np.cross(self.x_axis, self.y_axis)


@dataclass(frozen=True)
class Target:
    """A named set of boards; ``source`` is the file it came from (for messages)."""

    name: str
    boards: tuple[Board, ...]
    source: str = ""

    def board(self, name: str) -> Board:
        """The board called ``name``."""
        for b in self.boards:
            if b.name == name:
                return b
        raise KeyError(name)

    @property
    def is_planar(self) -> bool:
        """True when every board lies in one plane (no non-coplanar calibration possible)."""
        pts = np.concatenate([b.target_points_mm() for b in self.boards])
        centred = pts - pts.mean(axis=0)
        return bool(np.linalg.svd(centred, compute_uv=False)[-1] < 1e-6 * max(1.0, np.abs(centred).max()))


def _unit_check(v: list[float]) -> str | None:
    n = float(np.linalg.norm(v))
    if abs(n - 1.0) > 1e-3:
        return f"must be a unit vector (its length is {n:.4f})"
    return None


def _read_inner_corners(r: ConfigReader, key: str) -> tuple[int, int]:
    value = r.raw(key)
    if (not isinstance(value, (list, tuple)) or len(value) != 2
            or any(isinstance(v, bool) or not isinstance(v, int) for v in value)):
        raise r.fail(key, f"must be [cols, rows], two whole numbers (got {quote(value)})")
    cols, rows = int(value[0]), int(value[1])
    if cols < 2 or rows < 2:
        raise r.fail(key, f"needs at least 2 x 2 inner corners (got {cols} x {rows})")
    return cols, rows


def _read_origin(r: ConfigReader, key: str) -> tuple[float, ...]:
    return tuple(r.vector(key, 3, [0.0, 0.0, 0.0]))


def _read_x_axis(r: ConfigReader, key: str) -> tuple[float, ...]:
    return tuple(r.vector(key, 3, [1.0, 0.0, 0.0], check=_unit_check))


def _read_y_axis(r: ConfigReader, key: str) -> tuple[float, ...]:
    return tuple(r.vector(key, 3, [0.0, 1.0, 0.0], check=_unit_check))


@dataclass(frozen=True, kw_only=True)
class _BoardEntry:
    """One entry of a target file's ``boards`` list as the file writes it; `Board` is what the code uses
    (the file says ``inner_corners: [cols, rows]`` and lists, a Board holds cols, rows and arrays)."""

    name: str | None = setting(None, doc="the board's name (default board<index>), unique in the target")
    inner_corners: tuple[int, int] = setting(doc="[cols, rows] of inner corners", read=_read_inner_corners)
    square_mm: float = setting(doc="the side of a square (mm)", positive=True)
    origin_mm: tuple[float, ...] = setting((0.0, 0.0, 0.0), doc="inner corner (col 0, row 0) in the target "
                                           "frame (mm)", read=_read_origin)
    x_axis: tuple[float, ...] = setting((1.0, 0.0, 0.0), doc="unit direction of increasing col",
                                        read=_read_x_axis)
    y_axis: tuple[float, ...] = setting((0.0, 1.0, 0.0), doc="unit direction of increasing row",
                                        read=_read_y_axis)

    def config_problem(self) -> tuple[str, str] | None:
        """The axes must be perpendicular (read_settings names the field)."""
        if abs(float(np.dot(self.x_axis, self.y_axis))) > 1e-3:
            return "y_axis", "must be perpendicular to x_axis"
        return None

    def board(self, index: int) -> Board:
        """The Board this entry describes (``index`` names an unnamed one)."""
        cols, rows = self.inner_corners
        return Board(self.name or f"board{index}", cols, rows, self.square_mm, np.array(self.origin_mm),
                     np.array(self.x_axis), np.array(self.y_axis))


def _read_boards(r: ConfigReader, key: str) -> tuple[Board, ...]:
    return tuple(read_settings(_BoardEntry, br).board(i) for i, br in enumerate(r.sections(key)))


@dataclass(frozen=True, kw_only=True)
class _TargetFile:
    """A target file (configs/targets/*.yaml) as written."""

    name: str | None = setting(None, doc="the target's name (default: the file's stem)")
    boards: tuple[Board, ...] = setting(doc="the boards, each placed in the target frame", read=_read_boards)
    description: str | None = setting(None, doc="free text for people")


def target_from_mapping(data: dict, source: str) -> Target:
    """Build and validate a Target from a parsed YAML mapping; ``source`` names it in messages."""
    entry = read_settings(_TargetFile, ConfigReader(data, source))
    names = [b.name for b in entry.boards]
    for i, n in enumerate(names):
        if names.index(n) != i:
            raise ConfigError(f"{source}: field 'boards[{i}].name' repeats the board name {quote(n)}")
    return Target(entry.name or Path(source).stem or "target", entry.boards, source)


def load_target(path: str | Path) -> Target:
    """Load and validate a target YAML file (raises ConfigError naming the field)."""
    return target_from_mapping(load_yaml_mapping(path), str(path))


_BOARD_SPEC = re.compile(r"^\s*(\d+)\s*[xX]\s*(\d+)\s*$")


def planar_target(cols: int, rows: int, square_mm: float = 1.0, name: str | None = None) -> Target:
    """A target of one flat board with ``cols`` x ``rows`` inner corners."""
    label = name or f"chessboard-{cols}x{rows}"
    return Target(label, (Board(label, cols, rows, float(square_mm)),), source=f"--board {cols}x{rows}")


def parse_board_spec(spec: str, square_mm: float = 1.0) -> Target:
    """Parse the command-line shorthand ``CxR`` (inner corners) into a planar target."""
    m = _BOARD_SPEC.match(spec)
    if not m:
        raise ConfigError(f"--board {quote(spec)}: expected COLSxROWS of inner corners, e.g. 9x6")
    cols, rows = int(m.group(1)), int(m.group(2))
    if cols < 2 or rows < 2:
        raise ConfigError(f"--board {quote(spec)}: needs at least 2x2 inner corners")
    return planar_target(cols, rows, square_mm)
