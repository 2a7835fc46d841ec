"""What source to open: URI parsing and the validation of a config section.

A source is named by a URI on the command line or by a section of a configs/*.yaml file. A URI is first
turned into the mapping that the equivalent config section would hold (``replay:run1?pace=fast`` is
``{driver: replay, path: run1, pace: fast}``), and both go through the same validation into a
:class:`SourceSpec`: a typo or an out-of-range value is reported with the field's name before any device
is touched. Each driver's settings are a dataclass beside the driver (``SETTINGS`` maps the driver name
to it), read by edgecal.config.read_settings from the fields' metadata.

URI forms (options after ``?`` are the same fields as in a config section)::

    replay:PATH[?pace=fast&loop=true&fps=30]     folder of images, video file, edgecal recording
    v4l2:/dev/video0[?width=1280&height=720&fps=30&pixel_format=YUYV]
    aravis:NAME                                   IP address, device id, or ``fake`` (built-in Fake)
    dc1394:GUID                                   hexadecimal GUID, or empty for the first camera
    depthai:  /  depthai:MXID                     first / named OAK device (a stereo source)
    stereo:LEFT_URI,RIGHT_URI                     two mono sources paired by timestamp
    stereo:[LEFT_URI,RIGHT_URI]?max_skew_ms=2     ... with options of the pairing itself
    mcap:FILE.mcap?topic=/cam/image_raw           an image topic of an MCAP file (ROS 2 messages)
    mcap:FILE.mcap?left=/left/image&right=/right/image    two topics paired by header stamp (stereo)
    rosbag:BAG?topic=...  /  rosbag:BAG?left=...&right=...  the same over a ROS 1 .bag or a ROS 2 bag folder

A config section (e.g. ``source:`` in a YAML file)::

    source:
      uri: aravis:192.168.1.20     # or  driver: aravis  +  name: 192.168.1.20
      fps: 30
      exposure_us: 8000
      timeout_s: 1.0

or, for two mono cameras::

    source:
      stereo:
        left:  {uri: v4l2:/dev/video0}
        right: {uri: v4l2:/dev/video2}
        max_skew_ms: 3
"""

from __future__ import annotations

import importlib
import urllib.parse
from collections.abc import Mapping
from dataclasses import dataclass, fields
from typing import Any, Generic, TypeVar

import yaml

from edgecal.config import ConfigReader, read_settings, section_keys, setting
from edgecal.errors import ConfigError, quote

DRIVERS = ("replay", "v4l2", "aravis", "dc1394", "depthai", "stereo", "mcap", "rosbag")
# Drivers that read a robot log (an MCAP file or a ROS bag): image topics by name.
LOG_DRIVERS = ("mcap", "rosbag")

# The field of a config section that names the device/file, per driver.
TARGET_FIELD = {"replay": "path", "v4l2": "device", "aravis": "name", "dc1394": "guid", "depthai": "mxid",
                "mcap": "path", "rosbag": "path"}

# Driver name -> "module:class" of its settings, a dataclass beside the driver. The driver modules import
# SourceSpec from here, so their settings are imported when first needed: no import cycle, and parsing a
# replay URI does not import the camera drivers.
SETTINGS = {"replay": "replay:ReplaySettings", "v4l2": "v4l2:V4L2Settings", "aravis": "aravis:AravisSettings",
            "dc1394": "dc1394:DC1394Settings", "depthai": "oak:DepthaiSettings", "stereo": "stereo:PairSettings",
            "mcap": "robolog:RobotLogSettings", "rosbag": "robolog:RobotLogSettings"}


def settings_class(driver: str) -> type[SourceSettings]:
    """The settings dataclass of ``driver`` (one of DRIVERS)."""
    module, _, name = SETTINGS[driver].partition(":")
    return getattr(importlib.import_module(f"edgecal.drivers.{module}"), name)


@dataclass(frozen=True)
class SourceSettings:
    """The settings every driver takes; each driver's class adds its own (see SETTINGS)."""

    timeout_s: float = setting(2.0, doc="read() raises DeviceError when no frame comes within this (s)",
                               positive=True)
    camera_id: str | None = setting(None, doc="name written into Frame.camera_id (default: derived from the URI)")
    latest_only: bool = setting(False, doc="wrap in a background latest-frame-wins reader (the live loop's "
                                           "default: true)")

    def as_dict(self) -> dict[str, Any]:
        """Only the fields that differ from the defaults (for manifests and messages)."""
        default = type(self)()
        return {f.name: getattr(self, f.name) for f in fields(self)
                if getattr(self, f.name) != getattr(default, f.name)}


@dataclass(frozen=True)
class CameraSettings(SourceSettings):
    """What every camera driver can set; ``None`` leaves the device's own value."""

    width: int | None = setting(None, doc="image width (px)", minimum=1, maximum=65535)
    height: int | None = setting(None, doc="image height (px)", minimum=1, maximum=65535)
    fps: float | None = setting(None, doc="frame rate (Hz)", positive=True, maximum=10000)
    exposure_us: float | None = setting(None, doc="exposure time (us)", positive=True, maximum=60e6)


# Fields several drivers declare alike.
def pace_setting() -> Any:
    """``pace`` of a recording: real time as recorded, or as fast as frames are read."""
    return setting("recorded", doc='"recorded" (real time; "realtime" says the same) or "fast"',
                   choices=("recorded", "fast", "realtime"), synonyms={"realtime": "recorded"})


def skew_setting() -> Any:
    """``max_skew_ms`` of a stereo pairing."""
    return setting(5.0, doc="left and right frames further apart than this are not paired (ms)", minimum=0,
                   maximum=10000)


def buffers_setting() -> Any:
    """``buffers`` of a streaming camera."""
    return setting(4, doc="capture buffers queued in the driver", minimum=2, maximum=64)


S = TypeVar("S", bound=SourceSettings)


@dataclass(frozen=True)
class SourceSpec(Generic[S]):
    """A parsed, validated source: which driver, which device/file, with which settings.

    ``settings`` is the driver's own class (settings_class(driver)); a driver that wants them typed takes
    a ``SourceSpec[ItsSettings]``.
    """

    driver: str
    target: str
    settings: S
    left: SourceSpec[Any] | None = None
    right: SourceSpec[Any] | None = None

    @property
    def uri(self) -> str:
        """The canonical URI (without options) naming this source."""
        if self.driver == "stereo" and self.left is not None and self.right is not None:
            return f"stereo:{self.left.uri},{self.right.uri}"
        return f"{self.driver}:{self.target}"

    @property
    def camera_id(self) -> str:
        """The id put into frames: the configured one, else derived from the URI."""
        return self.settings.camera_id or self.uri

    @property
    def is_stereo(self) -> bool:
        """Whether the source delivers left/right pairs (a pair, an OAK, or a log's left and right topics)."""
        return self.driver in ("stereo", "depthai") or bool(getattr(self.settings, "left", None))


# --------------------------------------------------------------------------------------------------------
# URI -> mapping


def _parse_options(query: str, what: str) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in urllib.parse.parse_qsl(query, keep_blank_values=True, strict_parsing=False):
        if not key:
            raise ConfigError(f"{what}: an option after '?' has no name (expected key=value)")
        try:
            out[key] = yaml.safe_load(value) if value != "" else None
        except yaml.YAMLError:
            out[key] = value
    return out


def _split_pair(body: str, uri: str) -> tuple[str, str]:
    """Split ``LEFT,RIGHT`` at the comma that is followed by a driver name (paths may hold commas)."""
    for i, ch in enumerate(body):
        if ch == "," and any(body[i + 1:].startswith(d + ":") for d in DRIVERS):
            return body[:i], body[i + 1:]
    raise ConfigError(f"source URI {quote(uri)}: stereo needs two sources, e.g. "
                      "stereo:v4l2:/dev/video0,v4l2:/dev/video2")


# Keys of a section that are not settings: a URI option of one of these names is an unknown setting.
_SECTION_KEYS = ("uri", "driver", "stereo", "left", "right")


def uri_mapping(uri: str) -> dict[str, Any]:
    """The config section a source URI stands for (only its syntax is checked here).

    ``replay:run1?pace=fast`` -> ``{driver: replay, path: run1, pace: fast}``;
    ``stereo:[L,R]?max_skew_ms=2`` -> ``{stereo: {left: <L's mapping>, right: <R's>, max_skew_ms: 2}}``.
    """
    if not isinstance(uri, str) or ":" not in uri:
        raise ConfigError(f"source URI {quote(uri)}: expected DRIVER:TARGET with DRIVER one of {', '.join(DRIVERS)} "
                          "(e.g. replay:recordings/run1 or aravis:192.168.1.20)")
    driver, _, rest = uri.partition(":")
    driver = driver.strip().lower()
    what = f"source URI {quote(uri)}"
    if driver not in DRIVERS:
        raise ConfigError(f"{what}: unknown driver {quote(driver)} (known: {', '.join(DRIVERS)})")
    if driver == "stereo":
        body, options = rest, {}
        if body.startswith("["):
            close = body.rfind("]")
            if close < 0:
                raise ConfigError(f"{what}: '[' without a closing ']'")
            tail = body[close + 1:]
            if tail and not tail.startswith("?"):
                raise ConfigError(f"{what}: expected '?option=value' after ']' (got {quote(tail)})")
            options = _parse_options(tail[1:], what)
            body = body[1:close]
        left_uri, right_uri = _split_pair(body, uri)
        _no_section_keys(options, "stereo", what)
        return {"stereo": {"left": uri_mapping(left_uri), "right": uri_mapping(right_uri), **options}}
    target, _, query = rest.partition("?")
    options = _parse_options(query, what)
    _no_section_keys(options, driver, what)
    return {"driver": driver, **({TARGET_FIELD[driver]: target} if target else {}), **options}


def _no_section_keys(options: Mapping[str, Any], driver: str, what: str) -> None:
    reserved = (*_SECTION_KEYS, TARGET_FIELD.get(driver, ""))
    for key in options:
        if key in reserved and not (driver in LOG_DRIVERS and key in ("left", "right")):
            _unknown_setting(ConfigReader(options, what), key, driver, ())


# --------------------------------------------------------------------------------------------------------
# mapping -> SourceSpec (the one validation of URIs and config sections)


def _unknown_setting(r: ConfigReader, key: str, driver: str, reserved: tuple[str, ...]) -> None:
    """Raise for ``key``, which is no setting of ``driver``, naming the drivers that have it."""
    owners = [d for d in DRIVERS if key in section_keys(settings_class(d)) or key == TARGET_FIELD.get(d)]
    hint = f" (it is a field of: {', '.join(owners)})" if owners else ""
    raise r.fail(key, f"is not a setting of the {driver} driver{hint}; "
                      f"known: {', '.join(reserved + section_keys(settings_class(driver)))}")


def _read_settings(r: ConfigReader, driver: str, reserved: tuple[str, ...], listed: bool) -> SourceSettings:
    """The settings of ``driver`` from ``r``; ``reserved``: the section's other keys (driver, path, ...),
    named among the known ones when ``listed``."""
    keys = section_keys(settings_class(driver))
    for key in r.data:
        if str(key) not in reserved and str(key) not in keys:
            _unknown_setting(r, str(key), driver, reserved if listed else ())
    return read_settings(settings_class(driver), r, ignore=reserved)


def _check_log_topics(r: ConfigReader, driver: str, settings: Any) -> None:
    """A log source names either one topic (mono) or a left and a right one (stereo)."""
    example = f"{driver}:FILE?topic=/camera/image_raw or {driver}:FILE?left=/left/image_raw&right=/right/image_raw"
    if settings.topic and (settings.left or settings.right):
        raise r.fail("topic", f"cannot be given together with left/right (one topic is mono, left+right stereo: "
                              f"{example})")
    if not settings.topic and not (settings.left and settings.right):
        which = "right" if settings.left else "left" if settings.right else "topic"
        raise r.fail(which, f"is missing: name the image topic(s), e.g. {example}; "
                            "`edgecal sources FILE` lists them")


def _target(r: ConfigReader, driver: str, from_uri: bool) -> str:
    """The device/file of a mono section: its driver's target field, checked and defaulted."""
    key = TARGET_FIELD[driver]
    target = str(r.raw(key, "")) if r.has(key) else ""

    def fail(for_uri: str, for_section: str) -> ConfigError:
        return ConfigError(f"{r.source}: {for_uri}") if from_uri else r.fail(key, for_section)

    if driver == "replay" and not target:
        raise fail("replay needs a path (replay:FOLDER or replay:VIDEO_FILE)",
                   "is missing (the folder, video file or recording to replay)")
    if driver in LOG_DRIVERS and not target:
        raise fail(f"{driver} needs a path ({driver}:FILE?topic=TOPIC)",
                   f"is missing (the {'MCAP file' if driver == 'mcap' else 'bag'} to read)")
    if driver == "v4l2" and not target:
        target = "/dev/video0"
    if driver == "dc1394" and target:
        try:
            int(target, 16)
        except ValueError:
            problem = f"IEEE-1394 GUID {quote(target)} must be hexadecimal, e.g. 00b09d0100a1b2c3"
            raise fail(problem, problem) from None
    return target


def _spec(r: ConfigReader, from_uri: bool, complete: bool = True) -> SourceSpec:
    """Validate a section (or a URI's mapping) into a SourceSpec; ``complete``: also require what a
    section may add to its ``uri:`` (a log's topics)."""
    if r.has("stereo"):
        return _stereo_spec(r, from_uri)
    if r.has("uri"):
        return _uri_section_spec(r)
    driver = r.string("driver", choices=tuple(d for d in DRIVERS if d != "stereo"))
    target = _target(r, driver, from_uri)
    settings = _read_settings(r, driver, ("driver", TARGET_FIELD[driver]), listed=not from_uri)
    if driver in LOG_DRIVERS and complete:
        _check_log_topics(r, driver, settings)
    return SourceSpec(driver, target, settings)


def _stereo_spec(r: ConfigReader, from_uri: bool) -> SourceSpec:
    extra = [k for k in r.data if k != "stereo"]
    if extra:
        raise r.fail(str(extra[0]), "cannot sit beside 'stereo' (put it inside stereo.left/right)")
    s = r.section("stereo")
    known = ("left", "right", *section_keys(settings_class("stereo")))
    for key in s.data:
        if key not in known:
            raise s.fail(str(key), f"is not a field of a stereo section (known: {', '.join(known)})")
    sides = []
    for side in ("left", "right"):
        spec = _spec(s.section(side), from_uri)
        if spec.is_stereo:
            raise s.fail(side, f"must be a mono camera, not {spec.driver}"
                               + (" with left and right topics" if spec.driver in LOG_DRIVERS else ""))
        sides.append(spec)
    settings = read_settings(settings_class("stereo"), s, ignore=("left", "right"))
    return SourceSpec("stereo", "", settings, sides[0], sides[1])


def _uri_section_spec(r: ConfigReader) -> SourceSpec:
    """``uri:`` plus settings that override the URI's own options."""
    if r.has("driver"):
        raise r.fail("driver", "cannot be given together with 'uri' (the URI names the driver)")
    uri = r.string("uri")
    try:
        mapping = uri_mapping(uri)
        if "stereo" not in mapping:
            _spec(ConfigReader(mapping, f"source URI {quote(uri)}"), from_uri=True, complete=False)
    except ConfigError as exc:
        raise r.fail("uri", f"is not a valid source URI: {exc}") from None
    if "stereo" in mapping:
        raise r.fail("uri", "a stereo pair in a config file is written as a 'stereo:' section")
    driver = mapping["driver"]
    target_key = TARGET_FIELD[driver]
    if r.has(target_key):
        raise r.fail(target_key, "cannot be given together with 'uri' (the URI names the device)")
    merged = {**mapping, **{k: v for k, v in r.data.items() if k != "uri"}}
    m = ConfigReader(merged, r.source, r.prefix)
    settings = _read_settings(m, driver, ("driver", target_key), listed=False)
    if driver in LOG_DRIVERS:
        _check_log_topics(r, driver, settings)
    return SourceSpec(driver, _target(m, driver, from_uri=True), settings)


def parse_uri(uri: str) -> SourceSpec:
    """Parse a source URI (see the module docstring) into a validated SourceSpec."""
    return _spec(ConfigReader(uri_mapping(uri), f"source URI {quote(uri)}"), from_uri=True)


def spec_from_config(section: Mapping[str, Any] | ConfigReader, source: str = "config", *,
                     defaults: Mapping[str, Any] | None = None) -> SourceSpec:
    """Validate a config section (a mapping, or a ConfigReader positioned on it) into a SourceSpec.

    The section holds either ``uri:`` (plus settings that override the URI's options), or ``driver:``
    with that driver's target field (``path``, ``device``, ``name``, ``guid``, ``mxid``), or
    ``stereo:`` with ``left``/``right`` sub-sections. ``defaults``: settings of the source as a whole
    that the section (or its URI) does not give, e.g. the live loop's ``latest_only: true``.
    """
    r = section if isinstance(section, ConfigReader) else ConfigReader(section, source)
    if defaults:
        r = ConfigReader(_with_defaults(r.data, defaults), r.source, r.prefix)
    return _spec(r, from_uri=False)


def _with_defaults(data: Mapping[str, Any], defaults: Mapping[str, Any]) -> dict[str, Any]:
    """``data`` with ``defaults`` for the keys it (or its URI, or its stereo section) does not set."""
    if isinstance(data.get("stereo"), Mapping):
        return {**data, "stereo": {**defaults, **data["stereo"]}}
    if isinstance(data.get("uri"), str):
        try:
            given = uri_mapping(data["uri"])
        except ConfigError:
            given = {}      # reported with the field's name by the validation
        if "stereo" in given:
            return dict(data)
        return {**{k: v for k, v in defaults.items() if k not in given}, **data}
    return {**defaults, **data}


def as_spec(uri_or_config: str | Mapping[str, Any] | ConfigReader | SourceSpec) -> SourceSpec:
    """Accept a URI, a config mapping/ConfigReader or a ready SourceSpec."""
    if isinstance(uri_or_config, SourceSpec):
        return uri_or_config
    if isinstance(uri_or_config, str):
        return parse_uri(uri_or_config)
    if isinstance(uri_or_config, (Mapping, ConfigReader)):
        return spec_from_config(uri_or_config)
    raise ConfigError(f"a source must be a URI string or a config section, got {type(uri_or_config).__name__}")


__all__ = ["DRIVERS", "LOG_DRIVERS", "SETTINGS", "TARGET_FIELD", "CameraSettings", "SourceSettings", "SourceSpec",
           "as_spec", "buffers_setting", "pace_setting", "parse_uri", "settings_class", "skew_setting",
           "spec_from_config", "uri_mapping"]
