"""A calibration as plain data: per-view results named by file, and the ``calibrate --json`` object.

One place builds the JSON (and the per-view table the report draws from it); nothing patches it later.
NaN (a fixed parameter's σ) becomes null, so the output is strict JSON.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import SupportsFloat

import cv2
import numpy as np

from edgecal.calibration.settings import Acceptance
from edgecal.calibration.types import Calibration
from edgecal.calibration.views import View

JSON_FORMAT = "edgecal-calibration/1"
INTRINSICS = ("fx", "fy", "cx", "cy")


@dataclass(frozen=True)
class ViewResult:
    """How one input view took part: used or not (and why), per camera its RMS and dropped corners."""

    name: str
    files: tuple[str, ...]
    used: bool
    why_not: str                       # "" when used
    rms_px: tuple[float, ...]          # per camera, over its kept corners (nan when unused)
    corners: tuple[int, ...]           # per camera: corners found
    dropped: tuple[tuple[str, ...], ...]  # per camera: labels of corners rejected as outliers


def _view_order(cal: Calibration, n_views: int) -> list[int]:
    """Input view of each calibration view (box: the single view)."""
    return list(cal.view_index) if cal.view_index else list(range(min(n_views, len(cal.corners[0]))))


def view_results(cal: Calibration, views: list[View]) -> list[ViewResult]:
    """One ViewResult per input view, in input order."""
    used = {i: v for v, i in enumerate(_view_order(cal, len(views)))}
    out = []
    for i, view in enumerate(views):
        if i not in used:
            n = len(cal.camera_names)
            out.append(ViewResult(view.name, view.files, False, cal.skipped_views.get(i, "not used"),
                                  (math.nan,) * n, (0,) * n, ((),) * n))
            continue
        v = used[i]
        rms, count, dropped = [], [], []
        for c in range(len(cal.camera_names)):
            cs, res, inl = cal.corners[c][v], cal.residuals_px[c][v], cal.inliers[c][v]
            count.append(len(cs))
            r = res[inl] if len(cs) else np.zeros((0, 2))
            rms.append(float(np.sqrt(np.mean(np.sum(r ** 2, axis=1)))) if len(r) else math.nan)
            dropped.append(tuple(f"{b} ({col},{row})" for (b, col, row), ok in zip(cs.keys, inl) if not ok))
        out.append(ViewResult(view.name, view.files, True, "", tuple(rms), tuple(count), tuple(dropped)))
    return out


def _num(x: SupportsFloat) -> float | None:
    x = float(x)
    return None if math.isnan(x) or math.isinf(x) else x


def _param(value: SupportsFloat, std: SupportsFloat) -> dict[str, float | None]:
    return {"value": _num(value), "std": _num(std)}


def calibration_json(cal: Calibration, views: list[View], problems: list[str], bounds: Acceptance,
                     provenance: dict | None = None) -> dict:
    """The ``calibrate --json`` object: parameters with σ, RMS, the bounds and verdict, and every view."""
    cams = {}
    for name, cam, std in zip(cal.camera_names, cal.cameras, cal.camera_std):
        k, d = cam.camera_matrix, np.ravel(cam.dist_coeffs)
        entry: dict[str, object] = {n: _param(v, std[n])
                                    for n, v in zip(INTRINSICS, (k[0, 0], k[1, 1], k[0, 2], k[1, 2]))}
        entry["lens"] = cam.lens
        entry["distortion"] = {n: _param(v, std.get(n, math.nan)) for n, v in zip(cam.param_names, d)}
        cams[name] = entry
    doc: dict = {"format": JSON_FORMAT, "kind": cal.kind, "image_size": [int(v) for v in cal.image_size],
                 "verdict": "refused" if problems else "accepted", "problems": list(problems),
                 "bounds": asdict(bounds), "rms_px": _num(cal.rms_px), "sigma_px": _num(cal.sigma_px),
                 "cameras": cams}
    if cal.is_stereo:
        assert cal.rotation is not None and cal.translation_mm is not None  # set for every stereo calibration
        assert cal.rotation_std_rad is not None and cal.translation_std_mm is not None
        rv = cv2.Rodrigues(np.asarray(cal.rotation, dtype=np.float64))[0].ravel()
        doc["stereo"] = {
            "rotation_vector_rad": [_param(a, s) for a, s in zip(rv, np.ravel(cal.rotation_std_rad))],
            "translation_mm": [_param(a, s) for a, s in zip(np.ravel(cal.translation_mm),
                                                            np.ravel(cal.translation_std_mm))],
            "baseline_mm": _num(np.linalg.norm(cal.translation_mm)),
        }
        if cal.reconstruction is not None:
            r = cal.reconstruction
            doc["stereo"]["reconstruction_mm"] = {"mean": _num(r.mean_mm), "std": _num(r.std_mm),
                                                  "max": _num(r.max_mm), "corners": int(r.count)}
        if cal.rectification is not None:
            doc["stereo"]["epipolar_px"] = {"rms": _num(cal.rectification.epipolar_rms_px),
                                            "max": _num(cal.rectification.epipolar_max_px)}
    doc["per_board_rms_px"] = {k: _num(v) for k, v in cal.per_board_rms_px().items()}
    doc["views"] = [{"view": r.name, "files": list(r.files), "used": r.used,
                     **({} if r.used else {"why_not": r.why_not}),
                     "rms_px": {c: _num(v) for c, v in zip(cal.camera_names, r.rms_px)},
                     "corners": dict(zip(cal.camera_names, r.corners)),
                     "dropped_corners": {c: list(d) for c, d in zip(cal.camera_names, r.dropped)}}
                    for r in view_results(cal, views)]
    doc["notes"] = list(cal.notes)
    if provenance is not None:
        doc["provenance"] = provenance
    return doc
