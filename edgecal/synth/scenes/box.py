"""The calibration box (configs/targets/box-100mm.yaml) seen by a stereo pair, with the pair's truth."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from edgecal.config import packaged_config_path
from edgecal.geometry import look_at, rotation_about
from edgecal.synth.camera import camera_json, stereo_right_pose
from edgecal.synth.panels import board_panel_extent, panels_from_target
from edgecal.synth.photometric import Photometric
from edgecal.synth.scenes.common import (
    FloatOrRange,
    SeedLike,
    pick,
    random_camera,
    scene_background,
    scene_photometric,
    scene_rng,
    seed_list,
)
from edgecal.synth.truth import PAIR_FORMAT, target_json
from edgecal.synth.view import RenderedView, render_view
from edgecal.targets import Target, load_target

if TYPE_CHECKING:
    from edgecal.synth.scenes.robot import RobotRig


@dataclass
class StereoView:
    """A stereo pair of views of one scene and the pair truth (cameras, R_right_left, T_right_left_mm)."""

    left: RenderedView
    right: RenderedView
    pair: dict


def box_target() -> Target:
    """The calibration box of configs/targets/box-100mm.yaml."""
    return load_target(packaged_config_path("targets/box-100mm.yaml"))


def _box_face_extents(target: Target, cube_mm: float) -> dict[str, tuple[float, float, float, float]]:
    """Each board's panel = the whole cube face it lies on (in board coordinates)."""
    verts = np.array([[x, y, z] for x in (0, cube_mm) for y in (0, cube_mm) for z in (0, cube_mm)], dtype=float)
    out = {}
    for b in target.boards:
        d = verts - b.origin_mm
        on = np.abs(d @ b.normal) < 1e-6
        if on.sum() < 4:
            out[b.name] = board_panel_extent(b)
            continue
        u, v = d[on] @ b.x_axis, d[on] @ b.y_axis
        out[b.name] = (float(u.min()), float(v.min()), float(u.max()), float(v.max()))
    return out


def box_stereo(seed: SeedLike, *, size: tuple[int, int] = (1280, 800), distance_mm: FloatOrRange = (250.0, 350.0),
               baseline_mm: float = 70.0, photometric: Photometric | str = "normal", background: str = "clutter",
               target: Target | None = None, cube_mm: float = 100.0, supersampling: int = 12,
               border_px: float = 4.0, rig: RobotRig | None = None) -> StereoView:
    """The calibration box seen by a (nearly parallel) stereo rig; world frame = box frame.

    The rig looks at the box centre from the octant where all three printed faces are visible, with a
    random roll; the right camera sits ``baseline_mm`` along the left camera's x axis, slightly rotated.
    ``rig`` (e.g. :func:`robot_rig`) replaces the random cameras and extrinsics by its own, so the box
    calibrates the rig that a robot sequence uses.
    """
    rng = scene_rng(seed, "box")
    tgt = target or box_target()
    left_cam = random_camera(rng, size, hfov_deg=(55.0, 65.0))
    right_cam = random_camera(rng, size, hfov_deg=(55.0, 65.0))
    if rig is not None:
        left_cam, right_cam = rig.left, rig.right
        baseline_mm = float(np.linalg.norm(rig.T_right_left_mm))
    centre = np.full(3, cube_mm / 2.0)
    direction = -rng.uniform(0.7, 1.0, size=3)
    direction /= np.linalg.norm(direction)
    dist = pick(rng, distance_mm)
    rig_eye = centre + dist * direction
    R0, _ = look_at(rig_eye, centre, up=np.array([0.0, 0.0, -1.0]))
    R_roll = rotation_about(np.array([0, 0, 1.0]), np.radians(rng.uniform(-15, 15)))
    R_left = R_roll @ R0
    # Parallel rig centred on the box: the left eye sits half a baseline to the left of the rig's axis.
    left_eye = rig_eye - R_left[0] * baseline_mm / 2.0
    t_left = -R_left @ left_eye
    R_rl = rotation_about(rng.normal(size=3), np.radians(rng.uniform(0.3, 1.5)))
    T_rl = -R_rl @ np.array([baseline_mm, 0.0, 0.0]) + rng.normal(0, 1.0, size=3)
    if rig is not None:
        R_rl, T_rl = np.asarray(rig.R_right_left, dtype=np.float64), np.asarray(rig.T_right_left_mm, dtype=np.float64)
    R_right, t_right = stereo_right_pose(R_left, t_left, R_rl, T_rl)
    white = float(rng.uniform(0.75, 0.92))
    black = float(rng.uniform(0.03, 0.12))
    panels = panels_from_target(tgt, extents=_box_face_extents(tgt, cube_mm), black_albedo=black, white_albedo=white)
    bg_l, distractors_l = scene_background(rng, size, background)
    bg_r, distractors_r = scene_background(rng, size, background)
    phot = scene_photometric(rng, photometric)
    common = {"category": "box_stereo", "seed": seed_list(seed) + ["box"]}
    left = render_view(left_cam, panels, R_left, t_left, background=bg_l, photometric=phot, rng=rng,
                       supersampling=supersampling, border_px=border_px, target_frame="box", target_name=tgt.name,
                       extra={**common, "stereo_side": "left", "distractors": distractors_l}, camera_name="left")
    right = render_view(right_cam, panels, R_right, t_right, background=bg_r, photometric=phot, rng=rng,
                        supersampling=supersampling, border_px=border_px, target_frame="box",
                        target_name=tgt.name, extra={**common, "stereo_side": "right", "distractors": distractors_r},
                        camera_name="right")
    pair = {
        "format": PAIR_FORMAT,
        "units": {"length": "mm"},
        "convention": "X_right = R_right_left @ X_left + T_right_left_mm (camera frames, mm)",
        "left": camera_json(left_cam, "left", R_left, t_left),
        "right": camera_json(right_cam, "right", R_right, t_right),
        "R_right_left": R_rl.tolist(),
        "T_right_left_mm": T_rl.tolist(),
        "baseline_mm": float(np.linalg.norm(T_rl)),
        "distance_mm": float(np.linalg.norm(centre - left_eye)),
        "target": target_json(panels, "box", tgt.name),
        "seed": seed_list(seed) + ["box"],
    }
    return StereoView(left, right, pair)
