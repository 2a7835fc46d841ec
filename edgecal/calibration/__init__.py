"""Camera calibration: one-shot from a calibration box (mono and stereo) and planar multi-view.

Modules: dlt / tsai (linear starts from non-coplanar points), refine (robust least squares with
standard deviations), mono and stereo (one-shot box calibration), planar (many views of a flat
board via OpenCV), assign (detections -> target boards), io (rig.yaml, camera_info, load_rig),
report (overlays and summary), settings and acceptance (configs/calibration.yaml).
"""

from edgecal.calibration.io import RigFile, load_rig, write_calibration
from edgecal.calibration.types import Calibration, CornerSet, RigidTransform

__all__ = ["Calibration", "CornerSet", "RigidTransform", "RigFile", "load_rig", "write_calibration"]
