"""Detector thresholds: the paper's Table 1 and edgecal's own, with their defaults in configs/detector.yaml."""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from pathlib import Path

from edgecal.config import ConfigReader, load_yaml_mapping
from edgecal.detection.subpixel import REFINERS


@dataclass(frozen=True)
class DetectorParams:
    """All detector thresholds; see configs/detector.yaml for what each one means."""

    # Table 1 of the paper.
    probe_radius_px: float = 10.0
    angle_diff_max_deg: float = 30.0
    sign_fraction: float = 0.70
    line_distance_px: float = 10.0
    cross_ratio_tolerance: float = 0.05
    # edgecal's own.
    reference_spacing_px: float = 30.0
    probe_angles: int = 64
    probe_inner_radius_px: float = 1.5
    probe_radius_per_spacing: float = 0.6
    probe_radius_min_px: float = 4.0
    probe_radius_max_px: float = 30.0
    min_contrast: float = 12.0
    min_peak_ratio: float = 1.6
    candidate_quality: float = 0.002
    candidate_noise_quantile: float = 0.999
    candidate_chess_quantile: float = 0.9999
    candidate_chess_min: float = 6.0
    candidate_block_size: int = 3
    max_candidates: int = 6000
    min_grid_corners: int = 6
    pyramid_min_size_px: int = 400
    bloom_saturated_fraction: float = 0.10
    subpixel_refiner: str = "saddle"


DEFAULT_PARAMS_FILE_HINT = "defaults and their meaning: configs/detector.yaml"

_INT_FIELDS = {"probe_angles", "candidate_block_size", "max_candidates", "min_grid_corners",
               "pyramid_min_size_px"}
_FRACTION_FIELDS = {"sign_fraction", "cross_ratio_tolerance", "candidate_quality", "candidate_noise_quantile",
                    "candidate_chess_quantile",
                    "bloom_saturated_fraction"}


def params_from_mapping(data: dict, source: str, base: DetectorParams | None = None) -> DetectorParams:
    """DetectorParams from a YAML mapping; absent fields keep ``base`` (default: built-in defaults)."""
    base = base or DetectorParams()
    r = ConfigReader(data, source)
    names = [f.name for f in fields(DetectorParams)]
    r.reject_unknown(names)
    values = {}
    for name in names:
        if not r.has(name):
            continue
        if name == "subpixel_refiner":
            values[name] = r.string(name, choices=REFINERS)
        elif name in _INT_FIELDS:
            values[name] = r.integer(name, minimum=1)
        elif name in _FRACTION_FIELDS:
            values[name] = r.number(name, minimum=0.0, maximum=1.0)
        else:
            values[name] = r.number(name, minimum=0.0)
    if "probe_angles" in values and values["probe_angles"] < 16:
        raise r.fail("probe_angles", "must be at least 16")
    return replace(base, **values)


def load_params(path: str | Path) -> DetectorParams:
    """Load detector thresholds from a YAML file (fields not given keep their defaults)."""
    return params_from_mapping(load_yaml_mapping(path), str(path))
