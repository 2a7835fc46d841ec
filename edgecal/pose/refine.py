"""Refinement of T_rig_robot by minimising the reprojection error in one or both cameras, and its covariance."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import least_squares

from edgecal.camera import CameraModel, project


@dataclass(frozen=True)
class CameraView:
    """The corners one camera saw: robot-frame points (N, 3, metres) and their pixels (N, 2).

    ``R_cam_rig``, ``t_cam_rig_m`` place the rig frame in this camera (identity and zero for the left
    camera, the rig's T_right_left for the right one).
    """

    camera: CameraModel
    R_cam_rig: np.ndarray
    t_cam_rig_m: np.ndarray
    object_points_m: np.ndarray
    image_points_px: np.ndarray

    @property
    def n(self) -> int:
        """Number of corners."""
        return len(self.object_points_m)


def _residuals_and_jacobian(x: np.ndarray, views: list[CameraView]) -> tuple[np.ndarray, np.ndarray]:
    """Stacked residuals (projected - observed, px) and their Jacobian w.r.t. x = (rvec, t) of T_rig_robot."""
    res, jac = [], []
    R, dR = cv2.Rodrigues(x[:3].reshape(3, 1))   # dR: (3, 9), row k = dR/drvec_k (row-major)
    dR = dR.reshape(3, 3, 3)
    for v in views:
        if v.n == 0:
            continue
        X = v.object_points_m
        p_rig = X @ R.T + x[3:]
        p_cam = p_rig @ v.R_cam_rig.T + v.t_cam_rig_m
        q, dq_dp, _ = project(p_cam, v.camera, get_gradients=True)
        res.append((q - v.image_points_px).ravel())
        dq_drig = dq_dp @ v.R_cam_rig                                   # (N, 2, 3)
        dp_drvec = np.einsum("kij,nj->nik", dR, X)                      # d(R X)/d rvec: (N, 3, 3)
        jac.append(np.concatenate([dq_drig @ dp_drvec, dq_drig], axis=2).reshape(-1, 6))
    return np.concatenate(res), np.vstack(jac)


def refine_pose(R0: np.ndarray, t0: np.ndarray, views: list[CameraView],
                max_iterations: int = 50) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Levenberg-Marquardt refinement from (R0, t0); returns R, t, residuals (px) and the Jacobian.

    The Jacobian is with respect to the perturbation [dt (m), dtheta (rad)] with R = exp([dtheta]x) R_hat,
    t = t_hat + dt, i.e. the parameter order and meaning of the published covariance.
    """
    rvec0, _ = cv2.Rodrigues(np.asarray(R0, dtype=np.float64))
    x0 = np.concatenate([rvec0.ravel(), np.asarray(t0, dtype=np.float64).ravel()])
    cache: dict = {}

    def evaluate(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        key = x.tobytes()
        if key not in cache:
            cache.clear()
            cache[key] = _residuals_and_jacobian(x, views)
        return cache[key]

    sol = least_squares(lambda x: evaluate(x)[0], x0, jac=lambda x: evaluate(x)[1], method="lm",
                        max_nfev=max_iterations, xtol=1e-12, ftol=1e-12, gtol=1e-12)
    x = sol.x
    r, J = evaluate(x)
    R, _ = cv2.Rodrigues(x[:3].reshape(3, 1))
    # d rvec / d dtheta for R = exp([dtheta]x) R_hat: composeRT(rvec_hat, 0, dtheta = 0, 0) gives it.
    _, _, _, _, dr3dr2, *_ = cv2.composeRT(x[:3].reshape(3, 1), np.zeros((3, 1)), np.zeros((3, 1)),
                                           np.zeros((3, 1)))
    J_pert = np.hstack([J[:, 3:6], J[:, :3] @ dr3dr2])
    return R, x[3:].copy(), r, J_pert


def pose_covariance(J: np.ndarray, residuals: np.ndarray, scale: str, corner_noise_px: float) -> np.ndarray:
    """6x6 covariance sigma^2 (J^T J)^-1 of the perturbation [dt, dtheta]; ``scale`` picks sigma.

    "residual": sigma^2 = SSR / (m - 6) (the spread the fit itself shows); "noise": the configured
    corner noise; "max": the larger of the two. A singular J^T J gives an infinite covariance.
    """
    m = len(residuals)
    sigma2_res = float(residuals @ residuals) / max(m - 6, 1)
    sigma2_cfg = float(corner_noise_px) ** 2
    sigma2 = {"residual": sigma2_res, "noise": sigma2_cfg}.get(scale, max(sigma2_res, sigma2_cfg))
    JtJ = J.T @ J
    if m < 6 or np.linalg.cond(JtJ) > 1e14:
        return np.full((6, 6), np.inf)
    cov = sigma2 * np.linalg.inv(JtJ)
    return 0.5 * (cov + cov.T)
