"""The least-squares problem of a calibration: where each unknown sits, the residuals and their Jacobian.

The unknowns are each camera's intrinsics (fx, fy, cx, cy and the free parameters of its lens model,
edgecal.camera.DISTORTION_MODELS), each view's target pose in camera 0 (``T_cam0_target``) and, for
each further camera c, the rig pose ``T_camc_cam0``. Camera c sees target points at
``R_c0 (R_v X + t_v) + t_c0``.

Each residual depends only on its camera's intrinsics, its view's pose and its rig pose, so the Jacobian
is explicit and sparse: 300 stereo views give one that is 99 % zeros (a dense one of 900 views would need
~8 GB). The derivatives are analytic (edgecal.camera.project's gradients and cv2.Rodrigues'). The solver
is scipy's least_squares (trust-region reflective); the strategy around it (robust pass, outliers,
covariance) is edgecal.calibration.refine's.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import scipy.sparse
from scipy.optimize import least_squares

from edgecal.calibration.checks import DegenerateInput
from edgecal.calibration.types import RigidTransform
from edgecal.camera import DISTORTION_MODELS, LENS_PARAMS, CameraModel, project

POSE_NAMES = ("rx", "ry", "rz", "tx", "ty", "tz")

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


def lens_of(distortion: str) -> tuple[str, tuple[str, ...]]:
    """(lens model, free parameters) of a distortion option; DegenerateInput listing the known ones if unknown."""
    if distortion not in DISTORTION_MODELS:
        raise DegenerateInput(f"distortion model {distortion!r} unknown (one of {', '.join(DISTORTION_MODELS)})")
    return DISTORTION_MODELS[distortion]



class Layout:
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
        """The parameter vector of cameras, view poses and rig poses (only each camera's free intrinsics)."""
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
        """Cameras, view poses and rig poses of ``x``; the intrinsics that are not free keep ``start``'s."""
        cams = []
        for c in range(self.n_cameras):
            full = start[c].intrinsics.copy()   # fixed terms keep their start value (0 outside the model)
            full[self.free_intr] = x[self.cam_slice[c]]
            cams.append(start[c].with_intrinsics(full))
        views = [RigidTransform(x[s][:3].copy(), x[s][3:].copy()) for s in self.view_slice]
        rigs = [RigidTransform(x[s][:3].copy(), x[s][3:].copy()) for s in self.rig_slice]
        return cams, views, rigs


def rotations(rvecs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation matrices (K, 3, 3) of rotation vectors (K, 3) and dR/drvec as (K, 3 [rvec], 3, 3)."""
    R = np.empty((len(rvecs), 3, 3))
    dR = np.empty((len(rvecs), 3, 3, 3))
    for i, r in enumerate(rvecs):
        m, j = cv2.Rodrigues(r.reshape(3, 1))
        R[i], dR[i] = m, j.reshape(3, 3, 3)
    return R, dR


def weighted(obs: list[Observation]) -> bool:
    """Whether the corners of every observation carry covariances (then the problem is weighted by them)."""
    return bool(obs) and all(o.image_cov_px2 is not None for o in obs)


class Problem:
    """The stacked inlier corners of every observation and their residuals and sparse Jacobian, whitened
    by the corners' covariances when ``whiten`` (|L^T r|^2 = r^T C^-1 r: each corner counts by how well
    the detector knows it), each widened by ``floor_px2`` on both axes (noise_floor_px2)."""

    def __init__(self, obs: list[Observation], masks: list[np.ndarray], layout: Layout,
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
        """Two residuals (x, y) per corner."""
        return 2 * len(self.X)

    def evaluate(self, x: np.ndarray) -> tuple[np.ndarray, scipy.sparse.csr_matrix]:
        """Residuals (2M,) reprojected - detected (px, or whitened) and their Jacobian (2M, n), sparse."""
        key = x.tobytes()
        if self._cache is not None and self._cache[0] == key:
            return self._cache[1], self._cache[2]
        lay = self.layout
        cams, _, _ = lay.unpack(x, self.start)
        rv = np.array([x[s] for s in lay.view_slice])
        Rv, dRv = rotations(rv[:, :3])
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
                Rr, dRr = rotations(rig[None, :3])
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


def residual_norms(obs: list[Observation], layout: Layout, start: list[CameraModel],
                    x: np.ndarray, whiten: bool = False, floor_px2: float = 0.0) -> list[np.ndarray]:
    """Per observation, (N, 2) reprojected - detected for every corner (outliers included); px, or in the
    corners' own sigmas (covariance + ``floor_px2``) when ``whiten``."""
    everything = [np.ones(len(o.object_mm), dtype=bool) for o in obs]
    r, _ = Problem(obs, everything, layout, start, whiten, floor_px2).evaluate(x)
    out, k = [], 0
    for o in obs:
        out.append(r[2 * k:2 * (k + len(o.object_mm))].reshape(-1, 2).copy())
        k += len(o.object_mm)
    return out
