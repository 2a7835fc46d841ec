"""The calibration settings file (configs/calibration.yaml): refinement options and acceptance bounds."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from edgecal.calibration.refine import DISTORTION_MODELS, RefineOptions
from edgecal.config import ConfigReader, load_yaml_mapping, packaged_config_path

# Every lens model a calibration can fit, and "auto" (edgecal.calibration.lens_choice picks one).
DISTORTION_CHOICES = (*DISTORTION_MODELS, "auto")


@dataclass(frozen=True)
class Acceptance:
    """Bounds beyond which a calibration is refused."""

    max_rms_px: float = 1.0
    max_focal_std_percent: float = 1.0
    max_principal_point_std_px: float = 25.0
    max_baseline_std_mm: float = 5.0
    max_reconstruction_mean_mm: float = 2.0
    max_epipolar_rms_px: float = 1.0
    max_dropped_fraction: float = 0.2


@dataclass(frozen=True)
class PlanarSettings:
    """Checks of the planar multi-view case."""

    min_views: int = 3
    min_coverage: float = 0.3
    max_view_rms_factor: float = 3.0


@dataclass(frozen=True)
class CalibrationSettings:
    """Everything configs/calibration.yaml sets."""

    refine: RefineOptions = field(default_factory=RefineOptions)
    acceptance: Acceptance = field(default_factory=Acceptance)
    planar: PlanarSettings = field(default_factory=PlanarSettings)


_ACCEPT = tuple(Acceptance.__dataclass_fields__)
_PLANAR = tuple(PlanarSettings.__dataclass_fields__)


def load_calibration_settings(path: str | Path | None = None) -> CalibrationSettings:
    """Read and validate a calibration settings file (default: the packaged configs/calibration.yaml).

    Raises ConfigError naming the field for a missing, unknown or out-of-range value.
    """
    p = Path(path) if path is not None else packaged_config_path("calibration.yaml")
    r = ConfigReader(load_yaml_mapping(p), str(p))
    r.reject_unknown(("distortion", "robust_loss_scale_px", "outlier_sigmas", "outlier_min_px",
                      "acceptance", "planar"))
    d = RefineOptions()
    refine = RefineOptions(
        distortion=r.string("distortion", d.distortion, choices=DISTORTION_CHOICES),
        loss_scale_px=r.number("robust_loss_scale_px", d.loss_scale_px, positive=True),
        outlier_sigmas=r.number("outlier_sigmas", d.outlier_sigmas, minimum=2.0),
        outlier_min_px=r.number("outlier_min_px", d.outlier_min_px, minimum=0.0),
    )
    a = r.section("acceptance", {})
    a.reject_unknown(_ACCEPT)
    da = Acceptance()
    acceptance = Acceptance(**{
        k: a.number(k, getattr(da, k), positive=k != "max_dropped_fraction", minimum=0.0,
                    maximum=1.0 if k == "max_dropped_fraction" else None)
        for k in _ACCEPT})
    pl = r.section("planar", {})
    pl.reject_unknown(_PLANAR)
    dp = PlanarSettings()
    planar = PlanarSettings(min_views=pl.integer("min_views", dp.min_views, minimum=1),
                            min_coverage=pl.number("min_coverage", dp.min_coverage, minimum=0.0, maximum=1.0),
                            max_view_rms_factor=pl.number("max_view_rms_factor", dp.max_view_rms_factor,
                                                          minimum=1.0))
    return CalibrationSettings(refine, acceptance, planar)
