"""What source to open: URI parsing and the validation of a config section.

A source is named by a URI on the command line or by a section of a configs/*.yaml file; both become
a :class:`SourceSpec` checked field by field, so a typo or an out-of-range value is reported with the
field's name before any device is touched.

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

import urllib.parse
from collections.abc import Mapping
from dataclasses import dataclass, field, fields, replace
from typing import Any

import yaml

from edgecal.config import ConfigReader
from edgecal.errors import ConfigError, quote
from edgecal.images import DEFAULT_MAX_PIXELS

DRIVERS = ("replay", "v4l2", "aravis", "dc1394", "depthai", "stereo", "mcap", "rosbag")
# Drivers that read a robot log (an MCAP file or a ROS bag): image topics by name.
LOG_DRIVERS = ("mcap", "rosbag")

# The field of a config section that names the device/file, per driver.
TARGET_FIELD = {"replay": "path", "v4l2": "device", "aravis": "name", "dc1394": "guid", "depthai": "mxid",
                "mcap": "path", "rosbag": "path"}

# Fields every driver accepts.
COMMON_FIELDS = ("timeout_s", "camera_id", "latest_only")

# Settings each driver understands (a field a driver cannot honour is an error, not silently ignored).
DRIVER_FIELDS: dict[str, tuple[str, ...]] = {
    "replay": ("pace", "loop", "fps", "preload", "preload_max_mb", "max_pixels"),
    "v4l2": ("width", "height", "fps", "pixel_format", "exposure_us", "gain", "buffers"),
    "aravis": ("width", "height", "fps", "pixel_format", "exposure_us", "gain_db", "trigger", "packet_size",
               "buffers"),
    "dc1394": ("width", "height", "fps", "pixel_format", "exposure_us", "gain", "trigger", "iso_speed",
               "buffers"),
    "depthai": ("width", "height", "fps", "exposure_us", "iso", "max_skew_ms"),
    "stereo": ("max_skew_ms",),
    "mcap": ("topic", "left", "right", "pace", "loop", "max_skew_ms"),
    "rosbag": ("topic", "left", "right", "pace", "loop", "max_skew_ms"),
}

PIXEL_FORMATS: dict[str, tuple[str, ...]] = {
    "v4l2": ("GREY", "Y16", "YUYV", "UYVY", "MJPG", "BGR3", "RGB3", "NV12"),
    "aravis": ("Mono8", "Mono10", "Mono12", "Mono16", "BayerRG8", "BayerGR8", "BayerGB8", "BayerBG8",
               "RGB8", "BGR8"),
    "dc1394": ("Mono8", "Mono16", "RGB8", "YUV422", "Raw8"),
}

TRIGGERS: dict[str, tuple[str, ...]] = {
    "aravis": ("free", "software", "hardware"),
    "dc1394": ("free", "hardware"),
}


@dataclass(frozen=True)
class SourceSettings:
    """Validated settings of one source; ``None`` = leave the device's own value."""

    timeout_s: float = 2.0          # read() raises DeviceError when no frame comes within this
    camera_id: str | None = None    # name written into Frame.camera_id (default: derived from the URI)
    latest_only: bool = False       # wrap in a background latest-frame-wins reader
    width: int | None = None
    height: int | None = None
    fps: float | None = None
    pixel_format: str | None = None
    exposure_us: float | None = None
    gain_db: float | None = None
    gain: float | None = None       # raw device units (V4L2, IEEE-1394 have no standard unit)
    iso: int | None = None
    trigger: str = "free"
    packet_size: int | None = None
    iso_speed: int | None = None
    buffers: int = 4
    pace: str = "recorded"          # replay, mcap, rosbag: "recorded" (real time; "realtime" says the same) or "fast"
    loop: bool = False
    preload: bool = False           # replay: decode every image once at open() (frames as a camera gives them)
    preload_max_mb: float = 2048.0  # replay: refuse a preload whose decoded frames would need more (MiB)
    max_pixels: int = DEFAULT_MAX_PIXELS  # replay: refuse larger images (read from the header, before decoding)
    max_skew_ms: float = 5.0
    topic: str | None = None        # mcap, rosbag: the image topic of a mono source
    left: str | None = None         # mcap, rosbag: the left and right image topics of a stereo source
    right: str | None = None

    def as_dict(self) -> dict[str, Any]:
        """Only the fields that differ from the defaults (for manifests and messages)."""
        default = SourceSettings()
        return {f.name: getattr(self, f.name) for f in fields(self)
                if getattr(self, f.name) != getattr(default, f.name)}


@dataclass(frozen=True)
class SourceSpec:
    """A parsed, validated source: which driver, which device/file, with which settings."""

    driver: str
    target: str = ""
    settings: SourceSettings = field(default_factory=SourceSettings)
    left: SourceSpec | None = None
    right: SourceSpec | None = None

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


def _read_settings(r: ConfigReader, driver: str, skip: tuple[str, ...] = ()) -> SourceSettings:
    allowed = COMMON_FIELDS + DRIVER_FIELDS[driver]
    for key in r.data:
        if key in skip:
            continue
        if key not in allowed:
            known = [k for k in DRIVERS if key in DRIVER_FIELDS[k] or key in (TARGET_FIELD.get(k),)]
            hint = f" (it is a field of: {', '.join(known)})" if known else ""
            raise r.fail(str(key), f"is not a setting of the {driver} driver{hint}; "
                                   f"known: {', '.join(skip + allowed)}")
    kw: dict[str, Any] = {}
    kw["timeout_s"] = r.number("timeout_s", 2.0, positive=True)
    if r.has("camera_id"):
        kw["camera_id"] = r.string("camera_id")
    kw["latest_only"] = r.boolean("latest_only", False)
    if r.has("width"):
        kw["width"] = r.integer("width", minimum=1, maximum=65535)
    if r.has("height"):
        kw["height"] = r.integer("height", minimum=1, maximum=65535)
    if r.has("fps"):
        kw["fps"] = r.number("fps", positive=True, maximum=10000)
    if r.has("pixel_format"):
        kw["pixel_format"] = r.string("pixel_format", choices=PIXEL_FORMATS[driver])
    if r.has("exposure_us"):
        kw["exposure_us"] = r.number("exposure_us", positive=True, maximum=60e6)
    if r.has("gain_db"):
        kw["gain_db"] = r.number("gain_db", minimum=0, maximum=100)
    if r.has("gain"):
        kw["gain"] = r.number("gain", minimum=0)
    if r.has("iso"):
        kw["iso"] = r.integer("iso", minimum=100, maximum=6400)
    if r.has("trigger"):
        kw["trigger"] = r.string("trigger", choices=TRIGGERS[driver])
    if r.has("packet_size"):
        kw["packet_size"] = r.integer("packet_size", minimum=576, maximum=16384)
    if r.has("iso_speed"):
        kw["iso_speed"] = r.integer("iso_speed", minimum=100, maximum=3200)
    if r.has("buffers"):
        kw["buffers"] = r.integer("buffers", minimum=2, maximum=64)
    if r.has("pace"):
        pace = r.string("pace", choices=("recorded", "fast", "realtime"))
        kw["pace"] = "recorded" if pace == "realtime" else pace
    if r.has("loop"):
        kw["loop"] = r.boolean("loop")
    if r.has("preload"):
        kw["preload"] = r.boolean("preload")
    if r.has("preload_max_mb"):
        kw["preload_max_mb"] = r.number("preload_max_mb", positive=True)
    if r.has("max_pixels"):
        kw["max_pixels"] = r.integer("max_pixels", minimum=1)
    if r.has("max_skew_ms"):
        kw["max_skew_ms"] = r.number("max_skew_ms", minimum=0, maximum=10000)
    if driver in LOG_DRIVERS:
        for key in ("topic", "left", "right"):
            if r.has(key):
                kw[key] = r.string(key)
    return SourceSettings(**kw)


def _check_log_topics(r: ConfigReader, driver: str, settings: SourceSettings) -> None:
    """A log source names either one topic (mono) or a left and a right one (stereo)."""
    example = f"{driver}:FILE?topic=/camera/image_raw or {driver}:FILE?left=/left/image_raw&right=/right/image_raw"
    kw = {"topic": settings.topic, "left": settings.left, "right": settings.right}
    if kw.get("topic") and (kw.get("left") or kw.get("right")):
        raise r.fail("topic", f"cannot be given together with left/right (one topic is mono, left+right stereo: "
                              f"{example})")
    if not kw.get("topic") and not (kw.get("left") and kw.get("right")):
        which = "right" if kw.get("left") else "left" if kw.get("right") else "topic"
        raise r.fail(which, f"is missing: name the image topic(s), e.g. {example}; "
                            "`edgecal sources FILE` lists them")


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


def parse_uri(uri: str) -> SourceSpec:
    """Parse a source URI (see the module docstring) into a validated SourceSpec."""
    spec = _parse_uri(uri)
    if spec.driver in LOG_DRIVERS:
        _check_log_topics(ConfigReader({}, f"source URI {quote(uri)}"), spec.driver, spec.settings)
    return spec


def _parse_uri(uri: str) -> SourceSpec:
    """parse_uri without the completeness check of a log source's topics (a config section may add them)."""
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
        left, right = parse_uri(left_uri), parse_uri(right_uri)
        for side, spec in (("left", left), ("right", right)):
            if spec.driver in ("stereo", "depthai") or spec.settings.left:
                raise ConfigError(f"{what}: the {side} source must be a mono camera, not {spec.driver}")
        settings = _read_settings(ConfigReader(options, what), "stereo")
        return SourceSpec("stereo", "", settings, left, right)
    target, _, query = rest.partition("?")
    options = _parse_options(query, what)
    settings = _read_settings(ConfigReader(options, what), driver)
    if driver == "replay" and not target:
        raise ConfigError(f"{what}: replay needs a path (replay:FOLDER or replay:VIDEO_FILE)")
    if driver in LOG_DRIVERS and not target:
        raise ConfigError(f"{what}: {driver} needs a path ({driver}:FILE?topic=TOPIC)")
    if driver == "v4l2" and not target:
        target = "/dev/video0"
    if driver == "dc1394" and target:
        _check_guid(target, what)
    return SourceSpec(driver, target, settings)


def _check_guid(guid: str, what: str) -> None:
    try:
        int(guid, 16)
    except ValueError:
        raise ConfigError(f"{what}: IEEE-1394 GUID {quote(guid)} must be hexadecimal, e.g. 00b09d0100a1b2c3") from None


def spec_from_config(section: Mapping[str, Any] | ConfigReader, source: str = "config") -> SourceSpec:
    """Validate a config section (a mapping, or a ConfigReader positioned on it) into a SourceSpec.

    The section holds either ``uri:`` (plus settings that override the URI's options), or ``driver:``
    with that driver's target field (``path``, ``device``, ``name``, ``guid``, ``mxid``), or
    ``stereo:`` with ``left``/``right`` sub-sections.
    """
    r = section if isinstance(section, ConfigReader) else ConfigReader(section, source)
    if r.has("stereo"):
        extra = [k for k in r.data if k != "stereo"]
        if extra:
            raise r.fail(str(extra[0]), "cannot sit beside 'stereo' (put it inside stereo.left/right)")
        s = r.section("stereo")
        for key in s.data:
            if key not in ("left", "right") + COMMON_FIELDS + DRIVER_FIELDS["stereo"]:
                raise s.fail(str(key), "is not a field of a stereo section "
                                       f"(known: left, right, {', '.join(COMMON_FIELDS + DRIVER_FIELDS['stereo'])})")
        left = spec_from_config(s.section("left"))
        right = spec_from_config(s.section("right"))
        for side, spec in (("left", left), ("right", right)):
            if spec.driver in ("stereo", "depthai"):
                raise s.fail(side, f"must be a mono camera, not {spec.driver}")
        settings = _read_settings(s, "stereo", skip=("left", "right"))
        return SourceSpec("stereo", "", settings, left, right)
    if r.has("uri"):
        if r.has("driver"):
            raise r.fail("driver", "cannot be given together with 'uri' (the URI names the driver)")
        uri = r.string("uri")
        try:
            base = _parse_uri(uri)
        except ConfigError as exc:
            raise r.fail("uri", f"is not a valid source URI: {exc}") from None
        if base.driver == "stereo":
            raise r.fail("uri", "a stereo pair in a config file is written as a 'stereo:' section")
        # Settings from the section override the URI's own options.
        merged = dict(base.settings.as_dict())
        merged.update({k: v for k, v in r.data.items() if k != "uri"})
        target_key = TARGET_FIELD[base.driver]
        if target_key in merged:
            raise r.fail(target_key, "cannot be given together with 'uri' (the URI names the device)")
        settings = _read_settings(ConfigReader(merged, r.source, r.prefix), base.driver)
        if base.driver in LOG_DRIVERS:
            _check_log_topics(r, base.driver, settings)
        return replace(base, settings=settings)
    driver = r.string("driver", choices=tuple(d for d in DRIVERS if d != "stereo"))
    target_key = TARGET_FIELD[driver]
    target = str(r.raw(target_key, "")) if r.has(target_key) else ""
    if driver == "replay" and not target:
        raise r.fail("path", "is missing (the folder, video file or recording to replay)")
    if driver in LOG_DRIVERS and not target:
        raise r.fail("path", f"is missing (the {'MCAP file' if driver == 'mcap' else 'bag'} to read)")
    if driver == "v4l2" and not target:
        target = "/dev/video0"
    if driver == "dc1394" and target:
        try:
            _check_guid(target, r.source)
        except ConfigError as exc:
            raise r.fail("guid", str(exc).split(": ", 1)[1]) from None
    settings = _read_settings(r, driver, skip=("driver", target_key))
    if driver in LOG_DRIVERS:
        _check_log_topics(r, driver, settings)
    return SourceSpec(driver, target, settings)


def as_spec(uri_or_config: str | Mapping[str, Any] | ConfigReader | SourceSpec) -> SourceSpec:
    """Accept a URI, a config mapping/ConfigReader or a ready SourceSpec."""
    if isinstance(uri_or_config, SourceSpec):
        return uri_or_config
    if isinstance(uri_or_config, str):
        return parse_uri(uri_or_config)
    if isinstance(uri_or_config, (Mapping, ConfigReader)):
        return spec_from_config(uri_or_config)
    raise ConfigError(f"a source must be a URI string or a config section, got {type(uri_or_config).__name__}")
