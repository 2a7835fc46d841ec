"""``open_source``: from a URI or a config section to a Source, importing only the driver it needs.

Hardware libraries (gi/Aravis, libdc1394, depthai) are imported inside their driver, so a robot
without them can still replay recordings, and a missing library is a DeviceError that says what to
install.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from edgecal.config import ConfigReader
from edgecal.drivers.base import Source, StereoSource
from edgecal.drivers.latest import LatestFrameSource, LatestStereoFrameSource
from edgecal.drivers.spec import SourceSpec, as_spec


def _build(spec: SourceSpec) -> Source:
    if spec.driver == "replay":
        from edgecal.drivers.replay import open_replay
        return open_replay(spec)
    if spec.driver == "stereo":
        from edgecal.drivers.stereo import PairedStereoSource
        assert spec.left is not None and spec.right is not None
        return PairedStereoSource(open_source(spec.left), open_source(spec.right),
                                  int(spec.settings.max_skew_ms * 1e6), spec.settings.timeout_s, spec.uri)
    if spec.driver == "mcap":
        from edgecal.drivers.mcap_source import open_mcap
        return open_mcap(spec)
    if spec.driver == "rosbag":
        from edgecal.drivers.rosbag_source import open_rosbag
        return open_rosbag(spec)
    if spec.driver == "aravis":
        from edgecal.drivers.aravis import AravisSource
        return AravisSource(spec)
    if spec.driver == "v4l2":
        from edgecal.drivers.v4l2 import V4L2Source
        return V4L2Source(spec)
    if spec.driver == "dc1394":
        from edgecal.drivers.dc1394 import DC1394Source
        return DC1394Source(spec)
    if spec.driver == "depthai":
        from edgecal.drivers.oak import OakStereoSource
        return OakStereoSource(spec)
    raise AssertionError(f"driver {spec.driver} has no builder")  # spec validation lists every driver


def open_source(uri_or_config: str | Mapping[str, Any] | ConfigReader | SourceSpec) -> Source:
    """A Source for a URI (``replay:PATH``, ``aravis:NAME``, ...) or a validated config section.

    The source is not opened yet: use it as a context manager (``with open_source(uri) as src``).
    With ``latest_only: true`` it is wrapped in a latest-frame-wins background reader.
    """
    spec = as_spec(uri_or_config)
    source = _build(spec)
    if spec.settings.latest_only:
        wrapper = LatestStereoFrameSource if isinstance(source, StereoSource) else LatestFrameSource
        return wrapper(source, spec.settings.timeout_s)
    return source
