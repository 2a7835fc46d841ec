"""The live loop's config file (configs/robot.yaml), validated field by field before any device opens.

::

    source:                      # a drivers source section (see edgecal/drivers/spec.py)
      uri: replay:out/demo/robot?loop=true
    rig: out/demo/rig.yaml       # stereo calibration (cv2.FileStorage, T in metres)
    target: targets/robot-3boards.yaml
    detector: null               # optional detector thresholds file (configs/detector.yaml format)
    pose:    {triangulation: linear, covariance_scale: model, corner_noise_px: 0.1, outlier_sigmas: 4.0,
              outlier_min_px: 0.5,
              min_corners: 8, max_rms_px: 1.0, max_position_std_mm: 5.0, max_rotation_std_deg: 1.0}
    tracking: {enabled: true, max_gap_s: 0.5, min_confirmed_fraction: 0.6}
    publish: {endpoint: "tcp://127.0.0.1:5560", allow_remote: false, hwm: 4, handshake_timeout_s: 2.0,
              curve: {server_key: keys/server.key_secret, client_keys: keys/clients}}   # curve: beyond loopback
    loop:    {latest_frame_wins: true, status_period_s: 1.0, camera_lost_after_s: 2.0,
              reconnect_min_s: 0.5, reconnect_max_s: 10.0, stop_at_end: true}

Relative paths are taken from the current directory; a target or detector file that is not found
there is looked up among the files shipped in configs/ (e.g. ``targets/robot-3boards.yaml``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from edgecal.camera import StereoRig
from edgecal.config import ConfigReader, load_yaml_mapping, packaged_config_path
from edgecal.detection.params import DetectorParams, load_params
from edgecal.drivers.spec import SourceSpec, spec_from_config
from edgecal.errors import ConfigError, EdgecalError, InputError, exception_summary, quote
from edgecal.pose.types import PoseSettings, QualityBounds
from edgecal.publish.curve import ServerKeys, load_server_keys, read_key_file
from edgecal.publish.publisher import DEFAULT_ENDPOINT, HANDSHAKE_TIMEOUT_S, endpoint_problem, is_local_endpoint
from edgecal.publish.sink_settings import OUTPUT_FIELDS, OutputSettings, read_outputs
from edgecal.stream.tracker import TrackingSettings
from edgecal.targets import Target, load_target


@dataclass(frozen=True)
class LoopSettings:
    """Timing of the loop itself."""

    latest_frame_wins: bool = True     # read through a latest-frame-wins wrapper (latency never grows)
    status_period_s: float = 1.0       # log + status message + watchdog period
    camera_lost_after_s: float = 2.0   # no frame for this long: close the camera and reopen it
    reconnect_min_s: float = 0.5       # first wait before reopening; doubles up to reconnect_max_s
    reconnect_max_s: float = 10.0
    stop_at_end: bool = True           # a finite source (a replay) that ends stops the loop (exit 0)


@dataclass(frozen=True)
class PublishSettings:
    """Where and how poses are published."""

    endpoint: str = DEFAULT_ENDPOINT
    allow_remote: bool = False
    hwm: int = 4
    handshake_timeout_s: float = HANDSHAKE_TIMEOUT_S
    curve: ServerKeys | None = None     # required beyond loopback; optional (and then enforced) on it


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
    raise r.fail(key, f"names a file that does not exist: {quote(name)}")


def _read_pose(r: ConfigReader) -> PoseSettings:
    r.reject_unknown(("triangulation", "covariance_scale", "corner_noise_px", "outlier_sigmas", "outlier_min_px",
                      "min_corners", "max_rms_px", "max_position_std_mm", "max_rotation_std_deg"))
    d, b = PoseSettings(), QualityBounds()
    bounds = QualityBounds(
        min_corners=r.integer("min_corners", b.min_corners, minimum=3),
        max_rms_px=r.number("max_rms_px", b.max_rms_px, positive=True),
        max_position_std_mm=r.number("max_position_std_mm", b.max_position_std_mm, positive=True),
        max_rotation_std_deg=r.number("max_rotation_std_deg", b.max_rotation_std_deg, positive=True))
    return PoseSettings(
        triangulation=r.string("triangulation", d.triangulation, choices=("optimal", "linear")),
        covariance_scale=r.string("covariance_scale", d.covariance_scale,
                                  choices=("model", "max", "residual", "noise")),
        corner_noise_px=r.number("corner_noise_px", d.corner_noise_px, positive=True),
        outlier_sigmas=r.number("outlier_sigmas", d.outlier_sigmas, minimum=2.0),
        outlier_min_px=r.number("outlier_min_px", d.outlier_min_px, positive=True),
        bounds=bounds)


def _read_curve(r: ConfigReader) -> ServerKeys:
    r.reject_unknown(("server_key", "client_keys"))
    server_key = Path(r.string("server_key")).expanduser()
    client_keys = Path(r.string("client_keys")).expanduser()
    try:
        read_key_file(server_key, need_secret=True)    # its own field named when it is the wrong one
    except InputError as exc:
        raise r.fail("server_key", f"cannot be used: {exc}") from None
    try:
        return load_server_keys(server_key, client_keys)
    except InputError as exc:
        raise r.fail("client_keys", f"cannot be used: {exc}") from None


def _read_publish(r: ConfigReader) -> PublishSettings:
    r.reject_unknown(("endpoint", "allow_remote", "hwm", "handshake_timeout_s", "curve")
                     + OUTPUT_FIELDS)  # outputs: read_outputs
    endpoint = r.string("endpoint", DEFAULT_ENDPOINT)
    allow = r.boolean("allow_remote", False)
    problem = endpoint_problem(endpoint, allow)
    if problem is not None:
        raise r.fail("endpoint", f"{problem} (got {quote(endpoint)})")
    curve = _read_curve(r.section("curve")) if r.has("curve") else None
    if curve is None and not is_local_endpoint(endpoint):
        raise r.fail("curve", f"is missing: beyond the loopback interface ({quote(endpoint)}) only subscribers "
                              "with a known key may listen; give curve.server_key and curve.client_keys "
                              "(`edgecal keys` makes key pairs)")
    return PublishSettings(endpoint, allow, r.integer("hwm", 4, minimum=1, maximum=1000),
                           r.number("handshake_timeout_s", HANDSHAKE_TIMEOUT_S, minimum=0.1, maximum=60), curve)


def _read_loop(r: ConfigReader) -> LoopSettings:
    r.reject_unknown(("latest_frame_wins", "status_period_s", "camera_lost_after_s", "reconnect_min_s",
                      "reconnect_max_s", "stop_at_end"))
    d = LoopSettings()
    lo = r.number("reconnect_min_s", d.reconnect_min_s, positive=True, maximum=3600)
    hi = r.number("reconnect_max_s", d.reconnect_max_s, positive=True, maximum=3600)
    if hi < lo:
        raise r.fail("reconnect_max_s", f"must be at least reconnect_min_s ({lo:g})")
    return LoopSettings(
        latest_frame_wins=r.boolean("latest_frame_wins", d.latest_frame_wins),
        status_period_s=r.number("status_period_s", d.status_period_s, minimum=0.05, maximum=60),
        camera_lost_after_s=r.number("camera_lost_after_s", d.camera_lost_after_s, minimum=0.1, maximum=600),
        reconnect_min_s=lo, reconnect_max_s=hi,
        stop_at_end=r.boolean("stop_at_end", d.stop_at_end))


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


def _read_tracking(r: ConfigReader) -> TrackingSettings:
    r.reject_unknown(("enabled", "max_gap_s", "min_confirmed_fraction"))
    d = TrackingSettings()
    return TrackingSettings(
        enabled=r.boolean("enabled", d.enabled),
        max_gap_s=r.number("max_gap_s", d.max_gap_s, positive=True, maximum=10.0),
        min_confirmed_fraction=r.number("min_confirmed_fraction", d.min_confirmed_fraction, positive=True,
                                        maximum=1.0))


MONO_DRIVERS = ("v4l2", "aravis", "dc1394")


def _declared_sizes(spec: SourceSpec) -> list[tuple[str, tuple[int, int]]]:
    """(which camera, (width, height)) for each camera whose image size the config sets."""
    parts = [("left", spec.left), ("right", spec.right)] if spec.driver == "stereo" else [("source", spec)]
    return [(name, (p.settings.width, p.settings.height)) for name, p in parts
            if p is not None and p.settings.width is not None and p.settings.height is not None]


def check_source(r: ConfigReader, spec: SourceSpec, rig_size: tuple[int, int]) -> None:
    """What would only fail once the loop runs: a mono source, a replay that is missing or holds no frames,
    images of another size than the rig's (a replay's first frame, or the size a camera is set to)."""
    stereo_hint = "the live loop needs a stereo source (a 'stereo:' section with two cameras, depthai:, or a " \
        "replay of left/ and right/)"
    if spec.driver in MONO_DRIVERS:
        raise r.fail("source", f"{spec.uri} is one camera: {stereo_hint}")
    sizes = _declared_sizes(spec)
    if spec.driver == "replay":
        from edgecal.drivers.replay import replay_contents

        try:
            contents = replay_contents(spec)
        except EdgecalError as exc:
            raise r.fail("source", f"cannot be replayed: {exc}") from None
        if contents.frames == 0:
            raise r.fail("source", f"{spec.target} holds no frames to replay")
        if not contents.stereo:
            raise r.fail("source", f"{spec.target} holds single images: {stereo_hint}")
        if contents.image_size is not None:
            sizes.append(("replay", contents.image_size))
    w, h = rig_size
    for name, (sw, sh) in sizes:
        if (sw, sh) != (w, h):
            raise r.fail("rig", f"was calibrated at {w}x{h} but the {name} images are {sw}x{sh} "
                                "(calibrate at the size the cameras deliver)")


LIVE_FIELDS = ("source", "rig", "target", "detector", "pose", "tracking", "publish", "loop")


def load_live_config(path: str | Path) -> LiveConfig:
    """Load and validate a live-loop config; every problem is a ConfigError naming the field.

    Opens no device: the source section is only parsed (a replay's file list is read and its first image
    decoded, to check its size against the rig's); the rig, target and detector files are read.
    """
    src = str(path)
    r = ConfigReader(load_yaml_mapping(path), src)
    r.reject_unknown(LIVE_FIELDS)
    source = spec_from_config(r.section("source"))
    rig_path = _resolve(r, "rig", packaged=False)
    cameras = load_stereo_cameras(rig_path, "rig", src)
    check_source(r, source, cameras.image_size)
    target_path = _resolve(r, "target", packaged=True)
    try:
        target = load_target(target_path)
    except ConfigError as exc:
        raise ConfigError(f"{src}: field 'target': {exc}") from None
    detector = None
    if r.has("detector"):
        try:
            detector = load_params(_resolve(r, "detector", packaged=True))
        except ConfigError as exc:
            raise ConfigError(f"{src}: field 'detector': {exc}") from None
    pose = _read_pose(r.section("pose", {}))
    publish = _read_publish(r.section("publish", {}))
    outputs = read_outputs(r.section("publish", {}))
    loop = _read_loop(r.section("loop", {}))
    tracking = _read_tracking(r.section("tracking", {}))
    return LiveConfig(src, source, cameras, target, detector, pose, publish, loop, str(rig_path), tracking, outputs)
