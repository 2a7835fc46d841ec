"""Robot pose from a calibrated stereo pair: triangulate, fit rigidly, refine, estimate the covariance.

Pure functions: detections, target and a StereoRig (edgecal.camera) in, a :class:`Pose` out (see docs/conventions.md for
frames and units).
"""

from edgecal.pose.estimate import check_quality, estimate_pose
from edgecal.pose.refine import CameraView, pose_covariance, refine_pose
from edgecal.pose.rigid import fit_rigid
from edgecal.pose.types import Pose, PoseSettings, QualityBounds

__all__ = ["CameraView", "Pose", "PoseSettings", "QualityBounds", "check_quality", "estimate_pose", "fit_rigid",
           "pose_covariance", "refine_pose"]
