"""Detector thresholds: the paper's Table 1 and edgecal's own, with their defaults in configs/detector.yaml.

Each field's bounds and meaning are its metadata (edgecal.config.setting); configs/detector.yaml holds the
same defaults with the longer explanation, and a test keeps the two equal.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from edgecal.config import ConfigReader, load_yaml_mapping, read_settings, setting
from edgecal.detection.subpixel import REFINERS


def _fraction(default: float, doc: str) -> Any:
    return setting(default, doc=doc, minimum=0.0, maximum=1.0)


def _length(default: float, doc: str) -> Any:
    return setting(default, doc=doc, minimum=0.0)


def _count(default: int, doc: str, minimum: int = 1) -> Any:
    return setting(default, doc=doc, minimum=minimum)


@dataclass(frozen=True)
class DetectorParams:
    """All detector thresholds; see configs/detector.yaml for what each one means."""

    # Table 1 of the paper.
    probe_radius_px: float = _length(10.0, "r_e, Eq. (1): radius of the circular probe (first pass)")
    angle_diff_max_deg: float = _length(30.0, "theta_diff^th, Eq. (3): opposite border directions are 180 deg "
                                              "apart within this")
    sign_fraction: float = _fraction(0.70, "c_th, Eq. (5): share of a sector's samples above (below) its mean "
                                           "to call it + (-)")
    line_distance_px: float = _length(10.0, "d_l^th, Eq. (6): largest distance of a linked point from the search "
                                            "line, at reference_spacing_px")
    cross_ratio_tolerance: float = _fraction(0.05, "delta_cr, Eq. (8): relative error allowed on the cross-ratio "
                                                   "of 4 collinear points")
    # edgecal's own.
    reference_spacing_px: float = _length(30.0, "square size at which line_distance_px applies unscaled")
    probe_angles: int = _count(64, "rays of the probe (angular resolution 360/N deg before interpolation)",
                               minimum=16)
    probe_inner_radius_px: float = _length(1.5, "rays start here: the corner's own blur is bright all round")
    probe_radius_per_spacing: float = _length(0.6, "second pass: probe radius = this x local square size")
    probe_radius_min_px: float = _length(4.0, "second-pass probe radius, at least")
    probe_radius_max_px: float = _length(30.0, "second-pass probe radius, at most")
    min_contrast: float = _length(12.0, "grey levels: white sectors this much brighter than black ones")
    min_peak_ratio: float = _length(1.6, "weakest of the 4 border peaks over the profile's weakest valley")
    candidate_quality: float = _fraction(0.002, "min-eigenvalue candidates above this share of the strongest")
    candidate_noise_quantile: float = _fraction(0.999, "... and above what the image's noise reaches at this "
                                                       "quantile")
    candidate_chess_quantile: float = _fraction(0.9999, "snapped candidates: ChESS response above the noise's at "
                                                        "this quantile")
    candidate_chess_min: float = _length(6.0, "... and at least this (grey levels)")
    candidate_block_size: int = _count(3, "min-eigenvalue window (pixels)")
    max_candidates: int = _count(6000, "strongest candidates kept per image")
    min_grid_corners: int = _count(6, "smaller groups are ignored (not reported as a near miss)")
    pyramid_min_size_px: int = _count(400, "images at least this tall and wide are searched at half size first")
    bloom_saturated_fraction: float = _fraction(0.10, "a board missing and this share saturated: search again "
                                                      "eroded (bloom)")
    subpixel_refiner: str = setting("xjunction", doc="final corners: cornerSubPix, a saddle fit, then a blurred "
                                                     "X-junction fitted to the raw image (xjunction); cornerSubPix "
                                                     "and the saddle fit (saddle); or cornerSubPix alone",
                                    choices=REFINERS)


DEFAULT_PARAMS_FILE_HINT = "defaults and their meaning: configs/detector.yaml"


def params_from_mapping(data: dict, source: str, base: DetectorParams | None = None) -> DetectorParams:
    """DetectorParams from a YAML mapping; absent fields keep ``base`` (default: built-in defaults)."""
    return read_settings(DetectorParams, ConfigReader(data, source), base=base)


def load_params(path: str | Path) -> DetectorParams:
    """Load detector thresholds from a YAML file (fields not given keep their defaults)."""
    return params_from_mapping(load_yaml_mapping(path), str(path))
