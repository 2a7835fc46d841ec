"""The data that the calibration modules pass around: rigid transforms, matched corners, results.

Cameras are edgecal.camera.CameraModel.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from edgecal.camera import CameraModel
from edgecal.geometry import look_at

CAMERA_NAMES = ("left", "right")


@dataclass
class RigidTransform:
    """A rigid transform ``T_a_b`` as an OpenCV rotation vector and a translation (mm): a board's pose in a
    camera or one camera's in another (the robot pose is edgecal.pose.Pose)."""

    rvec: np.ndarray
    tvec: np.ndarray

    @staticmethod
    def from_rt(rotation: np.ndarray, translation: np.ndarray) -> RigidTransform:
        """From a 3x3 rotation matrix and a translation."""
        return RigidTransform(cv2.Rodrigues(np.asarray(rotation, dtype=np.float64))[0].ravel(),
                              np.asarray(translation, dtype=np.float64).ravel().copy())

    @staticmethod
    def looking_at(eye_mm: np.ndarray, centre_mm: np.ndarray, up: np.ndarray | None = None) -> RigidTransform:
        """T_cam_target of a camera at ``eye_mm`` looking at ``centre_mm`` with image-up along ``up`` (default +z;
        edgecal.geometry.look_at)."""
        return RigidTransform.from_rt(*(look_at(eye_mm, centre_mm) if up is None else look_at(eye_mm, centre_mm, up)))

    @property
    def rotation(self) -> np.ndarray:
        """The 3x3 rotation matrix."""
        return cv2.Rodrigues(np.asarray(self.rvec, dtype=np.float64).reshape(3, 1))[0]

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Map (N, 3) points from frame b to frame a."""
        return np.asarray(points, dtype=np.float64).reshape(-1, 3) @ self.rotation.T + np.ravel(self.tvec)


@dataclass(frozen=True)
class CornerSet:
    """Corners matched to the target in one image: 3-D target points (mm), pixels and their keys.

    ``keys[i]`` is (board name, col, row): the same key in two images is the same physical corner.
    """

    object_mm: np.ndarray   # (N, 3)
    image_px: np.ndarray    # (N, 2)
    keys: tuple[tuple[str, int, int], ...]
    image_cov_px2: np.ndarray | None = None   # (N, 2, 2) the detector's covariances less the light's shift, if known

    def __len__(self) -> int:
        return len(self.keys)

    def take(self, index: list[int] | np.ndarray) -> CornerSet:
        """The corners at ``index``, covariances included."""
        idx = np.asarray(index, dtype=np.int64)
        cov = None if self.image_cov_px2 is None else self.image_cov_px2[idx]
        return CornerSet(self.object_mm[idx], self.image_px[idx], tuple(self.keys[i] for i in idx), cov)

    def labels(self, camera: str, view: int | str | None = None) -> tuple[str, ...]:
        """Human-readable corner names for reports, e.g. ``left left03.jpg board top (3,1)``.

        ``view`` is the view's file name (or a number when there is none).
        """
        where = camera if view is None else f"{camera} view {view}" if isinstance(view, int) else f"{camera} {view}"
        return tuple(f"{where} board {b} ({c},{r})" for b, c, r in self.keys)


@dataclass(frozen=True)
class Reconstruction:
    """3-D reconstruction error of triangulated corners against their known positions (the paper's Table 2)."""

    mean_mm: float
    std_mm: float
    max_mm: float
    count: int
    per_board_mm: dict[str, float]   # mean error per board
    errors_mm: np.ndarray            # (count,)


@dataclass(frozen=True)
class Rectification:
    """cv2.stereoRectify output (R1, R2, P1, P2, Q) and the rectified epipolar error of the corners."""

    r1: np.ndarray
    r2: np.ndarray
    p1: np.ndarray
    p2: np.ndarray
    q: np.ndarray
    epipolar_rms_px: float
    epipolar_max_px: float


@dataclass
class Calibration:
    """The result of any calibration: one or two cameras, their uncertainty and the evidence.

    ``kind`` is box-stereo, box-mono, planar-stereo or planar-mono. Camera 0 is the left (or only)
    camera. ``rotation``/``translation_mm`` map left-camera points to the right camera
    (X_right = R X_left + T). Per-parameter standard deviations are 1-sigma, from the Jacobian.
    """

    kind: str
    image_size: tuple[int, int]
    cameras: list[CameraModel]                  # image_size set
    camera_std: list[dict[str, float]]          # per camera: CameraModel.intrinsic_names -> std (nan = fixed)
    view_poses: list[RigidTransform]            # T_cam0_target per view
    corners: list[list[CornerSet]]              # [camera][view]
    residuals_px: list[list[np.ndarray]]        # [camera][view] (N, 2) reprojected - detected
    inliers: list[list[np.ndarray]]             # [camera][view] (N,) bool
    rms_px: float
    sigma_px: float
    rotation: np.ndarray | None = None
    translation_mm: np.ndarray | None = None
    rotation_std_rad: np.ndarray | None = None  # std of the rotation vector of R
    translation_std_mm: np.ndarray | None = None
    reconstruction: Reconstruction | None = None
    rectification: Rectification | None = None
    dropped: list[str] = field(default_factory=list)
    undetermined: list[str] = field(default_factory=list)  # "camera k4": parameters the corners cannot fix
    notes: list[str] = field(default_factory=list)
    init: dict[str, dict[str, float]] = field(default_factory=dict)  # camera -> method -> RMS after refinement
    view_index: list[int] = field(default_factory=list)  # input image (pair) of each view, planar case
    skipped_views: dict[int, str] = field(default_factory=dict)  # input view -> why it was not used
    view_pose_std: list[np.ndarray] = field(default_factory=list)  # per view: std of rx ry rz (rad), tx ty tz (mm)
    noise_floor_px: float = 0.0   # weighted: sigma per axis the fit added to every corner's covariance

    @property
    def is_stereo(self) -> bool:
        """Whether there is a second camera."""
        return len(self.cameras) == 2

    @property
    def camera_names(self) -> tuple[str, ...]:
        """"left", "right" for stereo; "camera" for one camera."""
        return CAMERA_NAMES if self.is_stereo else ("camera",)

    def per_board_rms_px(self) -> dict[str, float]:
        """Reprojection RMS per "camera/board" over the inlier corners."""
        acc: dict[str, list[float]] = {}
        for c, name in enumerate(self.camera_names):
            for cs, res, inl in zip(self.corners[c], self.residuals_px[c], self.inliers[c]):
                for (board, _, _), r, ok in zip(cs.keys, res, inl):
                    if ok:
                        acc.setdefault(f"{name}/{board}", []).append(float(r @ r))
        return {k: float(np.sqrt(np.mean(v))) for k, v in sorted(acc.items())}
