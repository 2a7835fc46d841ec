"""Refinement of T_rig_robot by minimising the reprojection error in one or both cameras, and its covariance."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numba import njit
from scipy.optimize import leastsq

from edgecal.camera import CameraModel, _radtan_distort_kernel, project


@dataclass(frozen=True)
class CameraView:
    """The corners one camera saw: robot-frame points (N, 3, metres) and their pixels (N, 2).

    ``R_cam_rig``, ``t_cam_rig_m`` place the rig frame in this camera (identity and zero for the left
    camera, the rig's T_right_left for the right one). ``image_covariance_px2`` (N, 2, 2) is each corner's
    covariance (the detector's); with it the refinement minimises the whitened residuals, without it
    every corner weighs the same. ``image_shared_px2`` (N,) is the part of each covariance (px^2 per axis)
    that the corners of its board share (Detection.shared_px2), ``image_light_gradient`` (N, 2) the
    gradient of log light there (Detection.light_gradient), ``image_alternating_px2`` (N,) its board's light
    shift in the checkerboard pattern of its corners (Detection.alternating_px2), which
    ``image_covariance_px2`` then leaves out (a fit barely sees it).
    """

    camera: CameraModel
    R_cam_rig: np.ndarray
    t_cam_rig_m: np.ndarray
    object_points_m: np.ndarray
    image_points_px: np.ndarray
    image_covariance_px2: np.ndarray | None = None
    image_shared_px2: np.ndarray | None = None
    image_light_gradient: np.ndarray | None = None
    image_alternating_px2: np.ndarray | None = None

    @property
    def n(self) -> int:
        """Number of corners."""
        return len(self.object_points_m)


def _residuals_and_jacobian(x: np.ndarray, views: list[CameraView]) -> tuple[np.ndarray, np.ndarray]:
    """Stacked residuals (projected - observed, px) and their Jacobian w.r.t. x = (rvec, t) of T_rig_robot."""
    R, dR = cv2.Rodrigues(x[:3].reshape(3, 1))   # dR: (3, 9), row k = dR/drvec_k (row-major)
    dR = dR.reshape(3, 3, 3)
    parts = [_view_terms(R, dR, x[3:], v) for v in views if v.n > 0]
    return np.concatenate([r for r, _ in parts]), np.vstack([J for _, J in parts])


def _view_terms(R: np.ndarray, dR: np.ndarray, t: np.ndarray, v: CameraView) -> tuple[np.ndarray, np.ndarray]:
    """One view's residuals (2N,) and Jacobian rows (2N, 6) at T_rig_robot = (R, t); dR (3, 3, 3) = dR/drvec_k.

    A pinhole lens (radtan, rational) in one numba pass (_pinhole_view): the refinement evaluates ~6 times
    per call, and camera.project's array steps cost ~35 us a view each time, the pass ~3 us. Other lenses
    through camera.project (_projected_view)."""
    if v.camera.lens not in ("radtan", "rational"):
        return _projected_view(R, dR, t, v)
    k = np.zeros(8)
    k[:len(v.camera.params)] = v.camera.params
    return _pinhole_view(R, dR, t, v.object_points_m, v.R_cam_rig, v.t_cam_rig_m,
                         np.array([v.camera.fx, v.camera.fy, v.camera.cx, v.camera.cy]), k, v.image_points_px)


def _projected_view(R: np.ndarray, dR: np.ndarray, t: np.ndarray, v: CameraView) -> tuple[np.ndarray, np.ndarray]:
    """_view_terms through camera.project, for any lens."""
    X = v.object_points_m
    p_rig = X @ R.T + t
    p_cam = p_rig @ v.R_cam_rig.T + v.t_cam_rig_m
    q, dq_dp, _ = project(p_cam, v.camera, get_gradients=True, intrinsics_gradient=False)
    dq_drig = dq_dp @ v.R_cam_rig                                   # (N, 2, 3)
    dp_drvec = np.einsum("kij,nj->nik", dR, X)                      # d(R X)/d rvec: (N, 3, 3)
    return (q - v.image_points_px).ravel(), np.concatenate([dq_drig @ dp_drvec, dq_drig], axis=2).reshape(-1, 6)


def whitening(cov_px2: np.ndarray) -> np.ndarray:
    """(N, 2, 2) matrices L^T with |L^T r|^2 = r^T C^-1 r for each covariance C (N, 2, 2): L L^T = C^-1."""
    return np.transpose(np.linalg.cholesky(np.linalg.inv(cov_px2)), (0, 2, 1))


def _view_whitening(views: list[CameraView]) -> np.ndarray | None:
    """The stacked whitening of all corners (in the residuals' order), None when no view has covariances."""
    if all(v.image_covariance_px2 is None for v in views):
        return None
    parts = [whitening(v.image_covariance_px2) if v.image_covariance_px2 is not None
             else np.broadcast_to(np.eye(2), (v.n, 2, 2)) for v in views if v.n > 0]
    return np.concatenate(parts)


def refine_pose(R0: np.ndarray, t0: np.ndarray, views: list[CameraView],
                max_iterations: int = 50) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Levenberg-Marquardt refinement from (R0, t0); returns R, t, residuals (px) and the Jacobian (px).

    The Jacobian is with respect to the perturbation [dt (m), dtheta (rad)] with R = exp([dtheta]x) R_hat,
    t = t_hat + dt, i.e. the parameter order and meaning of the published covariance. When the views carry
    corner covariances the whitened residuals are minimised (each corner weighs by how well it is known);
    the returned residuals and Jacobian are in pixels either way.
    """
    rvec0, _ = cv2.Rodrigues(np.asarray(R0, dtype=np.float64))
    x0 = np.concatenate([rvec0.ravel(), np.asarray(t0, dtype=np.float64).ravel()])
    white = _view_whitening(views)
    cache: dict[bytes, tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = {}

    def evaluate(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(whitened residuals, whitened Jacobian, residuals px, Jacobian px) at x, cached for the last x."""
        key = x.tobytes()
        if key not in cache:
            cache.clear()
            r, J = _residuals_and_jacobian(x, views)
            if white is None:
                cache[key] = (r, J, r, J)
            else:
                rw = np.einsum("nij,nj->ni", white, r.reshape(-1, 2)).ravel()
                Jw = np.einsum("nij,njk->nik", white, J.reshape(-1, 2, 6)).reshape(-1, 6)
                cache[key] = (rw, Jw, r, J)
        return cache[key]

    def residuals(x: np.ndarray) -> np.ndarray:
        return evaluate(x)[0]

    def jacobian(x: np.ndarray) -> np.ndarray:
        return evaluate(x)[1]

    # MINPACK's Levenberg-Marquardt (lmder) through leastsq, the thin wrapper: least_squares(method="lm") calls
    # the same routine with the same arguments (scaling by the Jacobian's columns, factor 100), so the same
    # iterates, but its bookkeeping around it cost ~0.15 ms per call here (1.05 -> 0.89 ms per call). Its
    # refusals are kept: a start whose residuals are not finite (corners behind a camera), fewer residuals
    # than parameters.
    r0 = residuals(x0)
    if not np.all(np.isfinite(r0)):
        raise ValueError("residuals are not finite at the starting pose")
    if r0.size < x0.size:
        raise ValueError(f"{r0.size} residuals for {x0.size} pose parameters")
    x = leastsq(residuals, x0, Dfun=jacobian, full_output=True, maxfev=max_iterations, xtol=1e-12, ftol=1e-12,
                gtol=1e-12)[0]
    _, _, r, J = evaluate(x)
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


def model_covariance(J: np.ndarray, cov_px2: np.ndarray, groups: np.ndarray, shared_basis: np.ndarray,
                     shared_var: np.ndarray) -> np.ndarray:
    """6x6 covariance of the perturbation [dt, dtheta] of a fit weighted by the corner covariances, with an
    error shared by the corners of each group on top.

    J: (2M, 6) pixel Jacobian (refine_pose); cov_px2: (M, 2, 2) the corners' covariances (the weights);
    groups: (M,) int group of each corner (a board in one camera); shared_basis: (M, 2, K) how the K
    parameters of a group's shared error move each corner (px per unit); shared_var: (G, K) their
    variances. With W = C^-1 and H = J^T W J the weighted fit's covariance is
    H^-1 J^T W (C + S) W J H^-1 = H^-1 + H^-1 (sum_g G_g^T Lambda_g G_g) H^-1, G_g = sum over the group's
    corners of B_i^T W_i J_i: a shared error does not average out over a board's corners as independent
    ones do. A singular H gives an infinite covariance.
    """
    m = len(cov_px2)
    if m < 3:
        return np.full((6, 6), np.inf)
    W = np.linalg.inv(cov_px2)
    Jc = J.reshape(m, 2, 6)
    WJ = np.einsum("nij,njk->nik", W, Jc)
    H = np.einsum("nji,njk->ik", Jc, WJ)
    if not np.all(np.isfinite(H)) or np.linalg.cond(H) > 1e14:
        return np.full((6, 6), np.inf)
    Hi = np.linalg.inv(H)
    G = _sum_by_group(np.ascontiguousarray(groups, dtype=np.int64),
                      np.ascontiguousarray(np.einsum("nji,njk->nik", shared_basis, WJ)), int(groups.max()) + 1)
    shared = np.einsum("gk,gki,gkj->ij", np.asarray(shared_var, dtype=np.float64), G, G)
    cov = Hi + Hi @ shared @ Hi
    return 0.5 * (cov + cov.T)


@njit(cache=True, nogil=True)
def _sum_by_group(groups: np.ndarray, values: np.ndarray, n_groups: int) -> np.ndarray:
    """(n_groups, K, L) sums of ``values`` (M, K, L) over the rows of each group ``groups`` (M,), row by row in
    order: np.add.at's sums (the same additions in the same order), without its ~25 ns per element (a
    frame's M x K x L is ~30 000)."""
    m, k, n = values.shape
    out = np.zeros((n_groups, k, n))
    for i in range(m):
        g = groups[i]
        for a in range(k):
            for b in range(n):
                out[g, a, b] += values[i, a, b]
    return out


@njit(cache=True, nogil=True)
def _pinhole_view(R: np.ndarray, dR: np.ndarray, t: np.ndarray, X: np.ndarray, R_cam_rig: np.ndarray,
                  t_cam_rig: np.ndarray, intrinsics: np.ndarray, k: np.ndarray, observed: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """_view_terms of a radtan or rational lens (camera.project's numbers to rounding): residuals (2N,) px and
    their Jacobian (2N, 6) by (rvec, t), from T_rig_robot's R (3, 3), dR (3, 3, 3) = dR/drvec_k, t (3,), the
    view's robot points X (N, 3) m, its camera's (fx, fy, cx, cy) and distortion k padded to 8
    (camera._radtan_distort_kernel's), observed pixels (N, 2). NaN for points not in front of the camera,
    as camera.project gives."""
    n = X.shape[0]
    pc = np.empty((n, 3))
    xs = np.empty(n)
    ys = np.empty(n)
    zi = np.empty(n)
    for i in range(n):
        for a in range(3):
            pr = R[a, 0] * X[i, 0] + R[a, 1] * X[i, 1] + R[a, 2] * X[i, 2] + t[a]
            pc[i, a] = pr
        p0, p1, p2 = pc[i, 0], pc[i, 1], pc[i, 2]
        for a in range(3):
            pc[i, a] = R_cam_rig[a, 0] * p0 + R_cam_rig[a, 1] * p1 + R_cam_rig[a, 2] * p2 + t_cam_rig[a]
        zi[i] = 1.0 / pc[i, 2] if pc[i, 2] > 0 else np.nan
        xs[i] = pc[i, 0] * zi[i]
        ys[i] = pc[i, 1] * zi[i]
    xd, yd, da, db, de = _radtan_distort_kernel(xs, ys, k, True)
    fx, fy, cx, cy = intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3]
    res = np.empty(2 * n)
    jac = np.empty((2 * n, 6))
    dq_dp = np.empty((2, 3))
    dq_drig = np.empty((2, 3))
    for i in range(n):
        res[2 * i] = fx * xd[i] + cx - observed[i, 0]
        res[2 * i + 1] = fy * yd[i] + cy - observed[i, 1]
        z = zi[i]
        # d(xd, yd)/d p_cam: the distortion's [[a, b], [b, e]] times d(x, y)/d p_cam, scaled by the focal lengths
        for row, (u, w, f) in enumerate(((da[i], db[i], fx), (db[i], de[i], fy))):
            dq_dp[row, 0] = f * (u * z)
            dq_dp[row, 1] = f * (w * z)
            dq_dp[row, 2] = f * (-(u * xs[i] + w * ys[i]) * z)
        for row in range(2):
            for c in range(3):
                dq_drig[row, c] = (dq_dp[row, 0] * R_cam_rig[0, c] + dq_dp[row, 1] * R_cam_rig[1, c]
                                   + dq_dp[row, 2] * R_cam_rig[2, c])
            for kk in range(3):
                # d p_rig / d rvec_k = dR[k] X
                g = 0.0
                for c in range(3):
                    g += dq_drig[row, c] * (dR[kk, c, 0] * X[i, 0] + dR[kk, c, 1] * X[i, 1] + dR[kk, c, 2] * X[i, 2])
                jac[2 * i + row, kk] = g
                jac[2 * i + row, 3 + kk] = dq_drig[row, kk]
    return res, jac
