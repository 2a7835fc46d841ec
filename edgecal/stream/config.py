"""The live loop's config file (configs/robot.yaml), validated field by field before any device opens.

::

    source:                      # a drivers source section (see edgecal/drivers/spec.py)
      uri: replay:out/demo/robot?loop=true
      latest_only: true          # the live loop's default: always work on the newest frame
    rig: out/demo/rig.yaml       # stereo calibration (cv2.FileStorage, T in metres)
    target: targets/robot-3boards.yaml
    detector: null               # optional detector thresholds file (configs/detector.yaml format)
    pose:    {triangulation: linear, covariance_scale: model, corner_noise_px: 0.1, outlier_sigmas: 4.0,
              outlier_min_px: 0.5,
              min_corners: 8, max_rms_px: 1.0, max_position_std_mm: 5.0, max_rotation_std_deg: 1.0}
    tracking: {enabled: true, max_gap_s: 0.5, min_confirmed_fraction: 0.6}
    publish: {endpoint: "tcp://127.0.0.1:5560", allow_remote: false, hwm: 4, handshake_timeout_s: 2.0,
              max_connections: 64,
              curve: {server_key: keys/server.key_secret, client_keys: keys/clients}}   # curve: beyond loopback
    loop:    {status_period_s: 1.0, camera_lost_after_s: 2.0, reconnect_min_s: 0.5, reconnect_max_s: 10.0,
              stop_at_end: true}

Relative paths are taken from the current directory; a target or detector file that is not found
there is looked up among the files shipped in configs/ (e.g. ``targets/robot-3boards.yaml``).
Each section is a settings dataclass beside the code that uses it, read by edgecal.config.read_settings; so
is the top level (:class:`LiveFile`: the rig, target and detector files read by their fields' readers, the
source checked against the rig as soon as both are read).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

from edgecal.camera import StereoRig
from edgecal.config import ConfigReader, load_yaml_mapping, packaged_config_path, read_settings, section_keys, setting
from edgecal.detection.params import DetectorParams, load_params
from edgecal.drivers.spec import SourceSpec, spec_from_config
from edgecal.errors import ConfigError, EdgecalError, exception_summary, quote
from edgecal.pose.types import PoseSettings
from edgecal.publish.publisher import PublishSettings
from edgecal.publish.sink_settings import OUTPUT_FIELDS, OutputSettings, read_outputs
from edgecal.stream.tracker import TrackingSettings
from edgecal.targets import Target, load_target


@dataclass(frozen=True)
class LoopSettings:
    """Timing of the loop itself (latest-frame-wins is the source's ``latest_only``)."""

    status_period_s: float = setting(1.0, doc="log + status message + watchdog period (s)", minimum=0.05,
                                     maximum=60)
    camera_lost_after_s: float = setting(2.0, doc="no frame for this long: close the camera and reopen it (s)",
                                         minimum=0.1, maximum=600)
    reconnect_min_s: float = setting(0.5, doc="first wait before reopening; doubles up to reconnect_max_s (s)",
                                     positive=True, maximum=3600)
    reconnect_max_s: float = setting(10.0, doc="longest wait between reopen attempts (s)", positive=True,
                                     maximum=3600)
    stop_at_end: bool = setting(True, doc="a finite source (a replay) that ends stops the loop (exit 0)")

    def config_problem(self) -> tuple[str, str] | None:
        """The back-off's ceiling below its floor."""
        if self.reconnect_max_s < self.reconnect_min_s:
            return ("reconnect_max_s", f"must be at least reconnect_min_s ({self.reconnect_min_s:g})")
        return None


# Keys of the loop section that moved elsewhere -> what to write instead.
RETIRED_LOOP_KEYS = {"latest_frame_wins": "set source.latest_only instead (true by default in the live loop: "
                                          "the source's reader keeps only the newest frame)"}


@dataclass(frozen=True)
class LiveConfig:
    """Everything ``edgecal run`` needs, loaded and checked."""

    path: str
    source: SourceSpec
    cameras: StereoRig
    target: Target
    detector: DetectorParams | None
    pose: PoseSettings
    publish: PublishSettings
    loop: LoopSettings
    rig_path: str
    tracking: TrackingSettings = TrackingSettings()
    outputs: OutputSettings = OutputSettings()     # publish: frame names, stamps, MCAP log, Foxglove


def _resolve(r: ConfigReader, key: str, packaged: bool) -> Path:
    name = r.string(key)
    p = Path(name).expanduser()
    if p.is_file():
        return p
    if packaged and not p.is_absolute():
        q = packaged_config_path(name)
        if q.is_file():
            return q
    if p.is_dir():
        raise r.fail(key, f"names a folder, not a file: {quote(name)}")
    raise r.fail(key, f"names a file that does not exist: {quote(name)}")


def read_publish(r: ConfigReader) -> tuple[PublishSettings, OutputSettings]:
    """The ``publish:`` section: the ZeroMQ stream's settings and the outputs beside it (sink_settings)."""
    return (read_settings(PublishSettings, r, ignore=OUTPUT_FIELDS),
            read_outputs(r, ignore=section_keys(PublishSettings)))


def load_stereo_cameras(path: Path, field: str, source: str) -> StereoRig:
    """The stereo pair of a rig.yaml; a mono or unreadable file is a ConfigError naming ``field``."""
    from edgecal.calibration.io import load_rig

    try:
        rig = load_rig(path)
    except EdgecalError as exc:
        raise ConfigError(f"{source}: field '{field}': {exc}") from None
    except Exception as exc:  # noqa: BLE001 - OpenCV raises cv2.error/SystemError on some files
        raise ConfigError(f"{source}: field '{field}': {path}: not a readable calibration file "
                          f"({exception_summary(exc)})") from None
    if not rig.is_stereo:
        raise ConfigError(f"{source}: field '{field}': {path} holds one camera; the live loop needs a stereo rig")
    assert rig.stereo is not None
    return rig.stereo


MONO_DRIVERS = ("v4l2", "aravis", "dc1394")


def _declared_sizes(spec: SourceSpec) -> list[tuple[str, tuple[int, int]]]:
    """(which camera, (width, height)) for each camera whose image size the config sets."""
    parts = [("left", spec.left), ("right", spec.right)] if spec.driver == "stereo" else [("source", spec)]
    sizes = [(name, getattr(p.settings, "width", None), getattr(p.settings, "height", None)) for name, p in parts
             if p is not None]
    return [(name, (w, h)) for name, w, h in sizes if w is not None and h is not None]


def source_problem(spec: SourceSpec, rig_size: tuple[int, int]) -> tuple[str, str] | None:
    """What would only fail once the loop runs, as (field, what): a mono source, a replay that is missing or
    holds no frames, images of another size than the rig's (a replay's first frame, or a camera's set size)."""
    stereo_hint = "the live loop needs a stereo source (a 'stereo:' section with two cameras, depthai:, or a " \
        "replay of left/ and right/)"
    if spec.driver in MONO_DRIVERS:
        return ("source", f"{spec.uri} is one camera: {stereo_hint}")
    sizes = _declared_sizes(spec)
    if spec.driver == "replay":
        from edgecal.drivers.replay import replay_contents

        try:
            contents = replay_contents(spec)
        except EdgecalError as exc:
            return ("source", f"cannot be replayed: {exc}")
        if contents.frames == 0:
            return ("source", f"{spec.target} holds no frames to replay")
        if not contents.stereo:
            return ("source", f"{spec.target} holds single images: {stereo_hint}")
        if contents.image_size is not None:
            sizes.append(("replay", contents.image_size))
    w, h = rig_size
    for name, (sw, sh) in sizes:
        if (sw, sh) != (w, h):
            return ("rig", f"was calibrated at {w}x{h} but the {name} images are {sw}x{sh} "
                           "(calibrate at the size the cameras deliver)")
    return None


class LoadedRig(NamedTuple):
    """The ``rig:`` field: the rig.yaml it names and the stereo pair read from it."""

    path: Path
    cameras: StereoRig


def _read_source(r: ConfigReader, key: str) -> SourceSpec:
    # The live loop always works on the newest frame unless the source says otherwise.
    return spec_from_config(r.section(key), defaults={"latest_only": True})


def _read_rig(r: ConfigReader, key: str) -> LoadedRig:
    path = _resolve(r, key, packaged=False)
    return LoadedRig(path, load_stereo_cameras(path, key, r.source))


def _read_target(r: ConfigReader, key: str) -> Target:
    path = _resolve(r, key, packaged=True)
    try:
        return load_target(path)
    except ConfigError as exc:
        raise ConfigError(f"{r.source}: field '{key}': {exc}") from None


def _read_detector(r: ConfigReader, key: str) -> DetectorParams | None:
    if r.data[key] is None:          # `detector: null`, as the example above writes it: the built-in thresholds
        return None
    path = _resolve(r, key, packaged=True)
    try:
        return load_params(path)
    except ConfigError as exc:
        raise ConfigError(f"{r.source}: field '{key}': {exc}") from None


def _read_publish(r: ConfigReader, key: str) -> tuple[PublishSettings, OutputSettings]:
    return read_publish(r.section(key, {}))


def _read_loop(r: ConfigReader, key: str) -> LoopSettings:
    return read_settings(LoopSettings, r.section(key, {}), retired=RETIRED_LOOP_KEYS)


@dataclass(frozen=True)
class SourceAndRig:
    """The ``source:`` and ``rig:`` fields, checked against each other as soon as both are read (no device is
    opened: a replay's first image is decoded for its size)."""

    source: SourceSpec = setting(doc="the stereo source: a drivers source section (edgecal/drivers/spec.py)",
                                 read=_read_source)
    rig: LoadedRig = setting(doc="the stereo calibration (rig.yaml: cv2.FileStorage, T in metres)", read=_read_rig)

    def config_problem(self) -> tuple[str, str] | None:
        """The source refused by the rig (see source_problem)."""
        return source_problem(self.source, self.rig.cameras.image_size)


@dataclass(frozen=True)
class LiveFile:
    """The live config file's top level as read, in the order its fields are checked; :func:`load_live_config`
    makes the LiveConfig the loop uses of it."""

    cameras: SourceAndRig = setting(doc="source and rig", inline=True)
    target: Target = setting(doc="the target file (also looked up among the shipped configs/)", read=_read_target)
    detector: DetectorParams | None = setting(None, doc="optional detector thresholds file (configs/detector.yaml "
                                                        "format)", read=_read_detector)
    pose: PoseSettings = setting(PoseSettings(), doc="pose estimation and its quality bounds")
    tracking: TrackingSettings = setting(TrackingSettings(), doc="when predicted corners are verified, not searched")
    publish: tuple[PublishSettings, OutputSettings] = setting((PublishSettings(), OutputSettings()),
                                                              doc="the ZeroMQ stream and the outputs beside it",
                                                              read=_read_publish)
    loop: LoopSettings = setting(LoopSettings(), doc="the loop's timing", read=_read_loop)


LIVE_FIELDS = section_keys(LiveFile)


def load_live_config(path: str | Path) -> LiveConfig:
    """Load and validate a live-loop config; every problem is a ConfigError naming the field.

    Opens no device: the source section is only parsed (a replay's file list is read and its first image
    decoded, to check its size against the rig's); the rig, target and detector files are read.
    """
    src = str(path)
    f = read_settings(LiveFile, ConfigReader(load_yaml_mapping(path), src))
    publish, outputs = f.publish
    source, rig = f.cameras.source, f.cameras.rig
    return LiveConfig(src, source, rig.cameras, f.target, f.detector, f.pose, publish, f.loop, str(rig.path),
                      f.tracking, outputs)
