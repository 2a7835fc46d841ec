"""The calibration settings file (configs/calibration.yaml): refinement options and acceptance bounds.

The refinement options (edgecal.calibration.refine.RefineOptions) sit at the top level of the file, the
bounds in ``acceptance:`` and ``planar:``; every key is the name of its field.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from edgecal.calibration.refine import DISTORTION_CHOICES, RefineOptions
from edgecal.config import ConfigReader, load_yaml_mapping, packaged_config_path, read_settings, setting

__all__ = ["DISTORTION_CHOICES", "Acceptance", "CalibrationSettings", "PlanarSettings",
           "load_calibration_settings"]


def _bound(default: float, doc: str) -> Any:
    return setting(default, doc=doc, positive=True)


@dataclass(frozen=True)
class Acceptance:
    """Bounds beyond which a calibration is refused."""

    max_rms_px: float = _bound(1.0, "reprojection RMS of the kept corners")
    max_focal_std_percent: float = _bound(1.0, "1-sigma of fx and fy, in % of the value")
    max_principal_point_std_px: float = _bound(25.0, "1-sigma of cx and cy")
    max_baseline_std_mm: float = _bound(5.0, "1-sigma of each component of T (stereo)")
    max_reconstruction_mean_mm: float = _bound(2.0, "mean 3-D error of triangulated corners (stereo)")
    max_epipolar_rms_px: float = _bound(1.0, "rectified vertical disparity of the corners (stereo)")
    max_dropped_fraction: float = setting(0.2, doc="share of corners rejected as outliers", minimum=0.0,
                                          maximum=1.0)


@dataclass(frozen=True)
class PlanarSettings:
    """Checks of the planar multi-view case."""

    min_views: int = setting(3, doc="views (pairs, for stereo) in which the whole board was found", minimum=1)
    min_coverage: float = setting(0.3, doc="share of an 8 x 6 grid of image cells holding a corner", minimum=0.0,
                                  maximum=1.0)
    max_view_rms_factor: float = setting(3.0, doc="a view whose RMS exceeds this x the median view RMS is rejected",
                                         minimum=1.0)


@dataclass(frozen=True)
class CalibrationSettings:
    """Everything configs/calibration.yaml sets."""

    refine: RefineOptions = setting(default_factory=RefineOptions, doc="how to refine", inline=True)
    acceptance: Acceptance = setting(default_factory=Acceptance, doc="calibrations outside these are refused")
    planar: PlanarSettings = setting(default_factory=PlanarSettings, doc="checks of the planar multi-view case")


def load_calibration_settings(path: str | Path | None = None) -> CalibrationSettings:
    """Read and validate a calibration settings file (default: the packaged configs/calibration.yaml).

    Raises ConfigError naming the field for a missing, unknown or out-of-range value.
    """
    p = Path(path) if path is not None else packaged_config_path("calibration.yaml")
    return read_settings(CalibrationSettings, ConfigReader(load_yaml_mapping(p), str(p)))
