"""Input checks shared by the calibration solvers: enough points, not all on one plane."""

from __future__ import annotations

import numpy as np

from edgecal.errors import InputError


class DegenerateInput(InputError):
    """The points cannot determine a calibration (too few of them, or all on one plane)."""


def as_points(object_mm: np.ndarray, image_px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``object_mm`` as float64 (N, 3) and ``image_px`` as float64 (N, 2); raise if they do not pair up."""
    obj = np.asarray(object_mm, dtype=np.float64).reshape(-1, 3)
    img = np.asarray(image_px, dtype=np.float64).reshape(-1, 2)
    if len(obj) != len(img):
        raise DegenerateInput(f"{len(obj)} 3-D points but {len(img)} image points: they must pair up one to one")
    if not (np.isfinite(obj).all() and np.isfinite(img).all()):
        raise DegenerateInput("some 3-D or image points are not finite numbers")
    return obj, img


def require_non_coplanar(object_mm: np.ndarray, image_px: np.ndarray, *, min_points: int = 6,
                         what: str = "camera") -> tuple[np.ndarray, np.ndarray]:
    """Validated (obj, img); raise DegenerateInput saying what is missing for a one-shot calibration.

    A camera matrix from one view needs at least 6 points (11 unknowns, 2 equations per point) and
    points off a single plane: a flat target leaves the focal length and the distance coupled.
    """
    obj, img = as_points(object_mm, image_px)
    if len(obj) < min_points:
        raise DegenerateInput(
            f"{what}: only {len(obj)} corners were matched to the target; a one-shot calibration needs at "
            f"least {min_points}, on two or more boards that are not parallel")
    spread = np.linalg.svd(obj - obj.mean(axis=0), compute_uv=False) / np.sqrt(len(obj))
    if spread[-1] < 1e-3 * max(spread[0], 1e-12):
        raise DegenerateInput(
            f"{what}: all {len(obj)} matched corners lie on one plane; a one-shot calibration needs corners "
            f"on at least two non-parallel boards of the target (show two or three faces of the box), "
            f"or use --board with several views of a flat board")
    return obj, img
