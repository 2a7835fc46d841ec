"""``--distortion auto``: fit the candidate lens models and keep the simplest one the data supports.

A candidate is supported when its residual is within the noise (its noise estimate at most
NOISE_TOLERANCE above the lowest of all candidates: a model that leaves structure has a larger residual)
and every parameter is determined (no rank-deficient Jacobian and focal length / principal point σ within
the acceptance bounds). Simplest means fewest parameters; the radial-only models come first at equal count.
The choice and the reason for each rejected candidate are added to the calibration's notes.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import numpy as np

from edgecal.calibration.checks import DegenerateInput
from edgecal.calibration.refine import RefineOptions
from edgecal.calibration.settings import Acceptance
from edgecal.calibration.types import Calibration

# Simplest first: parameter count, radial-only before tangential at equal count.
AUTO_CANDIDATES = ("none", "k1", "k1k2", "k1k2k3", "fisheye", "k1k2p1p2", "k1k2p1p2k3", "rational")
# A residual within 5 % (and 0.005 px) of the best candidate's counts as "within the noise": beyond that,
# with hundreds of corners, the difference is structure the simpler model cannot follow.
NOISE_TOLERANCE = 0.05
NOISE_FLOOR_PX = 0.005


def _undetermined(cal: Calibration, bounds: Acceptance) -> str:
    """Why a calibration's parameters are not determined ("" when they are)."""
    if cal.undetermined:
        return f"{', '.join(cal.undetermined)} undetermined"
    for name, cam, std in zip(cal.camera_names, cal.cameras, cal.camera_std):
        for key, value in (("fx", cam.fx), ("fy", cam.fy)):
            if not 100.0 * std[key] / value <= bounds.max_focal_std_percent:
                return f"{name} {key} σ {100.0 * std[key] / value:.2g} % > {bounds.max_focal_std_percent:g} %"
        for key in ("cx", "cy"):
            if not np.isnan(std[key]) and not std[key] <= bounds.max_principal_point_std_px:
                return f"{name} {key} σ {std[key]:.2g} px > {bounds.max_principal_point_std_px:g} px"
    return ""


def choose_lens_model(fit: Callable[[RefineOptions], Calibration], options: RefineOptions, bounds: Acceptance,
                      candidates: tuple[str, ...] = AUTO_CANDIDATES) -> Calibration:
    """Fit every candidate with ``fit`` and return the simplest supported one (see the module docstring).

    Raises DegenerateInput naming each candidate's failure when none can be fitted at all.
    """
    fits: dict[str, Calibration] = {}
    failed: dict[str, str] = {}
    for name in candidates:
        try:
            fits[name] = fit(replace(options, distortion=name))
        except DegenerateInput as exc:
            failed[name] = str(exc)
    if not fits:
        raise DegenerateInput("no lens model could be fitted: " + "; ".join(f"{k}: {v}" for k, v in failed.items()))
    best = min(c.sigma_px for c in fits.values())
    limit = best * (1.0 + NOISE_TOLERANCE) + NOISE_FLOOR_PX
    why: dict[str, str] = {k: f"failed ({v})" for k, v in failed.items()}
    chosen = None
    for name in candidates:
        if name not in fits:
            continue
        cal = fits[name]
        if cal.sigma_px > limit:
            why[name] = f"residual σ {cal.sigma_px:.3f} px > {limit:.3f} px (the noise, from the best model)"
            continue
        reason = _undetermined(cal, bounds)
        if reason:
            why[name] = reason
            continue
        chosen = name
        break
    if chosen is None:
        # nothing is both within the noise and determined: keep the lowest residual, the bounds then say why
        chosen = min(fits, key=lambda k: fits[k].sigma_px)
        note = f"distortion auto: no candidate is within the noise and determined; kept {chosen} (lowest residual)"
    else:
        note = (f"distortion auto: chose {chosen} (residual σ {fits[chosen].sigma_px:.3f} px, within the noise "
                f"{limit:.3f} px; parameters determined)")
    cal = fits[chosen]
    simpler = [f"{k}: {why[k]}" for k in candidates if k in why and candidates.index(k) < candidates.index(chosen)]
    cal.notes = [note] + ([f"  simpler models rejected: {'; '.join(simpler)}"] if simpler else []) + cal.notes
    return cal
