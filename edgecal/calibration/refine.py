"""Non-linear refinement of cameras and poses, robust to outliers, with parameter standard deviations.

One solver serves every case: observations of a target by one or two cameras in one or more views.
The unknowns are each camera's intrinsics (fx, fy, cx, cy and the free distortion terms), each view's
target pose in camera 0 (``T_cam0_target``) and, for each further camera c, the rig pose
``T_camc_cam0``. Camera c sees target points at ``R_c0 (R_v X + t_v) + t_c0``. One box image from
each of two cameras is one view seen by two cameras; the planar multi-view case has many views.

The Jacobian is analytic (cv2.projectPoints and cv2.composeRT give their derivatives); the solver is
Levenberg-Marquardt. After a robust (Huber) fit, corners whose residual is far outside the noise are dropped and reported, the rest is
fitted with plain least squares, and the covariance is s^2 (J^T J)^-1 with s^2 = SSR / (m - n).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import cv2
import numpy as np

from edgecal.calibration.checks import DegenerateInput
from edgecal.calibration.types import CAMERA_NAMES, Calibration, Camera, CornerSet, Pose

INTRINSIC_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
POSE_NAMES = ("rx", "ry", "rz", "tx", "ty", "tz")
# Which of k1 k2 p1 p2 k3 are free for each distortion model name.
DISTORTION_MODELS = {
    "none": (),
    "k1": (0,),
    "k1k2": (0, 1),
    "k1k2k3": (0, 1, 4),
    "k1k2p1p2": (0, 1, 2, 3),
    "k1k2p1p2k3": (0, 1, 2, 3, 4),
}


@dataclass(frozen=True)
class Observation:
    """Corners of the target seen by ``camera`` in ``view``: 3-D target points (mm) and pixels."""

    camera: int
    view: int
    object_mm: np.ndarray   # (N, 3)
    image_px: np.ndarray    # (N, 2)
    labels: tuple[str, ...] = ()  # one name per corner, for reports (e.g. "left top (2,3)")


@dataclass(frozen=True)
class RefineOptions:
    """How to refine: distortion model, robust loss, outlier rejection."""

    distortion: str = "k1k2"
    loss_scale_px: float = 1.0       # Huber: residuals above this count linearly
    outlier_sigmas: float = 5.0      # drop corners this many noise sigmas out ...
    outlier_min_px: float = 0.5      # ... and at least this far from their reprojection
    max_rounds: int = 3
    fix_principal_point: bool = False


@dataclass
class RefineResult:
    """The refined cameras and poses, their standard deviations, residuals and dropped corners."""

    cameras: list[Camera]
    view_poses: list[Pose]
    rig_poses: list[Pose]            # rig_poses[c - 1] is T_camc_cam0
    names: list[str]                 # name of every parameter, e.g. "cam0.fx", "view0.tz", "rig1.rx"
    values: np.ndarray
    std: np.ndarray                  # standard deviation of every parameter (nan when fixed, inf if undetermined)
    covariance: np.ndarray
    rms_px: float
    sigma_px: float                  # noise estimate sqrt(SSR / (m - n)) per coordinate
    residuals: list[np.ndarray]      # per observation, (N, 2) reprojected - detected (dropped corners included)
    inliers: list[np.ndarray]        # per observation, (N,) bool
    dropped: list[str] = field(default_factory=list)
    rank_deficient: bool = False

    def std_of(self, name: str) -> float:
        """The standard deviation of the parameter ``name`` (nan if it was not estimated)."""
        return float(self.std[self.names.index(name)]) if name in self.names else float("nan")


class _Layout:
    """Where each unknown sits in the parameter vector."""

    def __init__(self, n_cameras: int, n_views: int, distortion: str, fix_pp: bool) -> None:
        if distortion not in DISTORTION_MODELS:
            raise DegenerateInput(f"distortion model {distortion!r} unknown (one of {', '.join(DISTORTION_MODELS)})")
        self.free_dist = DISTORTION_MODELS[distortion]
        self.free_intr = (0, 1) + (() if fix_pp else (2, 3)) + tuple(4 + i for i in self.free_dist)
        self.n_cameras, self.n_views = n_cameras, n_views
        self.names: list[str] = []
        self.cam_slice = []
        for c in range(n_cameras):
            self.cam_slice.append(slice(len(self.names), len(self.names) + len(self.free_intr)))
            self.names += [f"cam{c}.{INTRINSIC_NAMES[i]}" for i in self.free_intr]
        self.view_slice = []
        for v in range(n_views):
            self.view_slice.append(slice(len(self.names), len(self.names) + 6))
            self.names += [f"view{v}.{n}" for n in POSE_NAMES]
        self.rig_slice = []
        for c in range(1, n_cameras):
            self.rig_slice.append(slice(len(self.names), len(self.names) + 6))
            self.names += [f"rig{c}.{n}" for n in POSE_NAMES]

    def pack(self, cameras: list[Camera], views: list[Pose], rigs: list[Pose]) -> np.ndarray:
        x = np.zeros(len(self.names))
        for c, cam in enumerate(cameras):
            k, d = cam.camera_matrix, np.asarray(cam.dist_coeffs, dtype=np.float64).ravel()
            full = np.r_[k[0, 0], k[1, 1], k[0, 2], k[1, 2], np.r_[d, np.zeros(5)][:5]]
            x[self.cam_slice[c]] = full[list(self.free_intr)]
        for v, p in enumerate(views):
            x[self.view_slice[v]] = np.r_[np.ravel(p.rvec), np.ravel(p.tvec)]
        for c, p in enumerate(rigs):
            x[self.rig_slice[c]] = np.r_[np.ravel(p.rvec), np.ravel(p.tvec)]
        return x

    def unpack(self, x: np.ndarray, start: list[Camera]) -> tuple[list[Camera], list[Pose], list[Pose]]:
        cams = []
        free = np.array(self.free_intr, dtype=np.int64)
        fixed_dist = np.array([4 + i for i in range(5) if i not in self.free_dist], dtype=np.int64)
        for c in range(self.n_cameras):
            k0 = start[c].camera_matrix
            full = np.zeros(9)
            full[:4] = (k0[0, 0], k0[1, 1], k0[0, 2], k0[1, 2])
            d0 = np.ravel(start[c].dist_coeffs)[:5]
            full[4:4 + len(d0)] = d0
            full[free] = x[self.cam_slice[c]]
            full[fixed_dist] = 0.0  # terms outside the model are 0
            k = np.array([[full[0], 0.0, full[2]], [0.0, full[1], full[3]], [0.0, 0.0, 1.0]])
            cams.append(Camera(k, full[4:9]))
        views = [Pose(x[s][:3], x[s][3:]) for s in self.view_slice]
        rigs = [Pose(x[s][:3], x[s][3:]) for s in self.rig_slice]
        return cams, views, rigs


def _project(obs: Observation, cams: list[Camera], views: list[Pose], rigs: list[Pose],
             layout: _Layout, n_params: int, want_jac: bool) -> tuple[np.ndarray, np.ndarray | None]:
    """Residuals (2N,) of one observation and, if asked, their Jacobian (2N, n_params)."""
    cam = cams[obs.camera]
    view = views[obs.view]
    if obs.camera == 0:
        rvec, tvec = view.rvec, view.tvec
    else:
        rig = rigs[obs.camera - 1]
        (rvec, tvec, dr3dr1, dr3dt1, dr3dr2, dr3dt2,
         dt3dr1, dt3dt1, dt3dr2, dt3dt2) = cv2.composeRT(view.rvec, view.tvec, rig.rvec, rig.tvec)
    proj, jp = cv2.projectPoints(obs.object_mm, rvec, tvec, cam.camera_matrix, cam.dist_coeffs)
    res = (proj.reshape(-1, 2) - obs.image_px).ravel()
    if not want_jac:
        return res, None
    jac = np.zeros((len(res), n_params))
    # projectPoints columns: rvec(3) tvec(3) fx fy cx cy k1 k2 p1 p2 k3
    intr_cols = np.r_[6:15][list(layout.free_intr)]
    jac[:, layout.cam_slice[obs.camera]] = jp[:, intr_cols]
    d_r, d_t = jp[:, 0:3], jp[:, 3:6]
    if obs.camera == 0:
        jac[:, layout.view_slice[obs.view]] = np.c_[d_r, d_t]
    else:
        jac[:, layout.view_slice[obs.view]] = np.c_[d_r @ dr3dr1 + d_t @ dt3dr1, d_r @ dr3dt1 + d_t @ dt3dt1]
        jac[:, layout.rig_slice[obs.camera - 1]] = np.c_[d_r @ dr3dr2 + d_t @ dt3dr2, d_r @ dr3dt2 + d_t @ dt3dt2]
    return res, jac


def _stack(x: np.ndarray, obs: list[Observation], masks: list[np.ndarray], layout: _Layout,
           start: list[Camera], want_jac: bool) -> tuple[np.ndarray, np.ndarray | None]:
    cams, views, rigs = layout.unpack(x, start)
    rs, js = [], []
    for o, m in zip(obs, masks):
        r, j = _project(o, cams, views, rigs, layout, len(x), want_jac)
        keep = np.repeat(m, 2)
        rs.append(r[keep])
        if want_jac:
            js.append(j[keep])
    return np.concatenate(rs), (np.vstack(js) if want_jac else None)


def _levenberg_marquardt(fun: Callable[[np.ndarray, bool], tuple[np.ndarray, np.ndarray | None]],
                         x0: np.ndarray, huber_px: float | None = None, max_iter: int = 100) -> np.ndarray:
    """Minimise sum rho(r) by Levenberg-Marquardt (Marquardt's diagonal scaling).

    ``rho`` is the square, or Huber's function with threshold ``huber_px`` (iteratively reweighted).
    The normal equations are formed and solved with OpenCV: numpy's threaded BLAS is pathologically
    slow on a shared, oversubscribed machine, and these matrices are small.
    """
    def cost_and_weights(r: np.ndarray) -> tuple[float, np.ndarray]:
        if huber_px is None:
            return float(r @ r), np.ones_like(r)
        a = np.abs(r)
        inside = a <= huber_px
        cost = float(np.sum(np.where(inside, r * r, 2.0 * huber_px * a - huber_px ** 2)))
        return cost, np.where(inside, 1.0, huber_px / np.maximum(a, 1e-300))

    x = np.asarray(x0, dtype=np.float64).copy()
    r, jac = fun(x, True)
    cost, w = cost_and_weights(r)
    lam = 1e-3
    for _ in range(max_iter):
        sw = np.sqrt(w)
        a = cv2.mulTransposed(jac * sw[:, None], True)
        g = cv2.gemm(jac, (w * r).reshape(-1, 1), 1.0, None, 0.0, flags=cv2.GEMM_1_T).ravel()
        d = np.diag(a).copy()
        d[d <= 0] = 1.0
        improved = False
        while lam < 1e12:
            ok, step = cv2.solve(a + lam * np.diag(d), -g.reshape(-1, 1), flags=cv2.DECOMP_CHOLESKY)
            if not ok:
                ok, step = cv2.solve(a + lam * np.diag(d), -g.reshape(-1, 1), flags=cv2.DECOMP_SVD)
            step = step.ravel()
            x_new = x + step
            r_new, jac_new = fun(x_new, True)  # the Jacobian comes almost free with the residuals
            cost_new = cost_and_weights(r_new)[0] if np.all(np.isfinite(r_new)) else np.inf
            if cost_new < cost:
                improved = True
                lam = max(lam * 0.1, 1e-12)
                break
            lam *= 10.0
        if not improved:
            break  # no step lowers the cost: at the minimum (to rounding)
        small = (cost - cost_new) <= 1e-12 * max(cost, 1e-300) or np.linalg.norm(step) <= 1e-12 * (np.linalg.norm(x) + 1e-12)
        x, r, jac = x_new, r_new, jac_new
        cost, w = cost_and_weights(r)
        if small:
            break
    return x


def refine(observations: list[Observation], cameras: list[Camera], view_poses: list[Pose],
           rig_poses: list[Pose] | None = None, options: RefineOptions = RefineOptions()) -> RefineResult:
    """Refine cameras and poses from ``observations`` starting at the given values.

    Raises DegenerateInput when there are fewer residuals than unknowns.
    """
    rig_poses = list(rig_poses or [])
    if len(rig_poses) != len(cameras) - 1:
        raise ValueError("one rig pose is needed for every camera after the first")
    layout = _Layout(len(cameras), len(view_poses), options.distortion, options.fix_principal_point)
    obs = [Observation(o.camera, o.view, np.asarray(o.object_mm, np.float64).reshape(-1, 3),
                       np.asarray(o.image_px, np.float64).reshape(-1, 2),
                       tuple(o.labels) or tuple(f"cam{o.camera} view{o.view} #{i}" for i in range(len(o.object_mm))))
           for o in observations]
    masks = [np.ones(len(o.object_mm), dtype=bool) for o in obs]
    n_params = len(layout.names)
    if 2 * sum(len(o.object_mm) for o in obs) <= n_params:
        raise DegenerateInput(f"{sum(len(o.object_mm) for o in obs)} corners cannot determine {n_params} "
                              f"unknowns: more corners are needed")
    start = [c.copy() for c in cameras]
    x = layout.pack(start, view_poses, rig_poses)
    dropped: list[str] = []

    def fun(p: np.ndarray, want_jac: bool) -> tuple[np.ndarray, np.ndarray | None]:
        return _stack(p, obs, masks, layout, start, want_jac)

    # Robust pass: a few bad corners must not drag the solution before they can be identified.
    x = _levenberg_marquardt(fun, x, huber_px=options.loss_scale_px)
    for _ in range(options.max_rounds):
        cams, views, rigs = layout.unpack(x, start)
        norms = [np.linalg.norm(_project(o, cams, views, rigs, layout, n_params, False)[0].reshape(-1, 2), axis=1)
                 for o in obs]
        inlier_norms = np.concatenate([n[m] for n, m in zip(norms, masks)])
        # Per-corner residual norms of 2-D Gaussian noise follow a Rayleigh law: median = 1.1774 sigma.
        sigma = float(np.median(inlier_norms)) / 1.1774
        limit = max(options.outlier_min_px, options.outlier_sigmas * sigma)
        changed = False
        for o, n, m in zip(obs, norms, masks):
            bad = m & (n > limit)
            for i in np.flatnonzero(bad):
                dropped.append(f"{o.labels[i]}: residual {n[i]:.2f} px > {limit:.2f} px")
            if bad.any():
                m &= ~bad
                changed = True
        if 2 * sum(int(m.sum()) for m in masks) <= n_params:
            raise DegenerateInput("too many corners were rejected as outliers to determine the calibration")
        x = _levenberg_marquardt(fun, x)
        if not changed:
            break

    r, j = _stack(x, obs, masks, layout, start, True)
    m_res = len(r)
    dof = max(m_res - n_params, 1)
    s2 = float(r @ r) / dof
    jtj = cv2.mulTransposed(j, True)
    # Scale columns before inverting: fx ~ 1e3 and k1 ~ 1e-1 live in one matrix.
    d = np.sqrt(np.maximum(np.diag(jtj), 1e-300))
    jtj_n = jtj / np.outer(d, d)
    eig = np.ravel(cv2.eigen(jtj_n)[1])
    rank_deficient = bool(eig.min() < 1e-12 * eig.max())
    if rank_deficient:
        cov = np.full((n_params, n_params), np.inf)
    else:
        cov = s2 * cv2.invert(jtj_n, flags=cv2.DECOMP_SVD)[1] / np.outer(d, d)
    std = np.sqrt(np.abs(np.diag(cov)))
    cams, views, rigs = layout.unpack(x, start)
    residuals, inliers = [], []
    for o, msk in zip(obs, masks):
        rr = _project(o, cams, views, rigs, layout, n_params, False)[0].reshape(-1, 2).copy()
        residuals.append(rr)
        inliers.append(msk.copy())
    rms = float(np.sqrt(np.mean(np.sum(r.reshape(-1, 2) ** 2, axis=1))))
    return RefineResult(cams, views, rigs, list(layout.names), x, std, cov, rms, float(np.sqrt(s2)),
                        residuals, inliers, dropped, rank_deficient)


def observations_for(corners: list[list[CornerSet]], view_ids: list[int] | list[str] | None = None
                     ) -> list[Observation]:
    """One Observation per camera and view of ``corners[camera][view]`` (empty sets are skipped).

    ``view_ids`` name the views in corner labels (their file names, or numbers); default 0, 1, ...
    """
    names = CAMERA_NAMES if len(corners) == 2 else ("camera",)
    multi = max(len(c) for c in corners) > 1
    ids = view_ids if view_ids is not None else list(range(max(len(c) for c in corners)))
    return [Observation(c, v, cs.object_mm, cs.image_px, cs.labels(names[c], ids[v] if multi else None))
            for c, per_view in enumerate(corners) for v, cs in enumerate(per_view) if len(cs)]


def calibration_from_result(kind: str, image_size: tuple[int, int], corners: list[list[CornerSet]],
                            result: RefineResult) -> Calibration:
    """Package a RefineResult (made from ``observations_for(corners)``) as a Calibration."""
    n_cams = len(corners)
    camera_std = []
    for c in range(n_cams):
        camera_std.append({n: result.std_of(f"cam{c}.{n}") for n in INTRINSIC_NAMES})
    residuals: list[list[np.ndarray]] = [[np.zeros((0, 2)) for _ in per_view] for per_view in corners]
    inliers: list[list[np.ndarray]] = [[np.zeros(0, dtype=bool) for _ in per_view] for per_view in corners]
    k = 0
    for c, per_view in enumerate(corners):
        for v, cs in enumerate(per_view):
            if len(cs):
                residuals[c][v], inliers[c][v] = result.residuals[k], result.inliers[k]
                k += 1
    cal = Calibration(kind, (int(image_size[0]), int(image_size[1])), result.cameras, camera_std,
                      result.view_poses, corners, residuals, inliers, result.rms_px, result.sigma_px,
                      dropped=list(result.dropped))
    cal.view_pose_std = [np.array([result.std_of(f"view{v}.{n}") for n in POSE_NAMES])
                         for v in range(len(result.view_poses))]
    if n_cams == 2:
        rig = result.rig_poses[0]
        cal.rotation = rig.rotation
        cal.translation_mm = np.ravel(rig.tvec).copy()
        cal.rotation_std_rad = np.array([result.std_of(f"rig1.{n}") for n in POSE_NAMES[:3]])
        cal.translation_std_mm = np.array([result.std_of(f"rig1.{n}") for n in POSE_NAMES[3:]])
    if result.rank_deficient:
        cal.notes.append("the corners do not determine every parameter (rank-deficient Jacobian): "
                         "standard deviations are infinite; show more of the target")
    return cal
