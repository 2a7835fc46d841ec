"""Exact corner projections of a target with known cameras and poses (plus Gaussian noise), no image.

The truth that the calibration geometry is developed and tested against without a detector or the
renderer (edgecal.synth.scenes renders images of the same kind of scene). Poses are
edgecal.calibration.types.RigidTransform (``RigidTransform.looking_at`` places a camera).
"""

from __future__ import annotations

import numpy as np

from edgecal.calibration.types import CornerSet, RigidTransform
from edgecal.camera import CameraModel
from edgecal.synth.camera import project_world
from edgecal.targets import Board, Target


def cube_box_target(size_mm: float = 100.0, inner_corners: tuple[int, int] = (4, 5), square_mm: float = 16.0,
               name: str = "box-sim") -> Target:
    """A cube [0, size]^3 with one centred board on each of its top (z = size), front (y = 0) and right
    (x = size) faces; each board's normal points into the box (the camera sees it from outside).

    Sizes are free (a small problem keeps a test fast); the packaged box of configs/targets/box-100mm.yaml
    is edgecal.synth.scenes.box_target.
    """
    cols, rows = inner_corners
    w, h = (cols - 1) * square_mm, (rows - 1) * square_mm
    m_w, m_h = (size_mm - w) / 2, (size_mm - h) / 2
    s = size_mm
    boards = (
        # top: x along +x, y along -y -> normal -z (into the box)
        Board("top", cols, rows, square_mm, np.array([m_w, s - m_h, s]), np.array([1.0, 0, 0]), np.array([0, -1.0, 0])),
        # front (y = 0): x along +x, y along -z -> normal +y
        Board("front", cols, rows, square_mm, np.array([m_w, 0, s - m_h]), np.array([1.0, 0, 0]),
              np.array([0, 0, -1.0])),
        # right (x = size): x along +y, y along -z -> normal -x
        Board("right", cols, rows, square_mm, np.array([s, m_w, s - m_h]), np.array([0, 1.0, 0]),
              np.array([0, 0, -1.0])),
    )
    return Target(name, boards, source="simulated")


def project_target(target: Target, camera: CameraModel, pose: RigidTransform, image_size: tuple[int, int],
                   noise_px: float = 0.0, rng: np.random.Generator | None = None,
                   margin_px: float = 2.0) -> CornerSet:
    """The corners of every board facing the camera that fall inside the image, with Gaussian noise."""
    rng = rng or np.random.default_rng(0)
    centre_in_target = -pose.rotation.T @ np.ravel(pose.tvec)
    objs, imgs, keys = [], [], []
    for b in target.boards:
        pts = b.target_points_mm()
        if (centre_in_target - pts.mean(axis=0)) @ b.normal >= 0:
            continue  # the camera is behind this board
        px = project_world(camera, pts, pose.rotation, pose.tvec)
        inside = np.all(np.isfinite(px), axis=1) & ((px[:, 0] >= margin_px) & (px[:, 1] >= margin_px)
                  & (px[:, 0] <= image_size[0] - 1 - margin_px) & (px[:, 1] <= image_size[1] - 1 - margin_px))
        for (c, r), p3, p2, ok in zip(b.ids(), pts, px, inside):
            if ok:
                objs.append(p3)
                imgs.append(p2)
                keys.append((b.name, int(c), int(r)))
    img = np.array(imgs).reshape(-1, 2)
    if noise_px > 0 and len(img):
        img = img + rng.normal(0.0, noise_px, img.shape)
    return CornerSet(np.array(objs).reshape(-1, 3), img, tuple(keys))


def stereo_truth(distance_mm: float = 300.0, baseline_mm: float = 60.0, size_mm: float = 100.0,
                 focal_px: float = 800.0, image_size: tuple[int, int] = (640, 480),
                 dist: tuple[float, ...] = (-0.12, 0.08, 0.0, 0.0, 0.0)
                 ) -> tuple[CameraModel, CameraModel, RigidTransform, RigidTransform]:
    """A plausible stereo rig looking at the box of :func:`cube_box_target`: (left, right, T_left_box, T_right_left).

    The rig centre sits ``distance_mm`` from the box centre, looking down on its corner; the right camera
    is ``baseline_mm`` to the right, toed in towards the box.
    """
    c = np.full(3, size_mm / 2)
    direction = np.array([1.0, -1.3, 1.1])
    direction /= np.linalg.norm(direction)
    eye = c + distance_mm * direction
    side = RigidTransform.looking_at(eye, c).rotation[0]  # the rig's image-right direction: the right camera sits there
    left_pose = RigidTransform.looking_at(eye - side * baseline_mm / 2, c)
    right_pose = RigidTransform.looking_at(eye + side * baseline_mm / 2, c)
    r = right_pose.rotation @ left_pose.rotation.T
    rig = RigidTransform.from_rt(r, np.ravel(right_pose.tvec) - r @ np.ravel(left_pose.tvec))
    k_l = np.array([[focal_px, 0, image_size[0] / 2 + 4.0], [0, focal_px * 1.002, image_size[1] / 2 - 3.0], [0, 0, 1]])
    k_r = np.array([[focal_px * 1.01, 0, image_size[0] / 2 - 5.0], [0, focal_px * 1.011, image_size[1] / 2 + 2.0],
                    [0, 0, 1]])
    d = np.array(dist, dtype=float)
    return (CameraModel.from_opencv(k_l, d, image_size),
            CameraModel.from_opencv(k_r, d * np.array([1.05, 0.9, 1, 1, 1]), image_size), left_pose, rig)
