"""Judging a calibration against the configured bounds: refuse it, with the numbers, when it is poor."""

from __future__ import annotations

import numpy as np

from edgecal.calibration.settings import Acceptance
from edgecal.calibration.types import Calibration
from edgecal.errors import CalibrationRejected

# Share of the residual energy that a smooth function of the radius (along the radius) must explain before the
# residual counts as structured: pure noise leaves ~1 % in RADIAL_BINS bins of hundreds of corners.
RADIAL_STRUCTURE_SHARE = 0.15
RADIAL_BINS = 8


def radial_structure(cal: Calibration, camera: int) -> tuple[float, float]:
    """(share, rim_px): how much of a camera's residual is radial and a smooth function of the radius.

    The inlier residuals are projected on the direction away from the principal point and averaged in
    RADIAL_BINS bins of equal corner count by radius; share = energy of those means / total residual
    energy, rim_px = the mean radial residual of the outermost bin. A wrong lens model (a radtan polynomial
    on a fisheye lens) leaves exactly this: residuals that point along the radius and grow towards the rim.
    """
    cam = cal.cameras[camera]
    q_views, e_views = [], []
    for cs, res, inl in zip(cal.corners[camera], cal.residuals_px[camera], cal.inliers[camera]):
        if len(cs):
            q_views.append(cs.image_px[inl])
            e_views.append(res[inl])
    if not q_views:
        return 0.0, 0.0
    q, e = np.concatenate(q_views), np.concatenate(e_views)
    if len(q) < 4 * RADIAL_BINS:
        return 0.0, 0.0
    d = q - [cam.cx, cam.cy]
    r = np.linalg.norm(d, axis=1)
    radial = np.sum(e * d / np.maximum(r, 1e-9)[:, None], axis=1)
    order = np.argsort(r)
    bins = np.array_split(order, RADIAL_BINS)
    means = np.array([radial[b].mean() for b in bins])
    explained = float(sum(len(b) * m * m for b, m in zip(bins, means)))
    return explained / max(float(np.sum(e * e)), 1e-300), float(means[-1])


def acceptance_problems(cal: Calibration, bounds: Acceptance) -> list[str]:
    """Every bound the calibration exceeds, as "what = value > limit" (empty when acceptable)."""
    out = []
    lens = "/".join(sorted({c.lens for c in cal.cameras}))
    if cal.undetermined:
        out.append(f"the corners cannot determine {', '.join(cal.undetermined)} of the {lens} lens model "
                   f"(fit a simpler --distortion, or add views that tilt the board and reach the image corners)")
    if not cal.rms_px <= bounds.max_rms_px:
        msg = f"reprojection RMS {cal.rms_px:.3f} px > {bounds.max_rms_px:g} px"
        for c, name in enumerate(cal.camera_names):
            share, rim = radial_structure(cal, c)
            if share >= RADIAL_STRUCTURE_SHARE:
                msg += (f" ({name}: {100 * share:.0f} % of the residual is radial and follows the distance from the "
                        f"image centre, {rim:+.1f} px at the rim: the {cal.cameras[c].lens} lens model does not fit "
                        f"this lens; try --distortion fisheye, rational or auto)")
        out.append(msg)
    for name, cam, std in zip(cal.camera_names, cal.cameras, cal.camera_std):
        for key, value in (("fx", cam.camera_matrix[0, 0]), ("fy", cam.camera_matrix[1, 1])):
            pct = 100.0 * std[key] / value
            if not pct <= bounds.max_focal_std_percent:
                out.append(f"{name} {key} std {pct:.2f} % > {bounds.max_focal_std_percent:g} %")
        for key in ("cx", "cy"):
            if not np.isnan(std[key]) and not std[key] <= bounds.max_principal_point_std_px:
                out.append(f"{name} {key} std {std[key]:.1f} px > {bounds.max_principal_point_std_px:g} px")
    if cal.is_stereo:
        t_std = np.asarray(cal.translation_std_mm)
        if not np.all(t_std <= bounds.max_baseline_std_mm):
            out.append(f"baseline T std ({', '.join(f'{v:.2f}' for v in t_std)}) mm > "
                       f"{bounds.max_baseline_std_mm:g} mm")
        if cal.reconstruction is not None and not cal.reconstruction.mean_mm <= bounds.max_reconstruction_mean_mm:
            out.append(f"3-D reconstruction error mean {cal.reconstruction.mean_mm:.3f} mm > "
                       f"{bounds.max_reconstruction_mean_mm:g} mm")
        if cal.rectification is not None and not cal.rectification.epipolar_rms_px <= bounds.max_epipolar_rms_px:
            out.append(f"epipolar RMS {cal.rectification.epipolar_rms_px:.3f} px > {bounds.max_epipolar_rms_px:g} px")
    total = sum(len(m) for per_cam in cal.inliers for m in per_cam)
    dropped = total - sum(int(m.sum()) for per_cam in cal.inliers for m in per_cam)
    if total and dropped / total > bounds.max_dropped_fraction:
        out.append(f"{dropped} of {total} corners rejected as outliers ({100 * dropped / total:.0f} % > "
                   f"{100 * bounds.max_dropped_fraction:.0f} %)")
    return out


def require_acceptable(cal: Calibration, bounds: Acceptance) -> None:
    """Raise CalibrationRejected listing every exceeded bound; the calibration is then not written."""
    problems = acceptance_problems(cal, bounds)
    if problems:
        raise CalibrationRejected("calibration refused (bounds in configs/calibration.yaml): " + "; ".join(problems))
