"""The declarative config reader (edgecal.config.read_settings) and the packaged files' defaults."""

from __future__ import annotations

from dataclasses import dataclass, fields

import pytest

from edgecal.calibration.settings import CalibrationSettings, load_calibration_settings
from edgecal.config import (
    ConfigReader,
    describe_settings,
    load_yaml_mapping,
    packaged_config_path,
    read_settings,
    section_keys,
    setting,
)
from edgecal.detection.params import DetectorParams, load_params
from edgecal.errors import ConfigError


@dataclass(frozen=True)
class _Inner:
    rate_hz: float = setting(10.0, doc="how often", positive=True, maximum=100)
    mode: str = setting("a", doc="which", choices=("a", "b", "fast"), synonyms={"fast": "b"})


@dataclass(frozen=True)
class _Flat:
    lo: int = setting(1, doc="lower", minimum=0)
    hi: int = setting(5, doc="upper", minimum=0)

    def config_problem(self) -> tuple[str, str] | None:
        return ("hi", f"must be at least lo ({self.lo})") if self.hi < self.lo else None


@dataclass(frozen=True)
class _Outer:
    name: str = setting(doc="required")
    scale_px: float = setting(1.0, doc="scale", positive=True, renamed_from=("old_scale_px",))
    inner: _Inner = setting(default_factory=_Inner, doc="a section")
    flat: _Flat = setting(default_factory=_Flat, doc="fields at this level", inline=True)
    knob: int = 3   # a plain field: not a config key


def _read(data: dict) -> _Outer:
    return read_settings(_Outer, ConfigReader(data, "x.yaml", "top"))


def test_fills_nested_and_inline_sections_from_field_names() -> None:
    out = _read({"name": "n", "inner": {"rate_hz": 50, "mode": "fast"}, "hi": 7})
    assert out == _Outer("n", 1.0, _Inner(50.0, "b"), _Flat(1, 7))
    assert isinstance(out.inner.rate_hz, float)
    assert section_keys(_Outer) == ("name", "scale_px", "inner", "lo", "hi")


@pytest.mark.parametrize("data, message", [
    ({}, "x.yaml: field 'top.name' is missing"),
    ({"name": "n", "inner": {"rate_hz": 0}}, "x.yaml: field 'top.inner.rate_hz' must be greater than 0 (got 0)"),
    ({"name": "n", "inner": {"rate_hz": 101}}, "field 'top.inner.rate_hz' must be at most 100 (got 101)"),
    ({"name": "n", "inner": {"mode": "c"}}, "field 'top.inner.mode' must be one of a, b, fast (got 'c')"),
    ({"name": "n", "inner": {"rat_hz": 1}}, "field 'top.inner.rat_hz' is not a known field (known: rate_hz, mode)"),
    ({"name": "n", "knob": 4}, "field 'top.knob' is not a known field (known: name, scale_px, inner, lo, hi)"),
    ({"name": "n", "old_scale_px": 2}, "field 'top.old_scale_px' was renamed to 'scale_px'"),
    ({"name": "n", "lo": 4, "hi": 2}, "field 'top.hi' must be at least lo (4)"),
    ({"name": "n", "lo": True}, "field 'top.lo' must be a whole number (got True)"),
    ({"name": "n", "inner": 3}, "field 'top.inner' must be a mapping"),
])
def test_every_mistake_names_the_field_with_its_path(data: dict, message: str) -> None:
    with pytest.raises(ConfigError) as info:
        _read(data)
    assert message in str(info.value)


def test_null_and_absent_keep_the_default_or_the_base() -> None:
    assert _read({"name": "n", "scale_px": None}).scale_px == 1.0
    base = DetectorParams(probe_radius_px=7.0)
    got = read_settings(DetectorParams, ConfigReader({"max_candidates": 10}, "d.yaml"), base=base)
    assert (got.probe_radius_px, got.max_candidates) == (7.0, 10)


def test_every_setting_has_a_doc() -> None:
    from edgecal.pose.types import PoseSettings
    from edgecal.publish.publisher import PublishSettings
    from edgecal.publish.sink_settings import FoxgloveSettings, OutputSettings, RecordSettings
    from edgecal.stream.config import LoopSettings
    from edgecal.stream.tracker import TrackingSettings
    for cls in (DetectorParams, CalibrationSettings, PoseSettings, TrackingSettings, LoopSettings, PublishSettings,
                OutputSettings, RecordSettings, FoxgloveSettings):
        assert all(doc for _, _, doc in describe_settings(cls)), cls


def test_the_packaged_robot_config_uses_only_known_keys() -> None:
    """configs/robot.yaml needs the demo's rig to load in full; each of its sections is read here alone."""
    from edgecal.drivers.spec import spec_from_config
    from edgecal.pose.types import PoseSettings
    from edgecal.stream.config import LIVE_FIELDS, RETIRED_LOOP_KEYS, LoopSettings, read_publish
    from edgecal.stream.tracker import TrackingSettings
    path = packaged_config_path("robot.yaml")
    r = ConfigReader(load_yaml_mapping(path), str(path))
    r.reject_unknown(LIVE_FIELDS)
    assert spec_from_config(r.section("source")).settings.latest_only
    read_settings(PoseSettings, r.section("pose"))
    read_settings(TrackingSettings, r.section("tracking"))
    read_publish(r.section("publish"))
    read_settings(LoopSettings, r.section("loop"), retired=RETIRED_LOOP_KEYS)


@pytest.mark.parametrize("name, cls, load", [("detector.yaml", DetectorParams, load_params),
                                             ("calibration.yaml", CalibrationSettings, load_calibration_settings)])
def test_packaged_files_name_every_threshold_with_the_built_in_default(name, cls, load) -> None:
    """configs/detector.yaml (Table 1 of the paper and edgecal's own) and configs/calibration.yaml spell out
    every field, each with the value built into edgecal: the file documents the defaults."""
    path = packaged_config_path(name)
    assert load(path) == cls()
    data = load_yaml_mapping(path)
    flat = {**{k: v for k, v in data.items() if not isinstance(v, dict)},
            **{f"{k}.{kk}": vv for k, v in data.items() if isinstance(v, dict) for kk, vv in v.items()}}
    assert sorted(flat) == sorted(key for key, _, _ in describe_settings(cls))


def test_the_renamed_loss_scale_is_refused_with_its_new_name(tmp_path) -> None:
    cfg = tmp_path / "cal.yaml"
    cfg.write_text("robust_loss_scale_px: 2.0\n")
    with pytest.raises(ConfigError, match="field 'robust_loss_scale_px' was renamed to 'loss_scale_px'"):
        load_calibration_settings(cfg)
    cfg.write_text("loss_scale_px: 2.0\n")
    assert load_calibration_settings(cfg).refine.loss_scale_px == 2.0
    assert {f.name for f in fields(DetectorParams)} == set(section_keys(DetectorParams))
