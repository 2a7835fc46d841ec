"""The robot sequence: a fixed stereo rig at 30 fps watching a robot that carries three boards
(configs/targets/robot-3boards.yaml), with the true T_rig_robot of every frame."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from edgecal.camera import CameraModel
from edgecal.config import packaged_config_path
from edgecal.geometry import look_at, rotation_about
from edgecal.synth.camera import camera_json, stereo_right_pose
from edgecal.synth.clutter import clutter_background
from edgecal.synth.panels import Panel, panels_from_target
from edgecal.synth.photometric import Photometric
from edgecal.synth.scenes.common import SeedLike, random_camera, scene_photometric, scene_rng, seed_list
from edgecal.synth.view import RenderedView, render_view
from edgecal.targets import Target, load_target

ROBOT_BODY_MM = (400.0, 300.0, 250.0)  # x, y, z extent of the block carrying the boards


def robot_target() -> Target:
    """The three boards on the robot body (configs/targets/robot-3boards.yaml)."""
    return load_target(packaged_config_path("targets/robot-3boards.yaml"))


def _body_panels(R_world_robot: np.ndarray, t_world_robot: np.ndarray, albedo: float) -> list[Panel]:
    """The six faces of the robot body, 0.5 mm inside the faces the boards are glued to."""
    lx, ly, lz = (v / 2.0 for v in ROBOT_BODY_MM)
    e = 0.5
    faces = [  # (centre in robot frame, x_axis, y_axis, half sizes)
        ((lx - e, 0, lz), (0, 1, 0), (0, 0, 1), (ly, lz)), ((-lx + e, 0, lz), (0, 1, 0), (0, 0, 1), (ly, lz)),
        ((0, ly - e, lz), (1, 0, 0), (0, 0, 1), (lx, lz)), ((0, -ly + e, lz), (1, 0, 0), (0, 0, 1), (lx, lz)),
        ((0, 0, 2 * lz - e), (1, 0, 0), (0, 1, 0), (lx, ly)), ((0, 0, e), (1, 0, 0), (0, 1, 0), (lx, ly)),
    ]
    out = []
    for k, (c, xa, ya, (hu, hv)) in enumerate(faces):
        out.append(Panel(f"body{k}", R_world_robot @ np.array(c, float) + t_world_robot,
                         R_world_robot @ np.array(xa, float), R_world_robot @ np.array(ya, float),
                         (-hu, -hv, hu, hv), None, 0.0, albedo, albedo))
    return out


@dataclass
class RobotFrame:
    """One frame of the robot sequence: the stereo views and the true robot pose in the rig (left camera)."""

    index: int
    stamp_ns: int
    left: RenderedView
    right: RenderedView
    R_rig_robot: np.ndarray
    t_rig_robot_mm: np.ndarray


@dataclass
class RobotRig:
    """The fixed stereo rig of a robot sequence (left camera = rig frame)."""

    left: CameraModel
    right: CameraModel
    R_left_world: np.ndarray
    t_left_world_mm: np.ndarray
    R_right_left: np.ndarray
    T_right_left_mm: np.ndarray

    def as_json(self) -> dict:
        """Rig truth: both cameras (poses in the world/floor frame) and the stereo extrinsics."""
        R_r, t_r = stereo_right_pose(self.R_left_world, self.t_left_world_mm, self.R_right_left, self.T_right_left_mm)
        return {"left": camera_json(self.left, "left", self.R_left_world, self.t_left_world_mm),
                "right": camera_json(self.right, "right", R_r, t_r),
                "R_right_left": self.R_right_left.tolist(), "T_right_left_mm": self.T_right_left_mm.tolist(),
                "baseline_mm": float(np.linalg.norm(self.T_right_left_mm)),
                "convention": "X_right = R_right_left @ X_left + T_right_left_mm (camera frames, mm)"}


# Field of view of the robot rig's cameras per lens model: a ~70 deg pinhole, or a 110-120 deg fisheye whose
# squares at the robot are still ~0.6 of the pinhole's (both rigs then meet the same pose accuracy).
ROBOT_HFOV_DEG = {"radtan": (68.0, 72.0), "fisheye": (110.0, 120.0), "rational": (85.0, 95.0)}


def robot_rig(seed: SeedLike, size: tuple[int, int] = (1280, 800), baseline_mm: float = 75.0,
              lens: str = "radtan") -> RobotRig:
    """The rig of :func:`robot_sequence`: 0.8 m from the robot's area, 0.65 m up, looking down at it (~0.95 m).

    ``lens``: radtan (mild distortion), fisheye or rational (random_camera's lens models)."""
    rng = scene_rng(seed, "robot-rig")
    level = "mild" if lens == "radtan" else lens
    left = random_camera(rng, size, hfov_deg=ROBOT_HFOV_DEG[lens], distortion=level)
    right = random_camera(rng, size, hfov_deg=ROBOT_HFOV_DEG[lens], distortion=level)
    R_l, t_l = look_at(np.array([-800.0, 0.0, 650.0]), np.array([0.0, 0.0, 150.0]), up=np.array([0.0, 0.0, 1.0]))
    R_rl = rotation_about(rng.normal(size=3), np.radians(rng.uniform(0.1, 0.5)))
    T_rl = -R_rl @ np.array([baseline_mm, 0.0, 0.0]) + rng.normal(0, 0.3, size=3)
    return RobotRig(left, right, R_l, t_l, R_rl, T_rl)


def robot_pose_world(time_s: float, phase: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """T_world_robot at ``time_s``: a smooth wander on the floor, turning to show front, left and top."""
    a, b, c, d, e = phase
    x = 120.0 * np.sin(2 * np.pi * time_s / 8.0 + a)
    y = 180.0 * np.sin(2 * np.pi * time_s / 11.0 + b)
    # Yaw swings around 45 deg off the rig axis, so the front and the left face both stay in view.
    yaw = np.pi - 0.78 + 0.3 * np.sin(2 * np.pi * time_s / 9.0 + c)
    pitch = np.radians(2.5) * np.sin(2 * np.pi * time_s / 3.0 + d)
    roll = np.radians(2.0) * np.sin(2 * np.pi * time_s / 4.0 + e)
    R = (rotation_about(np.array([0, 0, 1.0]), yaw) @ rotation_about(np.array([0, 1.0, 0]), pitch)
         @ rotation_about(np.array([1.0, 0, 0]), roll))
    return R, np.array([x, y, 5.0 * np.sin(2 * np.pi * time_s / 2.0 + a)])


def robot_sequence(seed: SeedLike, n_frames: int | None = None, *, fps: float = 30.0,
                   size: tuple[int, int] = (1280, 800), photometric: Photometric | str = "clean",
                   supersampling: int = 8, border_px: float = 4.0, exposure_ms: float = 0.0,
                   exposure_samples: int = 5, lens: str = "radtan") -> Iterator[RobotFrame]:
    """Frames of a stereo rig watching the robot (endless when ``n_frames`` is None; nothing is kept).

    The room (clutter, rig, lighting) is fixed for the whole sequence; the robot moves smoothly at
    about 1 m from the rig and each frame gets fresh sensor noise. T_rig_robot = T_rig_world T_world_robot.
    ``exposure_ms`` > 0 blurs the motion: each image averages ``exposure_samples`` instants of the
    exposure, and the truth (stamp_ns, T_rig_robot, corners) is the mid-exposure one.
    """
    rng = scene_rng(seed, "robot")
    rig = robot_rig(seed, size, lens=lens)
    tgt = robot_target()
    phase = rng.uniform(0, 2 * np.pi, size=5)
    bg_l, _ = clutter_background(rng, size, distractors=["text", "dots"])
    bg_r, _ = clutter_background(rng, size, distractors=["text", "dots"])
    phot = scene_photometric(rng, photometric)
    body_albedo = float(rng.uniform(0.25, 0.45))
    R_r, t_r = stereo_right_pose(rig.R_left_world, rig.t_left_world_mm, rig.R_right_left, rig.T_right_left_mm)
    rig_json = rig.as_json()
    k = 0
    while n_frames is None or k < n_frames:
        time_s = k / fps
        R_wr, t_wr = robot_pose_world(time_s, phase)

        def scene(R_wr: np.ndarray, t_wr: np.ndarray) -> list[Panel]:
            """The robot's boards and body at pose T_world_robot."""
            return (panels_from_target(tgt, R_wr, t_wr, margin_mm=10.0, black_albedo=0.06, white_albedo=0.85)
                    + _body_panels(R_wr, t_wr, body_albedo))

        panels = scene(R_wr, t_wr)
        exposure = None
        if exposure_ms > 0:
            offsets = (np.linspace(-0.5, 0.5, max(2, exposure_samples))) * exposure_ms * 1e-3
            exposure = [scene(*robot_pose_world(time_s + dt, phase)) for dt in offsets]
        extra = {"category": "robot", "seed": seed_list(seed) + ["robot"], "frame": k, "exposure_ms": exposure_ms}
        noise = np.random.default_rng(seed_list(seed) + [k])
        left = render_view(rig.left, panels, rig.R_left_world, rig.t_left_world_mm, background=bg_l, photometric=phot,
                           rng=noise, supersampling=supersampling, border_px=border_px, target_frame="world",
                           target_name=tgt.name, extra={**extra, "stereo_side": "left"}, exposure=exposure,
                           camera_name="left")
        right = render_view(rig.right, panels, R_r, t_r, background=bg_r, photometric=phot, rng=noise,
                            supersampling=supersampling, border_px=border_px, target_frame="world",
                            target_name=tgt.name, extra={**extra, "stereo_side": "right"}, exposure=exposure,
                            camera_name="right")
        R_rig_robot = rig.R_left_world @ R_wr
        t_rig_robot = rig.R_left_world @ t_wr + rig.t_left_world_mm
        for view in (left, right):
            view.truth["rig"] = rig_json
            view.truth["R_rig_robot"] = R_rig_robot.tolist()
            view.truth["t_rig_robot_mm"] = t_rig_robot.tolist()
        yield RobotFrame(k, int(round(k * 1e9 / fps)), left, right, R_rig_robot, t_rig_robot)
        k += 1
