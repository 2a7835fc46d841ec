"""From the detections of one stereo frame to T_rig_robot: match, triangulate, fit, refine, check."""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from edgecal.camera import StereoRig, undistort_points
from edgecal.detection.corner_covariance import LIGHT_SHIFT_PX2
from edgecal.detection.types import Detection
from edgecal.geometry import triangulate_pixels
from edgecal.pose.predict import MIN_FACING_COS, camera_from_rig, facing_cos
from edgecal.pose.refine import CameraView, model_covariance, pose_covariance, refine_pose, whitening
from edgecal.pose.rigid import fit_rigid, is_degenerate
from edgecal.pose.types import Pose, PoseSettings
from edgecal.targets import Target

# The errors corners share, which do not average out over them as independent errors do and which a fit's
# residual cannot see (a bias the pose absorbs; see the README, "Live pose"):
# - each board's in each camera (corner_covariance.SHARED_FRACTION: the light field, blur and perspective over
#   a board bias its corners alike), modelled as an affine error of its corners - an offset and a linear map
#   about their centroid, in px at the corners' RMS distance from it - with the variance its corners'
#   shared_px2 say per parameter;
# - an offset common to every corner of the frame, in both cameras, along the light field's gradient: a light
#   field lights the boards from one side and both cameras see it alike, so the shift it puts on all corners
#   (corner_covariance.LIGHT_SHIFT_PX2 x grad log L) moves the whole robot sideways. Without it the searched
#   pose of the robot sequence with a strong light gradient (bench/live.py --scene other) had x and y errors
#   of 1.6 and 1.3 sigma and mean NEES 21.8;
# - each board's light shift in the checkerboard pattern of its corners (Detection.alternating_px2: the
#   X-junction fit's corners move with their polarity), which cancels over neighbouring corners: weighted
#   as independent errors instead, the other rig's searched pose had sigma 1.4x too large (mean NEES 2.7).


def unambiguous_detections(detections: Sequence[Detection], target: Target) -> list[Detection]:
    """The detections of boards the target knows that are seen once in the image.

    A board found twice in one image (``copy`` 1, 2, ...: another board of the same size) cannot say which of
    the two is the robot's: both are left out, rather than mixing their corners under one name.
    """
    names = {b.name for b in target.boards}
    seen: dict[str, int] = {}
    for det in detections:
        seen[det.board] = seen.get(det.board, 0) + 1
    return [det for det in detections if det.board in names and seen[det.board] == 1]


def corner_table(detections: Sequence[Detection], target: Target) -> dict[tuple[str, int, int], np.ndarray]:
    """(board, col, row) -> pixel (2,) for every usable detected corner of a board the target knows."""
    table: dict[tuple[str, int, int], np.ndarray] = {}
    for det in unambiguous_detections(detections, target):
        px = np.asarray(det.corners, dtype=np.float64).reshape(-1, 2)
        for (c, r), row, ok in zip(np.asarray(det.ids).reshape(-1, 2).tolist(), px, det.usable().tolist()):
            if ok:
                table[(det.board, c, r)] = row
    return table


def corner_covariances(detections: Sequence[Detection], target: Target
                       ) -> dict[tuple[str, int, int], tuple[np.ndarray, float, np.ndarray, float]]:
    """(board, col, row) -> (the detector's 2x2 covariance (px^2), its board's shared part (px^2 per axis),
    the light gradient there (2,), 1/px, its board's alternating part (px^2 per axis); zero when the
    detection has none) of every usable corner that has a covariance."""
    table: dict[tuple[str, int, int], tuple[np.ndarray, float, np.ndarray, float]] = {}
    for det in unambiguous_detections(detections, target):
        if det.covariance is None:
            continue
        n = len(det.corners)
        shared = [0.0] * n if det.shared_px2 is None else det.shared_px2.tolist()
        light = np.zeros((n, 2)) if det.light_gradient is None else det.light_gradient
        alternating = [0.0] * n if det.alternating_px2 is None else det.alternating_px2.tolist()
        # ids and flags as Python lists: one conversion, not one per corner
        for (c, r), cov, shared_px2, g, alt, ok in zip(np.asarray(det.ids).reshape(-1, 2).tolist(), det.covariance,
                                                       shared, light, alternating, det.usable().tolist()):
            if ok:
                table[(det.board, c, r)] = (cov, shared_px2, g, alt)
    return table


def robot_points_m(target: Target, keys: Sequence[tuple[str, int, int]]) -> np.ndarray:
    """Robot-frame (target-frame) positions in metres of corners named (board, col, row)."""
    if not keys:
        return np.zeros((0, 3))
    out = np.empty((len(keys), 3))
    by_board: dict[str, list[int]] = {}
    for i, (b, _, _) in enumerate(keys):
        by_board.setdefault(b, []).append(i)
    for b, idx in by_board.items():
        ids = np.array([[keys[i][1], keys[i][2]] for i in idx], dtype=np.int64)
        out[idx] = target.board(b).target_points_mm(ids) / 1000.0
    return out


def _covariances(keys: list, covs: dict, noise_px: float
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Of the corners ``keys``: (N, 2, 2) covariances less their alternating part (what the fit weighs by),
    (N,) shared parts, (N, 2) light gradients and (N,) alternating parts: the detector's, else ``noise_px``
    on both axes and none of the others."""
    fallback = (np.eye(2) * noise_px ** 2, 0.0, np.zeros(2), 0.0)
    rows = [covs.get(k, fallback) for k in keys]
    alternating = np.array([r[3] for r in rows], dtype=np.float64)
    cov = np.array([r[0] for r in rows]).reshape(-1, 2, 2) - alternating[:, None, None] * np.eye(2)
    return (cov, np.array([r[1] for r in rows], dtype=np.float64),
            np.array([r[2] for r in rows], dtype=np.float64).reshape(-1, 2), alternating)


def _views(rig: StereoRig, target: Target, left: dict, right: dict, covs: tuple[dict, dict] = ({}, {}),
           noise_px: float = 0.1) -> tuple[CameraView, CameraView]:
    kl, kr = sorted(left), sorted(right)
    vl = CameraView(rig.left, np.eye(3), np.zeros(3), robot_points_m(target, kl),
                    np.array([left[k] for k in kl]).reshape(-1, 2), *_covariances(kl, covs[0], noise_px))
    vr = CameraView(rig.right, rig.R_right_left, rig.t_right_left_m, robot_points_m(target, kr),
                    np.array([right[k] for k in kr]).reshape(-1, 2), *_covariances(kr, covs[1], noise_px))
    return vl, vr


def shared_error(xy: np.ndarray, shared_px2: np.ndarray, groups: np.ndarray, light: np.ndarray,
                 alternating_px2: np.ndarray | None = None, parity: np.ndarray | None = None
                 ) -> tuple[np.ndarray, np.ndarray]:
    """The errors corners share (LIGHT_SHIFT_PX2, corner_covariance.SHARED_FRACTION and XJUNCTION_LIGHT_PX)
    as K = 2 + 8 G parameters over all M corners: their basis (M, 2, K) - the common offset along the
    eigenvectors of its covariance, then per group (a board in one camera) its affine error: offset x, y, the
    linear map's four entries times the corner's offset from the group's centroid over their RMS distance -
    and its alternating shift x, y (times the corner's ``parity``, +1 or -1 by (col + row) mod 2) - and their
    variances (K,) px^2. xy (M, 2) pixels, shared_px2 (M,) the corners' shared parts, groups (M,) 0..G-1,
    light (M, 2) the gradient of log light at each corner (1/px), alternating_px2 (M,) the corners'
    alternating parts (default none)."""
    m = len(xy)
    n_groups = int(groups.max()) + 1 if m else 0
    n = np.maximum(np.bincount(groups, minlength=n_groups), 1)
    sums = np.stack([np.bincount(groups, weights=xy[:, 0], minlength=n_groups),
                     np.bincount(groups, weights=xy[:, 1], minlength=n_groups)], axis=1)
    d = xy - (sums / n[:, None])[groups]
    radius = np.sqrt(np.bincount(groups, weights=np.sum(d * d, axis=1), minlength=n_groups) / n)
    q = d / np.maximum(radius, 1e-9)[groups][:, None]
    basis = np.zeros((m, 2, 2 + 8 * n_groups))
    var = np.zeros(2 + 8 * n_groups)
    if m:
        # the common offset's covariance kappa^2 mean(g g^T), in its eigenbasis (uncorrelated parameters)
        w, v = np.linalg.eigh(LIGHT_SHIFT_PX2 ** 2 * np.einsum("ni,nj->ij", light, light) / m)
        basis[:, :, :2] = v[None, :, :]
        var[:2] = np.maximum(w, 0.0)
    rows = np.arange(m)
    col = 2 + 8 * groups
    basis[rows, 0, col] = basis[rows, 1, col + 1] = 1.0
    basis[rows, 0, col + 2], basis[rows, 0, col + 3] = q[:, 0], q[:, 1]
    basis[rows, 1, col + 4], basis[rows, 1, col + 5] = q[:, 0], q[:, 1]
    per_group = var[2:].reshape(n_groups, 8)
    per_group[:, :6] = (np.bincount(groups, weights=shared_px2, minlength=n_groups) / n)[:, None]
    if alternating_px2 is not None and parity is not None:
        basis[rows, 0, col + 6] = basis[rows, 1, col + 7] = parity
        per_group[:, 6:] = (np.bincount(groups, weights=alternating_px2, minlength=n_groups) / n)[:, None]
    return basis, var


def _fit_covariance(J: np.ndarray, res: np.ndarray, views: list[CameraView], tl: dict, tr: dict,
                    settings: PoseSettings) -> np.ndarray:
    """The pose covariance per settings.covariance_scale ("model": the corner model and the shared errors,
    shared_error; "residual", "noise", "max": an isotropic corner sigma, see pose_covariance)."""
    if settings.covariance_scale != "model":
        return pose_covariance(J, res, settings.covariance_scale, settings.corner_noise_px)
    # Groups: a board in one camera, in the residuals' order (left view, then right view; keys sorted).
    keys = [("left", k) for k in sorted(tl)] + [("right", k) for k in sorted(tr)]
    _, groups = np.unique(np.array([f"{side}/{k[0]}" for side, k in keys]), return_inverse=True)
    cov_px2 = np.concatenate([v.image_covariance_px2 for v in views])
    shared = np.concatenate([np.zeros(v.n) if v.image_shared_px2 is None else v.image_shared_px2 for v in views])
    light = np.concatenate([np.zeros((v.n, 2)) if v.image_light_gradient is None else v.image_light_gradient
                            for v in views])
    alternating = np.concatenate([np.zeros(v.n) if v.image_alternating_px2 is None else v.image_alternating_px2
                                  for v in views])
    parity = np.array([1.0 - 2.0 * ((k[1] + k[2]) % 2) for _side, k in keys])
    xy = np.concatenate([v.image_points_px for v in views])
    basis, var = shared_error(xy, shared, groups, light, alternating, parity)
    return model_covariance(J, cov_px2, np.zeros(len(xy), dtype=np.int64), basis, var[None, :])


def _pnp(view: CameraView) -> tuple[np.ndarray, np.ndarray] | None:
    """T_cam_robot from one camera's corners (SQPnP handles planar and non-planar layouts)."""
    if view.n < 4:
        return None
    # on ideal normalised coordinates, so every lens model (fisheye too) is one pinhole problem for OpenCV
    xn = undistort_points(view.image_points_px, view.camera)
    keep = np.all(np.isfinite(xn), axis=1)
    if keep.sum() < 4:
        return None
    ok, rvec, tvec = cv2.solvePnP(view.object_points_m[keep], xn[keep], np.eye(3), None, flags=cv2.SOLVEPNP_SQPNP)
    if not ok:
        return None
    R, _ = cv2.Rodrigues(rvec)
    return R, tvec.ravel()


def initial_pose(cams: StereoRig, target: Target, left: dict, right: dict, vl: CameraView, vr: CameraView,
                 settings: PoseSettings) -> tuple[np.ndarray, np.ndarray, str] | None:
    """A starting T_rig_robot: triangulation + rigid fit when enough corners are shared, else PnP."""
    both = sorted(set(left) & set(right))
    if len(both) >= 4:
        X_rig = triangulate_pixels(cams, np.array([left[k] for k in both]), np.array([right[k] for k in both]),
                                   optimal=settings.triangulation == "optimal")
        X_robot = robot_points_m(target, both)
        if np.all(np.isfinite(X_rig)) and not is_degenerate(X_robot):
            R, t = fit_rigid(X_robot, X_rig)
            return R, t, "stereo"
    best = max((vl, vr), key=lambda v: v.n)
    sol = _pnp(best)
    if sol is None:
        return None
    R_c, t_c = sol
    if best is vl:
        return R_c, t_c, "mono-left"
    # T_rig_robot = T_right_left^-1 * T_right_robot
    Rrl, Trl = cams.R_right_left, cams.t_right_left_m
    return Rrl.T @ R_c, Rrl.T @ (t_c - Trl), "mono-right"


def check_quality(pose: Pose, settings: PoseSettings) -> Pose:
    """Mark ``pose`` invalid, naming the first bound it fails; return it."""
    b = settings.bounds
    problems = []
    if pose.n_corners < b.min_corners:
        problems.append(f"only {pose.n_corners} corners (min_corners {b.min_corners})")
    if not np.isfinite(pose.rms_px) or pose.rms_px > b.max_rms_px:
        problems.append(f"reprojection RMS {pose.rms_px:.3g} px > max_rms_px {b.max_rms_px}")
    if not np.all(np.isfinite(pose.covariance)):
        problems.append("covariance undetermined (degenerate corner layout)")
    else:
        if pose.position_std_mm > b.max_position_std_mm:
            problems.append(f"position std {pose.position_std_mm:.3g} mm > max_position_std_mm "
                            f"{b.max_position_std_mm}")
        if pose.rotation_std_deg > b.max_rotation_std_deg:
            problems.append(f"rotation std {pose.rotation_std_deg:.3g} deg > max_rotation_std_deg "
                            f"{b.max_rotation_std_deg}")
    if problems:
        pose.valid = False
        pose.reason = "; ".join(problems)
    return pose


# Rayleigh median: the median length of a 2-D residual with sigma per axis is sigma * sqrt(2 ln 2).
_RAYLEIGH_MEDIAN = 1.1774
# At most this share of the corners is rejected one by one; beyond it the fit itself is wrong (a misread
# board), which the board-level rejection of estimate_pose handles.
MAX_OUTLIER_SHARE = 0.25


def corner_outliers(residuals: np.ndarray, sigmas: float, min_px: float,
                    cov_px2: np.ndarray | None = None) -> np.ndarray:
    """Which corners (residuals stacked as x, y per corner) lie beyond ``sigmas`` robust sigmas and ``min_px``.

    The robust sigma comes from the median residual length, so a few gross outliers do not inflate it.
    With the corners' covariances (M, 2, 2) the residuals are compared in their own units (whitened): a
    corner the detector knows to be noisy is not an outlier for being noisy.
    """
    norms = np.hypot(residuals[0::2], residuals[1::2])
    if norms.size == 0:
        return np.zeros(0, dtype=bool)
    if cov_px2 is None:
        threshold = max(min_px, sigmas * float(np.median(norms)) / _RAYLEIGH_MEDIAN)
        return norms > threshold
    white = np.linalg.norm(np.einsum("nij,nj->ni", whitening(cov_px2), residuals.reshape(-1, 2)), axis=1)
    return (white > sigmas * float(np.median(white)) / _RAYLEIGH_MEDIAN) & (norms > min_px)


def _estimate(tl: dict, tr: dict, target: Target, cams: StereoRig, settings: PoseSettings,
              start_pose: Pose | None = None, covs: tuple[dict, dict] = ({}, {})) -> Pose:
    """One fit over the corner tables of the left and right images (see estimate_pose).

    The refinement starts from ``start_pose`` when given (its mode is kept), else from initial_pose, and
    weighs each corner by its covariance in ``covs`` (left, right; corner_covariances), or by
    settings.corner_noise_px when it has none. After the refinement, single corners that reproject far worse than
    the rest (corner_outliers) are left out and the pose is refined again from where it is, a few rounds at most.
    """
    if not tl and not tr:
        return Pose.invalid("no board detected", n_left=0, n_right=0, n_both=0)
    vl, vr = _views(cams, target, tl, tr, covs, settings.corner_noise_px)
    start = (initial_pose(cams, target, tl, tr, vl, vr, settings) if start_pose is None
             else (start_pose.R, start_pose.t_m, start_pose.mode))
    if start is None:
        return Pose.invalid(f"too few corners for a pose ({len(tl)} left, {len(tr)} right)", n_left=len(tl),
                            n_right=len(tr), n_both=len(set(tl) & set(tr)))
    R, t, mode = start
    total = len(tl) + len(tr)
    outliers = 0
    for _round in range(4):
        # Mono: the other camera's few corners (fewer than 4 shared) still help, but only if they agree.
        views = [v for v in (vl, vr) if v.n > 0]
        try:
            R, t, res, J = refine_pose(R, t, views)
        except ValueError:
            # refine_pose refuses a start that puts corners behind a camera (no projection there), e.g.
            # a rigid fit to a misread board while boards are tried one by one: no pose from this start.
            return Pose.invalid("no pose: the starting pose puts corners behind a camera", mode,
                                n_left=len(tl), n_right=len(tr), n_both=len(set(tl) & set(tr)))
        bad = corner_outliers(res, settings.outlier_sigmas, settings.outlier_min_px,
                              np.concatenate([v.image_covariance_px2 for v in views]))
        if _round == 3 or not bad.any() or outliers + int(bad.sum()) > MAX_OUTLIER_SHARE * total:
            break
        keys = sorted(tl) + sorted(tr)          # the residuals' order: left view, then right view
        drop_left = {keys[i] for i in np.nonzero(bad[:len(tl)])[0]}
        drop_right = {keys[len(tl) + i] for i in np.nonzero(bad[len(tl):])[0]}
        tl = {k: v for k, v in tl.items() if k not in drop_left}
        tr = {k: v for k, v in tr.items() if k not in drop_right}
        outliers += int(bad.sum())
        vl, vr = _views(cams, target, tl, tr, covs, settings.corner_noise_px)
    rms = float(np.sqrt(np.mean(res ** 2))) if len(res) else float("nan")
    cov = _fit_covariance(J, res, views, tl, tr, settings)
    boards = tuple(sorted({k[0] for k in tl} | {k[0] for k in tr}))
    pose = Pose(R, t, cov, mode, True, "", rms, n_left=len(tl), n_right=len(tr), n_both=len(set(tl) & set(tr)),
                boards=boards, outliers=outliers)
    return check_quality(pose, settings)


def _without(table: dict, boards: set[str]) -> dict:
    """The corner table less every corner of ``boards``."""
    return {k: v for k, v in table.items() if k[0] not in boards}


def estimate_pose(left: Sequence[Detection], right: Sequence[Detection], target: Target, cams: StereoRig,
                  settings: PoseSettings = PoseSettings(), max_rejected: int = 2) -> Pose:
    """T_rig_robot from the detections of the left and right images of one stereo frame.

    Corners seen by both cameras are triangulated and fitted rigidly for a start; with fewer than four
    shared corners the camera that saw more is used alone (PnP). The pose is then refined over every
    corner either camera saw, its covariance computed, and the quality bounds applied.

    When the RMS bound fails, one board in one camera is probably not what its name says (a grid the
    detector misread or misnamed). Each board view is left out in turn and the pose fitted without it; the
    best of those fits is kept - a valid one with the most corners, else the lowest RMS - up to
    ``max_rejected`` times (``Pose.rejected`` names them). Leaving out the view that fits worst under the
    contaminated fit would be cheaper, but a wrong board pulls the fit towards itself and a good one then
    looks worst. Finally, boards a valid pose shows closer to edge-on than MIN_FACING_COS in a camera are
    left out of that camera and the pose refined again from where it is (``Pose.edge_on``).
    """
    tl, tr = corner_table(left, target), corner_table(right, target)
    covs = (corner_covariances(left, target), corner_covariances(right, target))
    pose = _estimate(tl, tr, target, cams, settings, covs=covs)
    rejected: list[str] = []
    while (not pose.valid and np.isfinite(pose.rms_px) and pose.rms_px > settings.bounds.max_rms_px
           and len(rejected) < max_rejected):
        views = sorted({(k[0], "left") for k in tl} | {(k[0], "right") for k in tr})
        if len(views) < 2:
            break
        trials = []
        for board, side in views:
            kl, kr = (_without(tl, {board}), tr) if side == "left" else (tl, _without(tr, {board}))
            trial = _estimate(kl, kr, target, cams, settings, covs=covs)
            if np.isfinite(trial.rms_px):
                trials.append(((trial.valid, trial.n_corners if trial.valid else 0, -trial.rms_px),
                               trial, board, side, kl, kr))
        if not trials:
            break
        _key, pose, board, side, tl, tr = max(trials, key=lambda x: x[0])
        rejected.append(f"{board} ({side})")
    pose.rejected = tuple(rejected)
    if pose.valid:
        pose, tl, tr, covs = _with_resolved_copies(pose, left, right, tl, tr, covs, target, cams, settings)
    edge_on = edge_on_views(pose, cams, target, tl, tr) if pose.valid else []
    if edge_on:
        kept_l = _without(tl, {board for board, side in edge_on if side == "left"})
        kept_r = _without(tr, {board for board, side in edge_on if side == "right"})
        refit = _estimate(kept_l, kept_r, target, cams, settings, start_pose=pose, covs=covs)
        # Only a valid pose replaces the first: the edge-on boards may be all there is.
        if refit.valid:
            refit.rejected = pose.rejected
            refit.edge_on = tuple(f"{board} ({side})" for board, side in edge_on)
            pose = refit
    return pose


def _with_resolved_copies(pose: Pose, left: Sequence[Detection], right: Sequence[Detection], tl: dict, tr: dict,
                          covs: tuple[dict, dict], target: Target, cams: StereoRig, settings: PoseSettings
                          ) -> tuple[Pose, dict, dict, tuple[dict, dict]]:
    """The pose, its corner tables and covariances with every board that an image shows twice or more
    (unambiguous_detections leaves them out) added in the copy that the pose from the other boards
    explains: refitted from ``pose`` with each copy in turn, the valid fit with the lowest RMS that drops no
    more corners as outliers than ``pose`` did. (A part of the asked size of another, edge-on board is
    reported as that board: 6-9 of 120 images of bench/live.py's robot sequences lost the real one.)"""
    names = {b.name for b in target.boards}
    for side, dets in (("left", left), ("right", right)):
        once = {d.board for d in unambiguous_detections(dets, target)}
        for board in sorted(({d.board for d in dets} & names) - once):
            best = None
            for det in (d for d in dets if d.board == board):
                copy, copy_covs = corner_table([det], target), corner_covariances([det], target)
                kl, kr = ({**tl, **copy}, tr) if side == "left" else (tl, {**tr, **copy})
                cl, cr = ({**covs[0], **copy_covs}, covs[1]) if side == "left" else (covs[0], {**covs[1], **copy_covs})
                trial = _estimate(kl, kr, target, cams, settings, start_pose=pose, covs=(cl, cr))
                if trial.valid and trial.outliers <= pose.outliers and (best is None or trial.rms_px < best[0].rms_px):
                    best = (trial, kl, kr, (cl, cr))
            if best is not None:
                best[0].rejected = pose.rejected
                pose, tl, tr, covs = best
    return pose, tl, tr, covs


def edge_on_views(pose: Pose, cams: StereoRig, target: Target, left: dict, right: dict) -> list[tuple[str, str]]:
    """(board, side) of every board in the corner tables that ``pose`` shows closer to edge-on than
    MIN_FACING_COS in that camera (none when the pose was not computed)."""
    if not np.all(np.isfinite(pose.t_m)):
        return []
    out = []
    for side, table in (("left", left), ("right", right)):
        R_c, t_c = camera_from_rig(cams, side, pose.R, pose.t_m)
        # |cos|: a board found in an image is seen from its printed side, whichever way its normal points.
        out += [(b, side) for b in sorted({k[0] for k in table})
                if abs(facing_cos(target.board(b), R_c, t_c)) < MIN_FACING_COS]
    return out
