"""Camera drivers behind one Source interface (imported as ``edgecal.drivers``).

``open_source("replay:recordings/run1")`` (or a config section) gives a Source; hardware drivers import
their libraries only when such a source is opened. See docs/drivers.md.
"""

from edgecal.drivers.base import Frame, Source, StereoFrame, StereoSource
from edgecal.drivers.factory import open_source
from edgecal.drivers.latest import LatestFrameSource
from edgecal.drivers.recording import record
from edgecal.drivers.spec import SourceSettings, SourceSpec, parse_uri, spec_from_config
from edgecal.drivers.stereo import PairedStereoSource, TimestampPairer

__all__ = ["Frame", "Source", "StereoFrame", "StereoSource", "open_source", "LatestFrameSource", "record",
           "SourceSettings", "SourceSpec", "parse_uri", "spec_from_config", "PairedStereoSource",
           "TimestampPairer"]
