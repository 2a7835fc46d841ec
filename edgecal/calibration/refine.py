"""Non-linear refinement of cameras and poses, robust to outliers, with parameter standard deviations.

One solver serves every case: observations of a target by one or two cameras in one or more views.
The unknowns are each camera's intrinsics (fx, fy, cx, cy and the free parameters of its lens model,
edgecal.camera.DISTORTION_MODELS), each view's target pose in camera 0 (``T_cam0_target``) and, for
each further camera c, the rig pose ``T_camc_cam0``. Camera c sees target points at
``R_c0 (R_v X + t_v) + t_c0``. One box image from each of two cameras is one view seen by two cameras;
the planar multi-view case has many views.

The solver is scipy's least_squares (trust-region reflective) with an explicit sparse Jacobian: each
residual depends only on its camera's intrinsics, its view's pose and its rig pose, so 300 stereo views
give a Jacobian that is 99 % zeros (a dense one of 900 views would need ~8 GB). The derivatives are
analytic (edgecal.camera.project's gradients and cv2.Rodrigues'). After a robust (Huber) fit, corners
whose residual is far outside the noise are dropped and reported, the rest is fitted with plain least
squares, and the covariance is s^2 (J^T J)^-1 with s^2 = SSR / (m - n).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import cv2
import numpy as np
import scipy.sparse
from scipy.optimize import least_squares

from edgecal.calibration.checks import DegenerateInput
from edgecal.calibration.types import (
    CAMERA_NAMES,
    Calibration,
    CornerSet,
    RigidTransform,
)
from edgecal.camera import DISTORTION_MODELS, LENS_PARAMS, CameraModel, project
from edgecal.config import setting

POSE_NAMES = ("rx", "ry", "rz", "tx", "ty", "tz")
# Every lens model a calibration can fit, and "auto" (edgecal.calibration.lens_choice picks one).
DISTORTION_CHOICES = (*DISTORTION_MODELS, "auto")
# Relative tolerances of least_squares: far below the 1e-4 relative uncertainty of a good calibration.
_TOL = 1e-10
_MAX_NFEV = 200
# Up to this many Jacobian entries (8 bytes each: 32 MB) the solver works on the dense Jacobian.
_DENSE_JACOBIAN_ENTRIES = 4_000_000


@dataclass(frozen=True)
class Observation:
    """Corners of the target seen by ``camera`` in ``view``: 3-D target points (mm) and pixels."""

    camera: int
    view: int
    object_mm: np.ndarray   # (N, 3)
    image_px: np.ndarray    # (N, 2)
    labels: tuple[str, ...] = ()  # one name per corner, for reports (e.g. "left top (2,3)")
    image_cov_px2: np.ndarray | None = None   # (N, 2, 2) corner covariances: the residuals are whitened by them


@dataclass(frozen=True)
class RefineOptions:
    """How to refine: distortion model (a key of DISTORTION_MODELS), robust loss, outlier rejection."""

    distortion: str = setting("k1k2", doc="lens model to fit (docs/conventions.md), or auto (the simplest whose "
                                          "residual is within the noise)", choices=DISTORTION_CHOICES)
    loss_scale_px: float = setting(1.0, doc="Huber: residuals above this count linearly (robust first pass)",
                                   positive=True, renamed_from=("robust_loss_scale_px",))
    outlier_sigmas: float = setting(5.0, doc="drop corners this many noise sigmas out ...", minimum=2.0)
    outlier_min_px: float = setting(0.5, doc="... and at least this far from their reprojection", minimum=0.0)
    # Solver knobs of the code, not of the config file.
    max_rounds: int = 3
    fix_principal_point: bool = False


@dataclass
class RefineResult:
    """The refined cameras and poses, their standard deviations, residuals and dropped corners."""

    cameras: list[CameraModel]
    view_poses: list[RigidTransform]
    rig_poses: list[RigidTransform]  # rig_poses[c - 1] is T_camc_cam0
    names: list[str]                 # name of every parameter, e.g. "cam0.fx", "view0.tz", "rig1.rx"
    values: np.ndarray
    std: np.ndarray                  # standard deviation of every parameter (inf if undetermined)
    covariance: np.ndarray
    rms_px: float
    sigma_px: float                  # noise estimate sqrt(SSR / (m - n)) per coordinate (px)
    residuals: list[np.ndarray]      # per observation, (N, 2) reprojected - detected (dropped corners included)
    inliers: list[np.ndarray]        # per observation, (N,) bool
    dropped: list[str] = field(default_factory=list)
    rank_deficient: bool = False
    undetermined: list[str] = field(default_factory=list)  # parameters in the Jacobian's null space
    noise_floor_px: float = 0.0      # weighted: the sigma per axis added to every corner's covariance (noise_floor_px2)

    def std_of(self, name: str) -> float:
        """The standard deviation of the parameter ``name`` (nan if it was not estimated)."""
        return float(self.std[self.names.index(name)]) if name in self.names else float("nan")


def lens_of(distortion: str) -> tuple[str, tuple[str, ...]]:
    """(lens model, free parameters) of a distortion option; DegenerateInput listing the known ones if unknown."""
    if distortion not in DISTORTION_MODELS:
        raise DegenerateInput(f"distortion model {distortion!r} unknown (one of {', '.join(DISTORTION_MODELS)})")
    return DISTORTION_MODELS[distortion]


def as_lens(camera: CameraModel, distortion: str) -> CameraModel:
    """``camera`` in the lens model of ``distortion``, the parameters outside its free set 0.

    radtan and rational share k1 k2 p1 p2 k3; between them and fisheye nothing carries over (a start with
    no distortion is close enough near the axis, where both are the pinhole).
    """
    lens, free = lens_of(distortion)
    if camera.lens == lens:
        params = np.array(camera.params)
    elif {camera.lens, lens} == {"radtan", "rational"}:
        params = np.r_[camera.params[:5], np.zeros(3)][:len(LENS_PARAMS[lens])]
    else:
        params = np.zeros(len(LENS_PARAMS[lens]))
    params[[i for i, n in enumerate(LENS_PARAMS[lens]) if n not in free]] = 0.0
    return camera.with_lens(lens, params)


class _Layout:
    """Where each unknown sits in the parameter vector."""

    def __init__(self, cameras: list[CameraModel], n_views: int, distortion: str, fix_pp: bool) -> None:
        lens, free = lens_of(distortion)
        names = LENS_PARAMS[lens]
        self.free_intr = np.array([0, 1] + ([] if fix_pp else [2, 3])
                                  + [4 + i for i, n in enumerate(names) if n in free], dtype=np.int64)
        self.n_cameras, self.n_views = len(cameras), n_views
        self.names: list[str] = []
        self.cam_slice = []
        for c, cam in enumerate(cameras):
            self.cam_slice.append(slice(len(self.names), len(self.names) + len(self.free_intr)))
            self.names += [f"cam{c}.{cam.intrinsic_names[i]}" for i in self.free_intr]
        self.view_slice = []
        for v in range(n_views):
            self.view_slice.append(slice(len(self.names), len(self.names) + 6))
            self.names += [f"view{v}.{n}" for n in POSE_NAMES]
        self.rig_slice = []
        for c in range(1, self.n_cameras):
            self.rig_slice.append(slice(len(self.names), len(self.names) + 6))
            self.names += [f"rig{c}.{n}" for n in POSE_NAMES]

    def pack(self, cameras: list[CameraModel], views: list[RigidTransform], rigs: list[RigidTransform]) -> np.ndarray:
        x = np.zeros(len(self.names))
        for c, cam in enumerate(cameras):
            x[self.cam_slice[c]] = cam.intrinsics[self.free_intr]
        for v, p in enumerate(views):
            x[self.view_slice[v]] = np.r_[np.ravel(p.rvec), np.ravel(p.tvec)]
        for c, p in enumerate(rigs):
            x[self.rig_slice[c]] = np.r_[np.ravel(p.rvec), np.ravel(p.tvec)]
        return x

    def unpack(self, x: np.ndarray, start: list[CameraModel]
               ) -> tuple[list[CameraModel], list[RigidTransform], list[RigidTransform]]:
        cams = []
        for c in range(self.n_cameras):
            full = start[c].intrinsics.copy()   # fixed terms keep their start value (0 outside the model)
            full[self.free_intr] = x[self.cam_slice[c]]
            cams.append(start[c].with_intrinsics(full))
        views = [RigidTransform(x[s][:3].copy(), x[s][3:].copy()) for s in self.view_slice]
        rigs = [RigidTransform(x[s][:3].copy(), x[s][3:].copy()) for s in self.rig_slice]
        return cams, views, rigs


def _rotations(rvecs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation matrices (K, 3, 3) of rotation vectors (K, 3) and dR/drvec as (K, 3 [rvec], 3, 3)."""
    R = np.empty((len(rvecs), 3, 3))
    dR = np.empty((len(rvecs), 3, 3, 3))
    for i, r in enumerate(rvecs):
        m, j = cv2.Rodrigues(r.reshape(3, 1))
        R[i], dR[i] = m, j.reshape(3, 3, 3)
    return R, dR


# Huber threshold of a weighted problem, in the corners' own sigmas: beyond 3 sigma a residual counts linearly.
HUBER_SIGMAS = 3.0
# Median of a chi^2 with 2 degrees of freedom (2 ln 2): the median normalised error r^T C^-1 r of a corner
# whose covariance C is right.
_CHI2_2_MEDIAN = 2.0 * np.log(2.0)


def noise_floor_px2(residuals: np.ndarray, cov_px2: np.ndarray, dof_fraction: float = 1.0) -> float:
    """The isotropic variance s0^2 (px^2) the corners' covariances lack: the smallest s0^2 >= 0 with which
    the median normalised residual r^T (C + s0^2 I)^-1 r is that of a consistent 2-D error.

    residuals (M, 2) px, cov_px2 (M, 2, 2) the detector's covariances, dof_fraction (m - n) / m of the fit
    (a fit's residuals are smaller than the errors by that much on average). A median, so gross outliers do
    not count. Why: the detector's covariance models the image noise and the window it sees, not what a
    real lens and sensor add on top (defocus, JPEG, a board that is not flat, the lens model's own misfit);
    on real photos that part dominates (Bouguet's set: the covariances say 0.02 px, the fit shows 0.13 px),
    and weighing by the covariance alone then trusts the sharpest corners 2000x more than a misdetected one
    instead of ~50x, and judges outliers on a scale the good corners do not follow. On renders the
    covariance is right and s0 is ~0: the weighting is unchanged.
    """
    r = np.asarray(residuals, np.float64).reshape(-1, 2)
    if not len(r):
        return 0.0
    target = _CHI2_2_MEDIAN * min(max(dof_fraction, 0.05), 1.0)

    def median_chi2(s2: float) -> float:
        c = cov_px2 + s2 * np.eye(2)
        return float(np.median(np.einsum("ni,nij,nj->n", r, np.linalg.inv(c), r)))

    if median_chi2(0.0) <= target:
        return 0.0
    lo, hi = 0.0, float(np.max(np.sum(r * r, axis=1))) + 1e-12
    for _ in range(60):                   # bisection in log space: s0 to ~1e-6 relative
        mid = np.sqrt(max(lo, 1e-16 * hi) * hi)
        if median_chi2(mid) > target:
            lo = mid
        else:
            hi = mid
    return float(hi)


def weighted(obs: list[Observation]) -> bool:
    """Whether the corners of every observation carry covariances (then the problem is weighted by them)."""
    return bool(obs) and all(o.image_cov_px2 is not None for o in obs)


class _Problem:
    """The stacked inlier corners of every observation and their residuals and sparse Jacobian, whitened
    by the corners' covariances when ``whiten`` (|L^T r|^2 = r^T C^-1 r: each corner counts by how well
    the detector knows it), each widened by ``floor_px2`` on both axes (noise_floor_px2)."""

    def __init__(self, obs: list[Observation], masks: list[np.ndarray], layout: _Layout,
                 start: list[CameraModel], whiten: bool = False, floor_px2: float = 0.0) -> None:
        self.layout, self.start = layout, start
        keep = [(o, m) for o, m in zip(obs, masks) if m.any()]
        self.white = None
        if whiten:
            covs = [o.image_cov_px2 for o, _ in keep]
            if any(c is None for c in covs):    # the caller whitens only views that all carry covariances
                raise ValueError("whitening needs a covariance for every corner")
            cov = np.concatenate([c[m] for c, (_, m) in zip(covs, keep) if c is not None]) + floor_px2 * np.eye(2)
            self.white = np.transpose(np.linalg.cholesky(np.linalg.inv(cov)), (0, 2, 1))
        self.X = np.concatenate([o.object_mm[m] for o, m in keep])
        self.q = np.concatenate([o.image_px[m] for o, m in keep])
        self.cam = np.concatenate([np.full(int(m.sum()), o.camera) for o, m in keep])
        self.view = np.concatenate([np.full(int(m.sum()), o.view) for o, m in keep])
        self.view_start = np.array([s.start for s in layout.view_slice], dtype=np.int64)
        self._cache: tuple[bytes, np.ndarray, scipy.sparse.csr_matrix] | None = None

    @property
    def n_residuals(self) -> int:
        return 2 * len(self.X)

    def evaluate(self, x: np.ndarray) -> tuple[np.ndarray, scipy.sparse.csr_matrix]:
        """Residuals (2M,) reprojected - detected (px, or whitened) and their Jacobian (2M, n), sparse."""
        key = x.tobytes()
        if self._cache is not None and self._cache[0] == key:
            return self._cache[1], self._cache[2]
        lay = self.layout
        cams, _, _ = lay.unpack(x, self.start)
        rv = np.array([x[s] for s in lay.view_slice])
        Rv, dRv = _rotations(rv[:, :3])
        p_view = np.einsum("nij,nj->ni", Rv[self.view], self.X) + rv[self.view, 3:]
        dp_drvec = np.einsum("nkij,nj->nik", dRv[self.view], self.X)      # d(R_v X)/d rvec_v: (M, 3, 3)
        res = np.empty((len(self.X), 2))
        n_intr = len(lay.free_intr)
        n_cols = n_intr + 6 + (6 if lay.n_cameras > 1 else 0)
        vals = np.zeros((len(self.X), 2, n_cols))
        cols = np.zeros((len(self.X), n_cols), dtype=np.int64)
        for c in range(lay.n_cameras):
            sel = np.flatnonzero(self.cam == c)
            if not len(sel):
                continue
            pv = p_view[sel]
            if c == 0:
                p_cam, R_c0 = pv, np.eye(3)
            else:
                rig = x[lay.rig_slice[c - 1]]
                Rr, dRr = _rotations(rig[None, :3])
                R_c0 = Rr[0]
                p_cam = pv @ R_c0.T + rig[3:]
            q, dq_dp, dq_di = project(p_cam, cams[c], get_gradients=True)
            res[sel] = q - self.q[sel]
            vals[sel, :, :n_intr] = dq_di[:, :, lay.free_intr]
            cols[sel, :n_intr] = np.arange(lay.cam_slice[c].start, lay.cam_slice[c].stop)
            dq_dview = dq_dp @ R_c0
            vals[sel, :, n_intr:n_intr + 3] = dq_dview @ dp_drvec[sel]
            vals[sel, :, n_intr + 3:n_intr + 6] = dq_dview
            cols[sel, n_intr:n_intr + 6] = self.view_start[self.view[sel], None] + np.arange(6)
            if c > 0:
                vals[sel, :, n_intr + 6:n_intr + 9] = dq_dp @ np.einsum("kij,nj->nik", dRr[0], pv)
                vals[sel, :, n_intr + 9:] = dq_dp
                cols[sel, n_intr + 6:] = lay.rig_slice[c - 1].start + np.arange(6)
            elif n_cols > n_intr + 6:
                # camera 0 has no rig pose: point its unused entries at a real column with value 0
                cols[sel, n_intr + 6:] = cols[sel, :1]
        if self.white is not None:
            res = np.einsum("nij,nj->ni", self.white, res)
            vals = np.einsum("nij,njk->nik", self.white, vals)
        m = len(self.X)
        rows = np.repeat(np.arange(2 * m).reshape(m, 2), n_cols, axis=1).reshape(m, 2, n_cols)
        jac = scipy.sparse.csr_matrix((vals.ravel(), (rows.ravel(), np.repeat(cols[:, None, :], 2, axis=1).ravel())),
                                      shape=(2 * m, len(x)))
        r = res.ravel()
        self._cache = (key, r, jac)
        return r, jac

    def solve(self, x0: np.ndarray, huber_px: float | None) -> np.ndarray:
        """Minimise the (Huber-robust when ``huber_px``) sum of squared residuals from ``x0``."""
        # Small problems: the exact trust-region step on the dense Jacobian (a few iterations). Large ones keep
        # the Jacobian sparse and solve each step by LSMR, to a tolerance tight enough that the outer iteration
        # converges as fast (scipy's default 1e-8 leaves steps so inexact that 200 evaluations do not suffice).
        dense = self.n_residuals * len(x0) <= _DENSE_JACOBIAN_ENTRIES

        def residuals(p: np.ndarray) -> np.ndarray:
            return self.evaluate(p)[0]

        def jacobian(p: np.ndarray) -> np.ndarray | scipy.sparse.csr_matrix:
            jac = self.evaluate(p)[1]
            return jac.toarray() if dense else jac

        kw: dict = {"tr_solver": "exact"} if dense else {"tr_solver": "lsmr", "tr_options": {"atol": 1e-12,
                                                                                              "btol": 1e-12}}
        sol = least_squares(residuals, x0, jac=jacobian, method="trf",
                            loss="huber" if huber_px else "linear", f_scale=huber_px or 1.0, x_scale="jac",
                            ftol=_TOL, xtol=_TOL, gtol=_TOL, max_nfev=_MAX_NFEV, **kw)
        return sol.x


def _residual_norms(obs: list[Observation], layout: _Layout, start: list[CameraModel],
                    x: np.ndarray, whiten: bool = False, floor_px2: float = 0.0) -> list[np.ndarray]:
    """Per observation, (N, 2) reprojected - detected for every corner (outliers included); px, or in the
    corners' own sigmas (covariance + ``floor_px2``) when ``whiten``."""
    everything = [np.ones(len(o.object_mm), dtype=bool) for o in obs]
    r, _ = _Problem(obs, everything, layout, start, whiten, floor_px2).evaluate(x)
    out, k = [], 0
    for o in obs:
        out.append(r[2 * k:2 * (k + len(o.object_mm))].reshape(-1, 2).copy())
        k += len(o.object_mm)
    return out


def refine(observations: list[Observation], cameras: list[CameraModel], view_poses: list[RigidTransform],
           rig_poses: list[RigidTransform] | None = None, options: RefineOptions = RefineOptions()) -> RefineResult:
    """Refine cameras and poses from ``observations`` starting at the given values.

    The cameras are first put into the lens model of ``options.distortion`` (`as_lens`). Raises
    DegenerateInput when there are fewer residuals than unknowns or the distortion model is unknown.
    """
    rig_poses = list(rig_poses or [])
    if len(rig_poses) != len(cameras) - 1:
        raise ValueError("one rig pose is needed for every camera after the first")
    start = [as_lens(c, options.distortion) for c in cameras]
    layout = _Layout(start, len(view_poses), options.distortion, options.fix_principal_point)
    obs = [Observation(o.camera, o.view, np.asarray(o.object_mm, np.float64).reshape(-1, 3),
                       np.asarray(o.image_px, np.float64).reshape(-1, 2),
                       tuple(o.labels) or tuple(f"cam{o.camera} view{o.view} #{i}" for i in range(len(o.object_mm))),
                       o.image_cov_px2)
           for o in observations]
    # Weighted by the detector's corner covariances when every observation has them (a corners file
    # re-solved without them, or corners from elsewhere, weigh every corner alike).
    whiten = weighted(obs)
    huber = (HUBER_SIGMAS if whiten else options.loss_scale_px) if options.loss_scale_px else None
    masks = [np.ones(len(o.object_mm), dtype=bool) for o in obs]
    n_params = len(layout.names)
    if 2 * sum(len(o.object_mm) for o in obs) <= n_params:
        raise DegenerateInput(f"{sum(len(o.object_mm) for o in obs)} corners cannot determine {n_params} "
                              f"unknowns: more corners are needed")
    x = layout.pack(start, view_poses, rig_poses)
    dropped: list[str] = []

    def floor_of(x: np.ndarray) -> float:
        """The variance the inliers' covariances lack at ``x`` (noise_floor_px2); 0 unweighted."""
        if not whiten:
            return 0.0
        r = np.concatenate([res[m] for res, m in zip(_residual_norms(obs, layout, start, x), masks)])
        cov = np.concatenate([np.asarray(o.image_cov_px2)[m] for o, m in zip(obs, masks)])
        return noise_floor_px2(r, cov, 1.0 - n_params / max(2 * len(r), 1))

    # Robust pass: a few bad corners must not drag the solution before they can be identified. Weighted,
    # it is repeated once with the covariances widened by what the first fit shows they lack (the Huber
    # threshold and the outlier test are in sigmas: they mean something only on a scale the corners follow).
    x = _Problem(obs, masks, layout, start, whiten).solve(x, huber)
    floor = floor_of(x)
    if floor > 0.0:
        x = _Problem(obs, masks, layout, start, whiten, floor).solve(x, huber)
    for _ in range(options.max_rounds):
        floor = floor_of(x)
        norms = [np.linalg.norm(r, axis=1) for r in _residual_norms(obs, layout, start, x)]
        # Outliers are judged in the corners' own sigmas when weighted: a corner known to be noisy is not
        # an outlier for being noisy; it must also be outlier_min_px off.
        units = ([np.linalg.norm(r, axis=1) for r in _residual_norms(obs, layout, start, x, True, floor)]
                 if whiten else norms)
        inlier_norms = np.concatenate([n[m] for n, m in zip(units, masks)])
        # Per-corner residual norms of 2-D Gaussian noise follow a Rayleigh law: median = 1.1774 sigma.
        sigma = float(np.median(inlier_norms)) / 1.1774
        limit = (options.outlier_sigmas * sigma if whiten
                 else max(options.outlier_min_px, options.outlier_sigmas * sigma))
        changed = False
        for o, n, u, m in zip(obs, norms, units, masks):
            bad = m & (u > limit) & (n > options.outlier_min_px)
            for i in np.flatnonzero(bad):
                dropped.append(f"{o.labels[i]}: residual {n[i]:.2f} px" + (
                    f" = {u[i]:.1f} sigma > {limit:.1f} sigma" if whiten else f" > {limit:.2f} px"))
            if bad.any():
                m &= ~bad
                changed = True
        if 2 * sum(int(m.sum()) for m in masks) <= n_params:
            raise DegenerateInput("too many corners were rejected as outliers to determine the calibration")
        x = _Problem(obs, masks, layout, start, whiten, floor).solve(x, None)
        if not changed:
            break

    # The covariance of the weighted problem: s2 (J_w^T J_w)^-1, s2 the whitened residual's chi^2 per degree
    # of freedom (about 1 when the corner model, widened by the floor, is right; it scales the model by what
    # the fit shows).
    r, j = _Problem(obs, masks, layout, start, whiten, floor).evaluate(x)
    r_px = _Problem(obs, masks, layout, start).evaluate(x)[0] if whiten else r
    dof = max(len(r) - n_params, 1)
    s2 = float(r @ r) / dof
    jtj = (j.T @ j).toarray()
    # Scale columns before inverting: fx ~ 1e3 and k1 ~ 1e-1 live in one matrix.
    d = np.sqrt(np.maximum(np.diag(jtj), 1e-300))
    jtj_n = jtj / np.outer(d, d)
    eig, vec = np.linalg.eigh(jtj_n)
    rank_deficient = bool(eig[0] < 1e-12 * eig[-1])
    undetermined: list[str] = []
    if rank_deficient:
        cov = np.full((n_params, n_params), np.inf)
        for k in np.flatnonzero(eig < 1e-12 * eig[-1]):
            undetermined += [layout.names[i] for i in np.flatnonzero(np.abs(vec[:, k]) > 0.3)]
        undetermined = sorted(set(undetermined))
    else:
        cov = s2 * (vec / eig) @ vec.T / np.outer(d, d)
    std = np.sqrt(np.abs(np.diag(cov)))
    cams, views, rigs = layout.unpack(x, start)
    residuals = _residual_norms(obs, layout, start, x)
    inliers = [m.copy() for m in masks]
    rms = float(np.sqrt(np.mean(np.sum(r_px.reshape(-1, 2) ** 2, axis=1))))
    return RefineResult(cams, views, rigs, list(layout.names), x, std, cov, rms,
                        float(np.sqrt(float(r_px @ r_px) / dof)),
                        residuals, inliers, dropped, rank_deficient, undetermined, float(np.sqrt(floor)))


def observations_for(corners: list[list[CornerSet]], view_ids: list[int] | list[str] | None = None
                     ) -> list[Observation]:
    """One Observation per camera and view of ``corners[camera][view]`` (empty sets are skipped).

    ``view_ids`` name the views in corner labels (their file names, or numbers); default 0, 1, ...
    """
    names = CAMERA_NAMES if len(corners) == 2 else ("camera",)
    multi = max(len(c) for c in corners) > 1
    ids = view_ids if view_ids is not None else list(range(max(len(c) for c in corners)))
    return [Observation(c, v, cs.object_mm, cs.image_px, cs.labels(names[c], ids[v] if multi else None),
                        cs.image_cov_px2)
            for c, per_view in enumerate(corners) for v, cs in enumerate(per_view) if len(cs)]


def calibration_from_result(kind: str, image_size: tuple[int, int], corners: list[list[CornerSet]],
                            result: RefineResult) -> Calibration:
    """Package a RefineResult (made from ``observations_for(corners)``) as a Calibration."""
    n_cams = len(corners)
    camera_std = []
    for c in range(n_cams):
        camera_std.append({n: result.std_of(f"cam{c}.{n}") for n in result.cameras[c].intrinsic_names})
    residuals: list[list[np.ndarray]] = [[np.zeros((0, 2)) for _ in per_view] for per_view in corners]
    inliers: list[list[np.ndarray]] = [[np.zeros(0, dtype=bool) for _ in per_view] for per_view in corners]
    k = 0
    for c, per_view in enumerate(corners):
        for v, cs in enumerate(per_view):
            if len(cs):
                residuals[c][v], inliers[c][v] = result.residuals[k], result.inliers[k]
                k += 1
    size = (int(image_size[0]), int(image_size[1]))
    cameras = [replace(c, image_size=size) for c in result.cameras]
    cal = Calibration(kind, size, cameras, camera_std,
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
    cal.noise_floor_px = result.noise_floor_px
    covs = [cs.image_cov_px2 for per_view in corners for cs in per_view if len(cs) and cs.image_cov_px2 is not None]
    if covs and result.noise_floor_px > 0.0:
        corner_sigma = float(np.median(np.sqrt(0.5 * np.trace(np.concatenate(covs), axis1=1, axis2=2))))
        if result.noise_floor_px > corner_sigma:
            cal.notes.append(f"the corners scatter more than the detector's covariances say (median corner sigma "
                             f"{corner_sigma:.3f} px): {result.noise_floor_px:.3f} px per axis was added to every "
                             f"corner's covariance (lens, focus, compression, a board that is not flat)")
    cal.undetermined = [f"{cal.camera_names[int(n[3])]} {n.split('.', 1)[1]}" if n.startswith("cam") else n
                        for n in result.undetermined]
    if result.rank_deficient:
        which = f" ({', '.join(result.undetermined)})" if result.undetermined else ""
        cal.notes.append(f"the corners do not determine every parameter{which} (rank-deficient Jacobian): "
                         "standard deviations are infinite; show more of the target or fit a simpler lens model")
    return cal
