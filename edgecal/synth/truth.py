"""Ground truth of a rendered view in the "edgecal-synth-gt/1" JSON format.

The format is the one of ../shared/data/synthetic/README.md, so one scoring code reads the shared sets
and edgecal's own renders. Corner pixels come from edgecal.camera.project (equal to cv2.projectPoints and
cv2.fisheye.projectPoints, the reference definitions, to 1e-6 px; tests/test_camera.py); a corner is listed only when its printed side faces the camera, no other panel is in
front of it (nor of the board within 0.3 squares around it) and it lies at least ``border_px`` inside
the image.
"""

from __future__ import annotations

import numpy as np

from edgecal.camera import CameraModel, unproject
from edgecal.synth.camera import pixel_rays, project_world
from edgecal.synth.render import Panel, visible_mask

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
        out.append(Panel(board.name, np.array(b["origin_mm"], dtype=np.float64), np.array(b["x_axis"], dtype=np.float64),
                         np.array(b["y_axis"], dtype=np.float64), tuple(float(v) for v in b["panel_extent_mm"]), board,
                         float(b.get("black_albedo", 0.06)), float(b.get("white_albedo", 0.85))))
    return out
