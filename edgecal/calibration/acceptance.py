"""Judging a calibration against the configured bounds: refuse it, with the numbers, when it is poor."""

from __future__ import annotations

import numpy as np

from edgecal.calibration.settings import Acceptance
from edgecal.calibration.types import Calibration
from edgecal.errors import CalibrationRejected


def acceptance_problems(cal: Calibration, bounds: Acceptance) -> list[str]:
    """Every bound the calibration exceeds, as "what = value > limit" (empty when acceptable)."""
    out = []
    if not cal.rms_px <= bounds.max_rms_px:
        out.append(f"reprojection RMS {cal.rms_px:.3f} px > {bounds.max_rms_px:g} px")
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
