"""Ground truth of a rendered view in the "edgecal-synth-gt/1" JSON format: built here, and read back.

The format is the one of ../shared/data/synthetic/README.md, so one scoring code reads the shared sets
and edgecal's own renders. Corner pixels come from edgecal.camera.project (equal to cv2.projectPoints and
cv2.fisheye.projectPoints, the reference definitions, to 1e-6 px; tests/test_camera.py); a corner is listed
only when its printed side faces the camera, no other panel is in front of it (nor of the board within 0.3
squares around it) and it lies at least ``border_px`` inside the image.

Reading: :func:`load_ground_truth` (a file) and :func:`ground_truth_from_mapping` (a parsed document)
give a :class:`GroundTruth` of :class:`TruthBoard` arrays, which edgecal.scoring compares detections
with; bench/references.py gives the same types from other tools' reference corners.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from edgecal.camera import CameraModel, unproject
from edgecal.errors import InputError, quote
from edgecal.synth.camera import pixel_rays, project_world
from edgecal.synth.panels import Panel
from edgecal.synth.render import visible_mask

GT_FORMAT = "edgecal-synth-gt/1"
PAIR_FORMAT = "edgecal-synth-gt/1+stereo"
UNITS = {"length": "mm", "pixels": "OpenCV: integer coordinates are pixel centres, x right, y down"}


def board_truth(camera: CameraModel, panels: list[Panel], R_cam_world: np.ndarray, t_cam_world_mm: np.ndarray,
                border_px: float = 4.0, occlusion_margin: float = 0.3) -> list[dict]:
    """The ``boards`` section: per printed panel with at least one visible corner, its visible corners.

    A corner is visible when its printed side faces the camera, no panel hides it or the board within
    ``occlusion_margin`` squares around it, and it lies ``border_px`` inside the image.
    """
    R = np.asarray(R_cam_world, dtype=np.float64)
    t = np.asarray(t_cam_world_mm, dtype=np.float64).ravel()
    w, h = camera.image_size
    out = []
    board_index = -1
    for k, p in enumerate(panels):
        if p.board is None:
            continue
        board_index += 1
        b = p.board
        ids = b.ids()
        s = b.square_mm
        xyz = (np.asarray(p.origin_mm)[None, :] + (ids[:, :1] * s) * np.asarray(p.x_axis)[None, :]
               + (ids[:, 1:2] * s) * np.asarray(p.y_axis)[None, :])
        z = (xyz @ R.T + t)[:, 2]
        # a pinhole lens sees only what is in front of it; a fisheye lens also what is beside and behind
        ok = visible_mask(camera, panels, R, t, k, xyz) & ((z > 0) | (camera.lens == "fisheye"))
        if occlusion_margin > 0 and ok.any():
            # A corner right at an occluding edge has half a saddle: list it only when the board around it
            # (occlusion_margin squares in 8 directions) is visible too.
            q = occlusion_margin * s
            offs = np.array([[1, 0], [-1, 0], [0, 1], [0, -1], [1, 1], [1, -1], [-1, 1], [-1, -1]], float) * q
            around = (xyz[:, None, :] + offs[None, :, :1] * np.asarray(p.x_axis)[None, None, :]
                      + offs[None, :, 1:] * np.asarray(p.y_axis)[None, None, :]).reshape(-1, 3)
            ok &= visible_mask(camera, panels, R, t, k, around).reshape(-1, 8).all(axis=1)
        px = np.full((len(ids), 2), np.nan)
        if ok.any():
            px[ok] = project_world(camera, xyz[ok], R, t)
            # Beyond the radius where the distortion folds over, a point can project into the image
            # although the pixel's ray (the unique inverse the renderer uses) points elsewhere: not seen.
            cam_pts = xyz[ok] @ R.T + t
            if camera.lens == "fisheye":
                rays = unproject(px[ok], camera)
                same = np.all(np.abs(rays - cam_pts / np.linalg.norm(cam_pts, axis=1, keepdims=True)) < 1e-7, axis=1)
            else:
                rays = pixel_rays(camera, px[ok])
                same = np.all(np.abs(rays[:, :2] - cam_pts[:, :2] / cam_pts[:, 2:3]) < 1e-7, axis=1)
            ok[np.flatnonzero(ok)[~same]] = False
        inside = ((px[:, 0] >= border_px - 0.5) & (px[:, 0] <= w - 0.5 - border_px)
                  & (px[:, 1] >= border_px - 0.5) & (px[:, 1] <= h - 0.5 - border_px))
        ok &= inside
        if not ok.any():
            continue
        out.append({
            "board": board_index,
            "name": p.name,
            "cols": b.cols,
            "rows": b.rows,
            "ids": ids[ok].tolist(),
            "corners": px[ok].tolist(),
            "xyz_mm": xyz[ok].tolist(),
            "n_total": int(b.n_corners),
            "n_visible": int(ok.sum()),
            "complete": bool(ok.all()),
        })
    return out


def target_json(panels: list[Panel], frame: str = "world", name: str | None = None) -> dict:
    """The ``target`` section: every printed panel of the scene, in the world (or target) frame."""
    boards = []
    for p in panels:
        if p.board is None:
            continue
        boards.append({
            "name": p.name,
            "cols": p.board.cols,
            "rows": p.board.rows,
            "square_mm": float(p.board.square_mm),
            "origin_mm": [float(v) for v in p.origin_mm],
            "x_axis": [float(v) for v in p.x_axis],
            "y_axis": [float(v) for v in p.y_axis],
            "panel_extent_mm": [float(v) for v in p.extent_mm],
            "first_square": "black",
            "black_albedo": float(p.black_albedo),
            "white_albedo": float(p.white_albedo),
        })
    out: dict = {"frame": frame, "boards": boards}
    if name:
        out["name"] = name
    return out


def panels_from_json(target: dict) -> list[Panel]:
    """The printed panels of a truth file's ``target`` section, to render the same scene again."""
    from edgecal.targets import Board

    out = []
    for b in target.get("boards", []):
        board = Board(str(b["name"]), int(b["cols"]), int(b["rows"]), float(b["square_mm"]))
        umin, vmin, umax, vmax = (float(v) for v in b["panel_extent_mm"])
        out.append(Panel(board.name, np.array(b["origin_mm"], dtype=np.float64),
                         np.array(b["x_axis"], dtype=np.float64), np.array(b["y_axis"], dtype=np.float64),
                         (umin, vmin, umax, vmax), board,
                         float(b.get("black_albedo", 0.06)), float(b.get("white_albedo", 0.85))))
    return out


# ----------------------------------------------------------------------------------------------------
# Reading truth back


@dataclass(frozen=True)
class TruthBoard:
    """One board's true (or reference) corners: ``ids`` (N, 2) int (col, row), ``corners`` (N, 2) px."""

    name: str
    cols: int
    rows: int
    ids: np.ndarray
    corners: np.ndarray

    @property
    def complete(self) -> bool:
        """True when all cols x rows corners are listed (visible)."""
        return len(self.ids) == self.cols * self.rows


@dataclass(frozen=True)
class GroundTruth:
    """Truth for one image: its boards (possibly none), and whether the corners are exact.

    ``exact`` is False for reference corners taken from another tool (real photographs): they may hold
    a few off-corner points, so a board counts as found when ``min_fraction`` of its corners agree.
    """

    image: str
    size: tuple[int, int]
    boards: tuple[TruthBoard, ...]
    exact: bool = True
    source: str = ""


def read_truth_json(path: Path) -> object:
    """The parsed JSON of a truth (or reference corner) file; InputError when missing or not JSON."""
    if not path.is_file():
        raise InputError(f"{path}: ground-truth file not found")
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"{path}: not readable JSON ({exc})") from None


def xy_pairs(value: object, where: str) -> np.ndarray:
    """A list of [a, b] pairs as an (N, 2) float array; InputError naming ``where`` otherwise."""
    arr = np.asarray(value, dtype=np.float64)
    if arr.size == 0:
        return np.zeros((0, 2))
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise InputError(f"{where}: expected a list of [a, b] pairs")
    return arr


def ground_truth_from_mapping(data: object, source: str) -> GroundTruth:
    """Build a GroundTruth from a parsed "edgecal-synth-gt/1" mapping; ``source`` names it in messages."""
    if not isinstance(data, dict):
        raise InputError(f"{source}: the top level must be a JSON object")
    fmt = data.get("format")
    if fmt != GT_FORMAT:
        raise InputError(f"{source}: field 'format' is {quote(fmt)}, expected {GT_FORMAT!r}")
    try:
        w, h = (int(v) for v in data["size"])
    except (KeyError, TypeError, ValueError):
        raise InputError(f"{source}: field 'size' must be [width, height]") from None
    raw_boards = data.get("boards")
    if not isinstance(raw_boards, list):
        raise InputError(f"{source}: field 'boards' must be a list")
    boards = []
    for i, b in enumerate(raw_boards):
        where = f"{source}: field 'boards[{i}]"
        if not isinstance(b, dict):
            raise InputError(f"{where}' must be an object")
        for key in ("cols", "rows", "ids", "corners"):
            if key not in b:
                raise InputError(f"{where}.{key}' is missing")
        ids = xy_pairs(b["ids"], f"{where}.ids'").astype(np.int64)
        xy = xy_pairs(b["corners"], f"{where}.corners'")
        if len(ids) != len(xy):
            raise InputError(f"{where}': {len(ids)} ids but {len(xy)} corners")
        boards.append(TruthBoard(str(b.get("name", f"board{i}")), int(b["cols"]), int(b["rows"]), ids, xy))
    image = str(data.get("image", ""))
    return GroundTruth(image, (w, h), tuple(boards), True, source)


def load_ground_truth(path: str | Path) -> GroundTruth:
    """Load a renderer ground-truth JSON file ("edgecal-synth-gt/1"); InputError naming the file/field."""
    p = Path(path)
    return ground_truth_from_mapping(read_truth_json(p), str(p))


def truth_targets(path: str | Path) -> list[dict]:
    """The ``target.boards`` list of a ground-truth JSON (all boards in the scene, with 3-D placement)."""
    p = Path(path)
    data = read_truth_json(p)
    boards = data.get("target", {}).get("boards", []) if isinstance(data, dict) else []
    if not isinstance(boards, list):
        raise InputError(f"{p}: field 'target.boards' must be a list")
    return boards
