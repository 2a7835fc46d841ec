"""Source URIs and config sections: parsed into specs, every mistake named by field."""

from __future__ import annotations

import pytest

from edgecal.drivers import parse_uri, spec_from_config
from edgecal.errors import ConfigError


def test_uri_forms() -> None:
    s = parse_uri("replay:/data/run1?pace=fast&loop=true&fps=15")
    assert (s.driver, s.target, s.settings.pace, s.settings.loop, s.settings.fps) == (
        "replay", "/data/run1", "fast", True, 15.0)
    assert parse_uri("v4l2:").target == "/dev/video0"
    a = parse_uri("aravis:127.0.0.1?exposure_us=5000&gain_db=3&pixel_format=BayerRG8&timeout_s=0.5")
    assert (a.target, a.settings.exposure_us, a.settings.gain_db, a.settings.pixel_format, a.settings.timeout_s) == (
        "127.0.0.1", 5000.0, 3.0, "BayerRG8", 0.5)
    assert parse_uri("dc1394:00b09d0100a1b2c3").target == "00b09d0100a1b2c3"
    assert parse_uri("depthai:").target == ""
    assert parse_uri("depthai:1844301011B5C01200").target == "1844301011B5C01200"


def test_stereo_uri_splits_at_driver_names_and_takes_pair_options() -> None:
    s = parse_uri("stereo:[replay:a,b/left,replay:c?pace=fast]?max_skew_ms=2")
    assert s.driver == "stereo" and s.settings.max_skew_ms == 2.0
    assert s.left is not None and s.right is not None
    assert (s.left.target, s.right.target, s.right.settings.pace) == ("a,b/left", "c", "fast")
    assert s.uri == "stereo:replay:a,b/left,replay:c"


@pytest.mark.parametrize("uri, words", [
    ("nothing", "DRIVER:TARGET"),
    ("usb:0", "unknown driver 'usb'"),
    ("replay:", "needs a path"),
    ("replay:x?pace=slow", "field 'pace' must be one of recorded, fast"),
    ("aravis:x?gain=3", "field 'gain' is not a setting of the aravis driver"),
    ("aravis:x?trigger=sometimes", "field 'trigger' must be one of"),
    ("v4l2:/dev/video0?pixel_format=ABCD", "field 'pixel_format'"),
    ("v4l2:/dev/video0?width=-4", "field 'width' must be at least 1"),
    ("aravis:x?fps=fast", "field 'fps' must be a number"),
    ("dc1394:notahex", "must be hexadecimal"),
    ("stereo:replay:a", "stereo needs two sources"),
    ("stereo:depthai:,replay:b", "must be a mono camera"),
])
def test_bad_uris_name_the_problem(uri: str, words: str) -> None:
    with pytest.raises(ConfigError, match=words.replace("(", r"\(").replace("?", r"\?")):
        parse_uri(uri)


def test_config_sections() -> None:
    s = spec_from_config({"uri": "aravis:10.0.0.5?fps=10", "fps": 30, "exposure_us": 2000}, "cam.yaml")
    assert (s.driver, s.target, s.settings.fps, s.settings.exposure_us) == ("aravis", "10.0.0.5", 30.0, 2000.0)
    s = spec_from_config({"driver": "v4l2", "device": "/dev/video2", "width": 640, "height": 480}, "cam.yaml")
    assert (s.target, s.settings.width, s.settings.height) == ("/dev/video2", 640, 480)
    s = spec_from_config({"stereo": {"left": {"uri": "replay:l"}, "right": {"driver": "replay", "path": "r"},
                                     "max_skew_ms": 1.5, "timeout_s": 0.3}}, "cam.yaml")
    assert (s.left.target, s.right.target, s.settings.max_skew_ms, s.settings.timeout_s) == ("l", "r", 1.5, 0.3)


@pytest.mark.parametrize("section, words", [
    ({"uri": "replay:a", "exposure_us": 3}, "cam.yaml: field 'exposure_us' is not a setting of the replay driver"),
    ({"driver": "aravis", "nme": "x"}, "field 'nme' is not a setting of the aravis driver"),
    ({"driver": "firewire"}, "field 'driver' must be one of"),
    ({"driver": "replay"}, "field 'path' is missing"),
    ({"uri": "aravis:x", "name": "y"}, "field 'name' cannot be given together with 'uri'"),
    ({"uri": "aravis:x", "timeout_s": 0}, "field 'timeout_s' must be greater than 0"),
    ({"stereo": {"left": {"uri": "replay:a"}}}, "field 'stereo.right' is missing"),
    ({"stereo": {"left": {"uri": "replay:a"}, "right": {"uri": "replay:b", "loop": "yes"}}},
     "field 'stereo.right.loop' must be true or false"),
    ({"stereo": {"left": {"uri": "replay:a"}, "right": {"uri": "replay:b"}, "skew": 1}},
     "field 'stereo.skew' is not a field of a stereo section"),
])
def test_bad_sections_name_the_field(section: dict, words: str) -> None:
    with pytest.raises(ConfigError, match=words.replace("(", r"\(")):
        spec_from_config(section, "cam.yaml")


def test_packaged_example_sections_are_valid() -> None:
    from edgecal.config import ConfigReader, load_yaml_mapping, packaged_config_path
    path = packaged_config_path("sources.yaml")
    data = load_yaml_mapping(path)
    reader = ConfigReader(data, str(path))
    specs = {name: spec_from_config(reader.section(name)) for name in data}
    assert specs["two_usb_cameras"].driver == "stereo" and specs["gige_camera"].settings.latest_only
    assert {s.driver for s in specs.values()} == {"replay", "v4l2", "aravis", "dc1394", "depthai", "stereo", "mcap",
                                                 "rosbag"}
    assert (specs["robot_log_stereo"].settings.left, specs["ros1_bag_mono"].settings.topic) == (
        "/stereo/left/image_raw", "/camera/image_raw/compressed")


@pytest.mark.parametrize("uri, section", [
    ("replay:/data/run1?pace=fast&loop=true", {"driver": "replay", "path": "/data/run1", "pace": "fast", "loop": True}),
    ("aravis:10.0.0.5?exposure_us=2000", {"driver": "aravis", "name": "10.0.0.5", "exposure_us": 2000}),
    ("mcap:f.mcap?left=/l&right=/r", {"driver": "mcap", "path": "f.mcap", "left": "/l", "right": "/r"}),
    ("stereo:[v4l2:/dev/video0,v4l2:/dev/video2?fps=30]?max_skew_ms=3",
     {"stereo": {"left": {"driver": "v4l2", "device": "/dev/video0"},
                 "right": {"driver": "v4l2", "device": "/dev/video2", "fps": 30}, "max_skew_ms": 3}}),
])
def test_a_uri_is_the_mapping_of_its_config_section(uri: str, section: dict) -> None:
    """parse_uri builds the mapping a config section gives and validates it the same way."""
    from edgecal.drivers.spec import uri_mapping
    assert uri_mapping(uri) == section
    assert parse_uri(uri) == spec_from_config(section)
    if "stereo" not in section:      # a pair in a config file is a stereo: section, not uri: stereo:...
        assert parse_uri(uri) == spec_from_config({"uri": uri})


def test_each_driver_has_its_own_settings_class() -> None:
    from edgecal.config import describe_settings
    from edgecal.drivers.spec import DRIVERS, SourceSettings, settings_class
    for driver in DRIVERS:
        cls = settings_class(driver)
        assert issubclass(cls, SourceSettings) and all(doc for _, _, doc in describe_settings(cls)), driver
    assert type(parse_uri("replay:x").settings).__name__ == "ReplaySettings"
    assert not hasattr(parse_uri("replay:x").settings, "exposure_us")      # no union of every driver's fields
    assert parse_uri("v4l2:?buffers=8").settings.buffers == 8


def test_defaults_fill_what_a_section_and_its_uri_leave_out() -> None:
    """The live loop's latest_only: true, unless the section (or its URI, or its stereo pair) says false."""
    live = {"latest_only": True}
    assert spec_from_config({"driver": "replay", "path": "a"}, defaults=live).settings.latest_only
    off = {"driver": "replay", "path": "a", "latest_only": False}
    assert not spec_from_config(off, defaults=live).settings.latest_only
    assert spec_from_config({"uri": "replay:a"}, defaults=live).settings.latest_only
    assert not spec_from_config({"uri": "replay:a?latest_only=false"}, defaults=live).settings.latest_only
    pair = {"left": {"uri": "replay:a"}, "right": {"uri": "replay:b"}}
    s = spec_from_config({"stereo": pair}, defaults=live)
    assert s.settings.latest_only and not s.left.settings.latest_only     # the pair is wrapped, not each side
    assert not spec_from_config({"stereo": {**pair, "latest_only": False}}, defaults=live).settings.latest_only


def test_a_log_with_two_topics_is_no_side_of_a_pair() -> None:
    with pytest.raises(ConfigError, match="field 'stereo.left' must be a mono camera, not mcap with left and right"):
        spec_from_config({"stereo": {"left": {"uri": "mcap:f.mcap?left=/l&right=/r"}, "right": {"uri": "replay:b"}}})
