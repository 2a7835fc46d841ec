"""edgecal: chessboard detection, one-shot stereo calibration and live robot pose."""

from edgecal.runtime import tune_allocator

tune_allocator()

from edgecal.detection.detector import detect, detect_debug
from edgecal.detection.params import DetectorParams, load_params
from edgecal.detection.types import Detection, DetectionDebug
from edgecal.targets import Board, Target, load_target, parse_board_spec

__all__ = ["Board", "Detection", "DetectionDebug", "DetectorParams", "Target", "detect", "detect_debug",
           "load_params", "load_target", "parse_board_spec"]
__version__ = "0.1.0"
