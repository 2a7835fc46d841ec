"""What the pose estimator takes and returns besides the rig (edgecal.camera.StereoRig): settings and the pose."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from edgecal.config import setting


@dataclass(frozen=True)
class QualityBounds:
    """A pose outside any of these bounds is published as invalid, with the bound named in the reason."""

    min_corners: int = setting(8, doc="corners used by the fit (both cameras counted once each)", minimum=3)
    max_rms_px: float = setting(1.0, doc="reprojection RMS over all residuals", positive=True)
    max_position_std_mm: float = setting(5.0, doc="sqrt of the largest eigenvalue of the position covariance",
                                         positive=True)
    max_rotation_std_deg: float = setting(1.0, doc="the same for the rotation block", positive=True)


@dataclass(frozen=True)
class PoseSettings:
    """How the pose is computed.

    triangulation:    "linear" (DLT on undistorted points) or "optimal" (Hartley-Sturm correction of each
                      match first). Either only starts the refinement, which minimises the reprojection
                      error in both cameras and so reaches the same optimum; "optimal" costs ~15 ms per
                      80 corners in OpenCV, hence the default "linear".
    covariance_scale: how the 6x6 covariance is computed:
                      "model"    (default) from the detector's per-corner covariances (the weights of the
                                 refinement) plus the errors corners share: each board's, and an
                                 offset common to all (edgecal.pose.estimate.shared_error);
                      "residual" sigma^2 (J^T J)^-1 with the fit's own corner noise sigma^2 = SSR / (m - 6);
                      "noise"    the same with the configured ``corner_noise_px``;
                      "max"      the larger of the two (edgecal's default before the corner model).
    corner_noise_px:  1-sigma corner localisation noise of the detector, in pixels: the "noise" scale, and
                      the weight of a corner that comes without a covariance.
    outlier_sigmas,   a corner whose reprojection residual exceeds both ``outlier_sigmas`` robust sigmas
    outlier_min_px:   (from the median residual) and ``outlier_min_px`` is left out and the pose refitted:
                      one corner locked onto the wrong structure must not move the pose by millimetres.
                      The floor keeps a clean frame's tiny spread from rejecting good corners.
    """

    triangulation: str = setting("linear", doc="linear | optimal (Hartley-Sturm first)", choices=("optimal", "linear"))
    covariance_scale: str = setting("model", doc="model | max | residual | noise (see above)",
                                    choices=("model", "max", "residual", "noise"))
    corner_noise_px: float = setting(0.1, doc="1-sigma corner noise of the detector (px)", positive=True)
    outlier_sigmas: float = setting(4.0, doc="a corner beyond this many robust sigmas ...", minimum=2.0)
    outlier_min_px: float = setting(0.5, doc="... and beyond this is left out and the pose refitted (px)",
                                    positive=True)
    bounds: QualityBounds = setting(default_factory=QualityBounds, doc="quality bounds (in the same section)",
                                    inline=True)


@dataclass
class Pose:
    """T_rig_robot from one stereo frame.

    R, t_m:      rotation and translation (metres) mapping robot-frame points to the rig (left camera) frame.
    covariance:  6x6, order [x, y, z, rx, ry, rz] in metres and radians; the rotation part is a small
                 rotation about the rig's axes applied on the left (R_true = exp([d]x) R), as ROS does.
    mode:        "stereo", "mono-left", "mono-right" or "none".
    valid:       False when the pose failed a quality bound (or could not be computed); ``reason`` says why.
    """

    R: np.ndarray
    t_m: np.ndarray
    covariance: np.ndarray
    mode: str
    valid: bool
    reason: str = ""
    rms_px: float = float("nan")
    n_left: int = 0
    n_right: int = 0
    n_both: int = 0
    boards: tuple[str, ...] = ()
    rejected: tuple[str, ...] = ()        # "board (camera)" taken out of the fit as misfits
    outliers: int = 0                     # single corner observations left out of the fit
    edge_on: tuple[str, ...] = ()         # "board (camera)" left out as seen too close to edge-on

    @property
    def quaternion_xyzw(self) -> np.ndarray:
        """Unit quaternion (x, y, z, w) with w >= 0."""
        q = Rotation.from_matrix(self.R).as_quat()
        return -q if q[3] < 0 else q

    @property
    def n_corners(self) -> int:
        """Corner observations used by the fit (a corner seen by both cameras counts twice)."""
        return self.n_left + self.n_right

    @property
    def position_std_mm(self) -> float:
        """1-sigma position uncertainty along the worst direction, in millimetres."""
        return 1000.0 * float(np.sqrt(max(np.linalg.eigvalsh(self.covariance[:3, :3]).max(), 0.0)))

    @property
    def rotation_std_deg(self) -> float:
        """1-sigma rotation uncertainty about the worst axis, in degrees."""
        return float(np.degrees(np.sqrt(max(np.linalg.eigvalsh(self.covariance[3:, 3:]).max(), 0.0))))

    @staticmethod
    def invalid(reason: str, mode: str = "none", n_left: int = 0, n_right: int = 0, n_both: int = 0) -> Pose:
        """A pose that could not be computed at all."""
        return Pose(np.full((3, 3), np.nan), np.full(3, np.nan), np.full((6, 6), np.nan), mode, False, reason,
                    n_left=n_left, n_right=n_right, n_both=n_both)
