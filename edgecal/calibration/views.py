"""What a calibration is made from: the input views (one image file per camera), named by their files,
and the corners file that records the corners found in them so a solve can be replayed without detecting.

The corners file (NAME.corners.csv beside rig.yaml) is a CSV with ``#`` header lines, the idea of mrcal's
corners.vnl: one row per corner, and a row with an empty board for a view in which no board was found,
so the file lists every input view::

    # edgecal-corners/1
    # image_size: 1280 800
    # cameras: left right
    # target: box-100mm
    view,camera,file,board,col,row,x,y
    left03.jpg,left,/data/left03.jpg,chessboard-9x6,0,0,412.3381,220.9170

``col``/``row`` are the corner's id on its board (docs/conventions.md), ``x``/``y`` OpenCV pixels. This
module reads and writes; it does not detect or solve.
"""

from __future__ import annotations

import csv
import io
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from edgecal.calibration.types import CAMERA_NAMES, CornerSet
from edgecal.errors import ConfigError, InputError, quote
from edgecal.fileio import permission_denied
from edgecal.targets import Target

CORNERS_FORMAT = "edgecal-corners/1"
CORNER_COLUMNS = ("view", "camera", "file", "board", "col", "row", "x", "y")
# The detector's corner covariance (px^2), written after the corner so that a re-solve weighs the corners
# as the first solve did; files without these columns still read (every corner then weighs alike).
COVARIANCE_COLUMNS = ("cov_xx", "cov_xy", "cov_yy")


@dataclass(frozen=True)
class View:
    """One input view: a short name for messages and reports, and the image file of each camera."""

    name: str
    files: tuple[str, ...]   # left (or only) camera first


def camera_names(n_cameras: int) -> tuple[str, ...]:
    """"left", "right" for two cameras, "camera" for one (as Calibration.camera_names)."""
    return CAMERA_NAMES if n_cameras == 2 else ("camera",)


def name_views(files: Sequence[tuple[str | Path, ...]]) -> list[View]:
    """Views named by the first camera's file name; by a longer path where two names would be the same.

    A recording's ``left/000003.png`` and a folder's ``left03.jpg`` both name their view by the file the
    user can open; two folders holding the same file names get their folder in the name.
    """
    paths = [tuple(str(f) for f in fs) for fs in files]
    names = [Path(fs[0]).name for fs in paths]
    if len(set(names)) < len(names):
        try:
            common = os.path.commonpath([os.path.abspath(fs[0]) for fs in paths])
            names = [os.path.relpath(os.path.abspath(fs[0]), common) for fs in paths]
        except ValueError:  # different drives: fall back on the paths as given
            names = [fs[0] for fs in paths]
    if len(set(names)) < len(names):
        names = [f"{n} #{i + 1}" for i, n in enumerate(names)]
    return [View(n, fs) for n, fs in zip(names, paths)]


def corners_path(rig_path: str | Path) -> Path:
    """The corners file written beside ``rig_path``: NAME.corners.csv."""
    p = Path(rig_path)
    stem = p.name[: -len(p.suffix)] if p.suffix else p.name
    return p.with_name(f"{stem}.corners.csv")


def corner_set(target: Target, keys: list[tuple[str, int, int]], image_px: np.ndarray,
               image_cov_px2: np.ndarray | None = None) -> CornerSet:
    """The CornerSet of ``keys`` (board, col, row) at ``image_px`` (N, 2), with the target's 3-D points (mm)
    and the corners' covariances (N, 2, 2) when known.

    A planar target keeps each point in its board's own frame (z = 0), as planar calibration needs;
    a box puts it in the target frame.
    """
    if not keys:
        return CornerSet(np.zeros((0, 3)), np.zeros((0, 2)), ())
    obj = np.zeros((len(keys), 3))
    for i, (b, c, r) in enumerate(keys):
        board = target.board(b)
        ids = np.array([[c, r]])
        obj[i] = (board.board_points_mm(ids) if target.is_planar else board.target_points_mm(ids))[0]
    return CornerSet(obj, np.asarray(image_px, dtype=np.float64).reshape(-1, 2), tuple(keys), image_cov_px2)


def corners_text(views: list[View], corners: list[list[CornerSet]], image_size: tuple[int, int],
                 target: Target) -> str:
    """The corners file of ``corners[camera][view]`` found in ``views``."""
    names = camera_names(len(corners))
    out = io.StringIO()
    out.write(f"# {CORNERS_FORMAT}\n# image_size: {int(image_size[0])} {int(image_size[1])}\n"
              f"# cameras: {' '.join(names)}\n# target: {target.name}\n")
    w = csv.writer(out, lineterminator="\n")
    w.writerow(CORNER_COLUMNS + COVARIANCE_COLUMNS)
    for v, view in enumerate(views):
        for c, cam in enumerate(names):
            cs = corners[c][v]
            if not len(cs):
                w.writerow([view.name, cam, view.files[c], "", "", "", "", "", "", "", ""])
            covs = cs.image_cov_px2 if cs.image_cov_px2 is not None else [None] * len(cs)
            for (b, col, row), (x, y), cov in zip(cs.keys, cs.image_px, covs):
                var = ["", "", ""] if cov is None else [f"{cov[0, 0]:.6g}", f"{cov[0, 1]:.6g}", f"{cov[1, 1]:.6g}"]
                w.writerow([view.name, cam, view.files[c], b, col, row, f"{x:.4f}", f"{y:.4f}", *var])
    return out.getvalue()


@dataclass(frozen=True)
class CornersFile:
    """A corners file read back: the views, their corners ``[camera][view]`` and the image size."""

    views: list[View]
    corners: list[list[CornerSet]]
    image_size: tuple[int, int]


def _covariance(row: dict, where: str) -> list[list[float]] | None:
    """The corner's 2x2 covariance from a row's cov_* columns; None when they are absent or empty."""
    text = [row.get(k) or "" for k in COVARIANCE_COLUMNS]
    if not all(text):
        return None
    try:
        xx, xy, yy = (float(v) for v in text)
    except ValueError:
        raise ConfigError(f"{where}: cov_xx,cov_xy,cov_yy must be numbers") from None
    if not (np.isfinite([xx, xy, yy]).all() and xx > 0 and yy > 0 and xx * yy > xy * xy):
        raise ConfigError(f"{where}: the covariance ({text[0][:12]}, {text[1][:12]}, {text[2][:12]}) is not "
                          f"positive definite")
    return [[xx, xy], [xy, yy]]


def read_corners(path: str | Path, target: Target) -> CornersFile:
    """Read a corners file written by :func:`corners_text` against ``target``.

    Raises InputError for a missing or unreadable file, ConfigError naming the line for a bad row or a
    board the target does not have.
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputError(f"{p}: corners file not found (calibrate writes NAME.corners.csv beside rig.yaml)") from None
    except PermissionError:
        raise permission_denied(p, "corners file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{p}: cannot read the corners file ({exc})") from None
    lines = text.splitlines()
    header: dict[str, str] = {}
    n_head = 0
    for line in lines:
        if not line.startswith("#"):
            break
        n_head += 1
        key, _, value = line[1:].partition(":")
        header[key.strip()] = value.strip()
    if CORNERS_FORMAT not in header:
        raise InputError(f"{p}: not an edgecal corners file (its first line must be '# {CORNERS_FORMAT}')")
    try:
        w, h = (int(v) for v in header.get("image_size", "").split())
        cams = tuple(header["cameras"].split())
    except (KeyError, ValueError):
        raise InputError(f"{p}: the header needs '# image_size: W H' and '# cameras: ...'") from None
    if cams not in (("camera",), CAMERA_NAMES):
        raise InputError(f"{p}: '# cameras:' must be 'camera' or 'left right' (got {quote(header['cameras'])})")
    reader = csv.DictReader(lines[n_head:])
    if tuple(reader.fieldnames or ()) not in (CORNER_COLUMNS, CORNER_COLUMNS + COVARIANCE_COLUMNS):
        raise InputError(f"{p}: line {n_head + 1} must be the column names {','.join(CORNER_COLUMNS)} "
                         f"(optionally followed by {','.join(COVARIANCE_COLUMNS)})")
    order: list[str] = []
    files: dict[str, dict[str, str]] = {}
    rows: dict[tuple[str, str], tuple[list[tuple[str, int, int]], list[tuple[float, float]], list]] = {}
    for k, row in enumerate(reader):
        where = f"{p}: line {n_head + 2 + k}"
        view, cam = row["view"] or "", row["camera"] or ""
        if cam not in cams:
            raise ConfigError(f"{where}: camera {quote(cam)} is not one of {' '.join(cams)}")
        if view not in files:
            order.append(view)
            files[view] = {}
        files[view][cam] = row["file"] or ""
        keys, px, covs = rows.setdefault((view, cam), ([], [], []))
        if not row["board"]:
            continue
        try:
            board = target.board(row["board"])
        except KeyError:
            raise ConfigError(f"{where}: board {quote(row['board'])} is not in target {target.name!r} "
                              f"(give the --target/--board the corners were found with)") from None
        try:
            col, r, x, y = int(row["col"]), int(row["row"]), float(row["x"]), float(row["y"])
        except (TypeError, ValueError):
            raise ConfigError(f"{where}: col,row must be whole numbers and x,y numbers") from None
        if not (0 <= col < board.cols and 0 <= r < board.rows):
            raise ConfigError(f"{where}: corner ({col},{r}) is outside board {board.name!r} "
                              f"({board.cols}x{board.rows} inner corners)")
        keys.append((board.name, col, r))
        px.append((x, y))
        covs.append(_covariance(row, where))
    if not order:
        raise InputError(f"{p}: the corners file lists no view")
    views: list[View] = []
    corners: list[list[CornerSet]] = [[] for _ in cams]
    for name in order:
        missing = [c for c in cams if c not in files[name]]
        if missing:
            raise ConfigError(f"{p}: view {quote(name)} has no row for the {missing[0]} camera")
        views.append(View(name, tuple(files[name][c] for c in cams)))
        for c, cam in enumerate(cams):
            keys, px, covs = rows[(name, cam)]
            has_cov = covs and all(v is not None for v in covs)
            cov = np.array(covs, dtype=np.float64).reshape(-1, 2, 2) if has_cov else None
            corners[c].append(corner_set(target, keys, np.array(px, dtype=np.float64), cov))
    return CornersFile(views, corners, (w, h))
