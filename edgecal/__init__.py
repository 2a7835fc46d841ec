"""edgecal: chessboard detection, one-shot stereo calibration and live robot pose.

Importing edgecal changes nothing in the process: the glibc allocator tuning the commands apply
(edgecal.runtime.tune_allocator) is for a program that processes images to call itself.
"""

from edgecal.detection.detector import detect, detect_debug
from edgecal.detection.params import DetectorParams, load_params
from edgecal.detection.types import Detection, DetectionDebug
from edgecal.runtime import tune_allocator
from edgecal.targets import Board, Target, load_target, parse_board_spec
from edgecal.version import __version__

__all__ = ["Board", "Detection", "DetectionDebug", "DetectorParams", "Target", "__version__", "detect", "detect_debug",
           "load_params", "load_target", "parse_board_spec", "tune_allocator"]
