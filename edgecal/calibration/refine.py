"""Non-linear refinement of cameras and poses, robust to outliers, with parameter standard deviations.

One solver serves every case: observations of a target by one or two cameras in one or more views (the
problem itself, its unknowns and its sparse Jacobian: edgecal.calibration.problem). One box image from
each of two cameras is one view seen by two cameras; the planar multi-view case has many views.

After a robust (Huber) fit, corners whose residual is far outside the noise are dropped and reported, the
rest is fitted with plain least squares, and the covariance is s^2 (J^T J)^-1 with s^2 = SSR / (m - n).
When every corner carries the detector's covariance the residuals are whitened by it, widened by the
noise floor the fit shows (noise_floor_px2).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import scipy.sparse

from edgecal.calibration.checks import DegenerateInput
from edgecal.calibration.problem import (
    POSE_NAMES,
    Layout,
    Observation,
    Problem,
    lens_of,
    residual_norms,
    weighted,
)
from edgecal.calibration.types import (
    CAMERA_NAMES,
    Calibration,
    CornerSet,
    RigidTransform,
)
from edgecal.camera import DISTORTION_MODELS, LENS_PARAMS, CameraModel
from edgecal.config import setting

__all__ = ["DISTORTION_CHOICES", "HUBER_SIGMAS", "Observation", "RefineOptions", "RefineResult", "as_lens",
           "calibration_from_result", "lens_of", "noise_floor_px2", "observations_for", "refine"]

# Every lens model a calibration can fit, and "auto" (edgecal.calibration.lens_choice picks one).
DISTORTION_CHOICES = (*DISTORTION_MODELS, "auto")


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


def _parameter_covariance(jac: scipy.sparse.csr_matrix, s2: float, names: list[str]
                          ) -> tuple[np.ndarray, bool, list[str]]:
    """s2 (J^T J)^-1, whether J is rank-deficient (then the covariance is all inf) and the names of the
    parameters in its null space."""
    jtj = (jac.T @ jac).toarray()
    # Scale columns before inverting: fx ~ 1e3 and k1 ~ 1e-1 live in one matrix.
    d = np.sqrt(np.maximum(np.diag(jtj), 1e-300))
    eig, vec = np.linalg.eigh(jtj / np.outer(d, d))
    null = np.flatnonzero(eig < 1e-12 * eig[-1])
    if len(null):
        return (np.full(jtj.shape, np.inf), True,
                sorted({names[i] for k in null for i in np.flatnonzero(np.abs(vec[:, k]) > 0.3)}))
    return s2 * (vec / eig) @ vec.T / np.outer(d, d), False, []


def _drop_outliers(obs: list[Observation], norms: list[np.ndarray], units: list[np.ndarray],
                   masks: list[np.ndarray], options: RefineOptions, whiten: bool
                   ) -> tuple[list[np.ndarray], list[str]]:
    """The inlier masks without the corners whose residual is outside the noise, and a line for each dropped.

    ``norms`` are the residual norms in px per observation, ``units`` the same in the corners' own sigmas when
    weighted (else ``norms``): a corner known to be noisy is not an outlier for being noisy; it must also be
    outlier_min_px off.
    """
    inlier_norms = np.concatenate([n[m] for n, m in zip(units, masks)])
    # Per-corner residual norms of 2-D Gaussian noise follow a Rayleigh law: median = 1.1774 sigma.
    sigma = float(np.median(inlier_norms)) / 1.1774
    limit = (options.outlier_sigmas * sigma if whiten
             else max(options.outlier_min_px, options.outlier_sigmas * sigma))
    kept, dropped = [], []
    for o, n, u, m in zip(obs, norms, units, masks):
        bad = m & (u > limit) & (n > options.outlier_min_px)
        for i in np.flatnonzero(bad):
            dropped.append(f"{o.labels[i]}: residual {n[i]:.2f} px" + (
                f" = {u[i]:.1f} sigma > {limit:.1f} sigma" if whiten else f" > {limit:.2f} px"))
        kept.append(m & ~bad)
    return kept, dropped


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
    layout = Layout(start, len(view_poses), options.distortion, options.fix_principal_point)
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
        r = np.concatenate([res[m] for res, m in zip(residual_norms(obs, layout, start, x), masks)])
        cov = np.concatenate([np.asarray(o.image_cov_px2)[m] for o, m in zip(obs, masks)])
        return noise_floor_px2(r, cov, 1.0 - n_params / max(2 * len(r), 1))

    # Robust pass: a few bad corners must not drag the solution before they can be identified. Weighted,
    # it is repeated once with the covariances widened by what the first fit shows they lack (the Huber
    # threshold and the outlier test are in sigmas: they mean something only on a scale the corners follow).
    x = Problem(obs, masks, layout, start, whiten).solve(x, huber)
    floor = floor_of(x)
    if floor > 0.0:
        x = Problem(obs, masks, layout, start, whiten, floor).solve(x, huber)
    for _ in range(options.max_rounds):
        floor = floor_of(x)
        norms = [np.linalg.norm(r, axis=1) for r in residual_norms(obs, layout, start, x)]
        units = ([np.linalg.norm(r, axis=1) for r in residual_norms(obs, layout, start, x, True, floor)]
                 if whiten else norms)
        masks, newly_dropped = _drop_outliers(obs, norms, units, masks, options, whiten)
        dropped += newly_dropped
        if 2 * sum(int(m.sum()) for m in masks) <= n_params:
            raise DegenerateInput("too many corners were rejected as outliers to determine the calibration")
        x = Problem(obs, masks, layout, start, whiten, floor).solve(x, None)
        if not newly_dropped:
            break

    # The covariance of the weighted problem: s2 (J_w^T J_w)^-1, s2 the whitened residual's chi^2 per degree
    # of freedom (about 1 when the corner model, widened by the floor, is right; it scales the model by what
    # the fit shows).
    r, j = Problem(obs, masks, layout, start, whiten, floor).evaluate(x)
    r_px = Problem(obs, masks, layout, start).evaluate(x)[0] if whiten else r
    dof = max(len(r) - n_params, 1)
    cov, rank_deficient, undetermined = _parameter_covariance(j, float(r @ r) / dof, layout.names)
    std = np.sqrt(np.abs(np.diag(cov)))
    cams, views, rigs = layout.unpack(x, start)
    residuals = residual_norms(obs, layout, start, x)
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
