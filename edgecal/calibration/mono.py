"""One-shot calibration of one camera from one image of a non-coplanar target (a calibration box).

Both linear starts are tried — Tsai's method (as the paper) and the DLT with RQ decomposition — each
is refined, and the better refined camera is kept; both RMS values are recorded for the benchmark.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from edgecal.calibration.checks import DegenerateInput, require_non_coplanar
from edgecal.calibration.dlt import LinearCamera, calibrate_dlt
from edgecal.calibration.refine import (
    Observation,
    RefineOptions,
    RefineResult,
    calibration_from_result,
    observations_for,
    refine,
)
from edgecal.calibration.tsai import calibrate_tsai
from edgecal.calibration.types import Calibration, CornerSet, RigidTransform
from edgecal.camera import CameraModel


def linear_start(corners: CornerSet, image_size: tuple[int, int], method: str) -> LinearCamera:
    """The linear camera of ``method`` ("tsai" or "dlt") from one image's matched corners."""
    if method == "tsai":
        return calibrate_tsai(corners.object_mm, corners.image_px, image_size)
    if method == "dlt":
        return calibrate_dlt(corners.object_mm, corners.image_px)
    raise ValueError(f"unknown initialisation {method!r}")


def initialise_camera(corners: CornerSet, image_size: tuple[int, int], options: RefineOptions,
                      name: str = "camera") -> tuple[CameraModel, RigidTransform, RefineResult, dict[str, float]]:
    """The best refined camera and box pose from Tsai and DLT starts, and the refined RMS of each start.

    Raises DegenerateInput (naming the camera) when the corners cannot determine a camera.
    """
    require_non_coplanar(corners.object_mm, corners.image_px, what=name)
    obs = [Observation(0, 0, corners.object_mm, corners.image_px, corners.labels(name))]
    tried: dict[str, float] = {}
    best: tuple[tuple[int, float], CameraModel, RigidTransform, RefineResult, str] | None = None
    error: DegenerateInput | None = None
    # One rejection round is enough to compare the starts; the caller's final refinement does the rest.
    quick = replace(options, max_rounds=min(options.max_rounds, 1))
    for method in ("tsai", "dlt"):
        try:
            lin = linear_start(corners, image_size, method)
            res = refine(obs, [CameraModel.from_opencv(lin.camera_matrix, lin.dist_coeffs, image_size)],
                         [RigidTransform.from_rt(lin.rotation, lin.translation)], options=quick)
        except DegenerateInput as exc:
            error = error or exc
            continue
        tried[f"{method}_linear_rms_px"] = lin.rms_px
        tried[f"{method}_refined_rms_px"] = res.rms_px
        score = (len(res.dropped), res.rms_px)  # fewer corners dropped first: a bad start may "explain" by dropping
        if best is None or score < best[0]:
            best = (score, res.cameras[0], res.view_poses[0], res, method)
    if best is None:
        assert error is not None
        raise DegenerateInput(f"{name}: {error}")
    tried["chosen_" + best[4]] = 1.0
    return best[1], best[2], best[3], tried


def calibrate_box_mono(corners: CornerSet, image_size: tuple[int, int],
                       options: RefineOptions = RefineOptions()) -> Calibration:
    """Intrinsics, distortion and box pose of one camera from one image, with standard deviations."""
    cam, pose, _, tried = initialise_camera(corners, image_size, options)
    res = refine(observations_for([[corners]]), [cam], [pose], options=options)
    cal = calibration_from_result("box-mono", image_size, [[corners]], res)
    cal.init = {"camera": tried}
    return cal


def relative_pose(left: RigidTransform, right: RigidTransform) -> RigidTransform:
    """T_right_left from the target poses T_left_target and T_right_target."""
    r = right.rotation @ left.rotation.T
    return RigidTransform.from_rt(r, np.ravel(right.tvec) - r @ np.ravel(left.tvec))


__all__ = ["calibrate_box_mono", "initialise_camera", "linear_start", "relative_pose"]
