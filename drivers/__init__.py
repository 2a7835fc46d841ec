"""Camera drivers behind one Source interface (imported as ``edgecal.drivers``)."""

from edgecal.drivers.base import Frame, Source, StereoFrame, StereoSource

__all__ = ["Frame", "Source", "StereoFrame", "StereoSource"]
