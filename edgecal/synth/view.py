"""One rendered view: geometry (render.py), then photometry (photometric.py), plus its ground truth."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from edgecal.camera import CameraModel
from edgecal.synth.camera import camera_json
from edgecal.synth.panels import Panel
from edgecal.synth.photometric import CLEAN, Photometric, apply_photometric
from edgecal.synth.render import render_radiance
from edgecal.synth.truth import GT_FORMAT, UNITS, board_truth, target_json


@dataclass
class RenderedView:
    """An 8-bit grey image and its "edgecal-synth-gt/1" truth (``truth["boards"]`` lists visible corners)."""

    image: np.ndarray
    truth: dict = field(default_factory=dict)

    def corners(self, board: int = 0) -> np.ndarray:
        """Ground-truth pixel corners (N, 2) of the ``board``-th listed board."""
        return np.asarray(self.truth["boards"][board]["corners"], dtype=np.float64).reshape(-1, 2)

    def ids(self, board: int = 0) -> np.ndarray:
        """Ground-truth (col, row) ids (N, 2) of the ``board``-th listed board."""
        return np.asarray(self.truth["boards"][board]["ids"], dtype=np.int64).reshape(-1, 2)


def render_view(camera: CameraModel, panels: list[Panel], R_cam_world: np.ndarray, t_cam_world_mm: np.ndarray,
                *, background: np.ndarray | float = 0.5, photometric: Photometric = CLEAN,
                rng: np.random.Generator | int | None = 0, supersampling: int = 12, border_px: float = 4.0,
                target_frame: str = "world", target_name: str | None = None,
                extra: dict | None = None, exposure: list[list[Panel]] | None = None,
                camera_name: str = "cam") -> RenderedView:
    """Render ``panels`` seen by ``camera`` at pose (R_cam_world, t_cam_world_mm) and describe the truth.

    ``rng`` (a Generator or a seed) drives the noise only; geometry is exact and deterministic.
    ``extra`` entries are added to the truth document (category, seed, distractors, ...).
    ``exposure``: the scene at several instants of the exposure; their images are averaged (motion blur)
    while the truth describes ``panels`` (the mid-exposure scene).
    """
    gen = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
    if exposure:
        radiance = np.mean([render_radiance(camera, sub, R_cam_world, t_cam_world_mm, background, supersampling)[0]
                            for sub in exposure], axis=0)
    else:
        radiance, _coverage = render_radiance(camera, panels, R_cam_world, t_cam_world_mm, background,
                                              supersampling)
    image = apply_photometric(radiance, photometric, gen)
    truth = {
        "format": GT_FORMAT,
        "units": dict(UNITS),
        "size": list(camera.image_size),
        "camera": camera_json(camera, camera_name, R_cam_world, t_cam_world_mm),
        "target": target_json(panels, target_frame, target_name),
        "boards": board_truth(camera, panels, R_cam_world, t_cam_world_mm, border_px),
        "render": {"supersampling": int(supersampling), "border_px": float(border_px),
                   "photometric": photometric.as_json()},
    }
    truth.update(extra or {})
    return RenderedView(image, truth)
