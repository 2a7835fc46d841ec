"""The pose tests' scene: a robot target, a stereo rig, a true pose and the exact detections of it."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from edgecal.camera import CameraModel, StereoRig, project
from edgecal.detection.types import Detection
from edgecal.targets import Board, Target


def robot_target() -> Target:
    """Three 6x5 boards on three faces of a robot body (like configs/targets/robot-3boards.yaml)."""
    return Target("robot", (
        Board("front", 6, 5, 20.0, np.array([-50.0, -40.0, -60.0]), np.array([1.0, 0, 0]), np.array([0, 1.0, 0])),
        Board("left", 6, 5, 20.0, np.array([-80.0, -40.0, 50.0]), np.array([0, 0, -1.0]), np.array([0, 1.0, 0])),
        Board("right", 6, 5, 20.0, np.array([80.0, -40.0, -50.0]), np.array([0, 0, 1.0]), np.array([0, 1.0, 0])),
    ))


def stereo_cams(distorted: bool | str = True) -> StereoRig:
    """A 1280x800 rig 12 cm wide; ``distorted`` True (radtan), False (none) or "fisheye" (a 160 deg lens)."""
    R = Rotation.from_euler("y", -4, degrees=True).as_matrix()
    T = np.array([-0.12, 0.001, 0.002])
    if distorted == "fisheye":
        f = 640 / np.radians(80.0)
        left = CameraModel(f, f, 640.0, 400.0, "fisheye", np.array([0.02, -0.01, 0.002, 0.0]), (1280, 800))
        right = CameraModel(f * 1.01, f * 1.01, 630.0, 405.0, "fisheye", np.array([0.018, -0.008, 0.001, 0.0]),
                            (1280, 800))
        return StereoRig(left, right, R, T)
    d1 = np.array([-0.12, 0.08, 0.001, -0.0005, 0.0]) if distorted else np.zeros(5)
    d2 = np.array([-0.10, 0.05, -0.001, 0.0005, 0.0]) if distorted else np.zeros(5)
    return StereoRig(CameraModel(1100.0, 1100.0, 640.0, 400.0, "radtan", d1, (1280, 800)),
                     CameraModel(1090.0, 1092.0, 630.0, 405.0, "radtan", d2, (1280, 800)), R, T)


def true_pose() -> tuple[np.ndarray, np.ndarray]:
    """A robot pose 1 m in front of the rig, turned on all three axes."""
    R = Rotation.from_euler("xyz", [20, 25, -10], degrees=True).as_matrix()
    return R, np.array([-0.05, 0.03, 1.0])


def render_detections(target: Target, cams: StereoRig, R: np.ndarray, t: np.ndarray, noise_px: float = 0.0,
                      rng: np.random.Generator | None = None) -> tuple[list[Detection], list[Detection]]:
    """Exact projections of every corner facing each camera (plus Gaussian noise) as Detections."""
    out: tuple[list[Detection], list[Detection]] = ([], [])
    for b in target.boards:
        X = b.target_points_mm() / 1000.0
        for side, cam in enumerate(cams.cameras):
            Rc = R if side == 0 else cams.R_right_left @ R
            tc = t if side == 0 else cams.R_right_left @ t + cams.t_right_left_m
            centre = Rc @ X.mean(axis=0) + tc
            if (Rc @ b.normal) @ centre >= 0:      # board faces away from this camera
                continue
            px = project(X @ Rc.T + tc, cam)
            if noise_px:
                px = px + rng.normal(0, noise_px, px.shape)
            out[side].append(Detection(b.name, px, b.ids(), np.ones(len(px)), (b.cols, b.rows)))
    return out


def rotation_error_rad(R_est: np.ndarray, R_true: np.ndarray) -> np.ndarray:
    """The estimate's rotation error d with R_est = exp([d]x) R_true (rad), the sign of t_est - t_true."""
    return Rotation.from_matrix(R_est @ R_true.T).as_rotvec()
