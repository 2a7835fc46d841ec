"""Board tracking across frames: where the robot's corners should be in the next stereo frame.

The live loop keeps the latest valid poses here and asks, before each frame, for the corners every
board of the target should show in the left and right images (the pose extrapolated to the frame's
capture stamp at constant velocity, then projected: edgecal.pose.predict). The detector then only
verifies those corners (edgecal.detection.tracking.track_boards) instead of searching both images,
which is what lets the loop keep up with 30 stereo frames a second. Any doubt - no recent pose, a gap
in the stream, an invalid pose, too few confirmed corners - and the loop searches the images again.

A prediction that is wrong cannot pass as a board: edgecal.detection.tracking explains the checks
(corners near their predictions and moving together, square colours, no corners beyond the board's
sides). ``max_gap_s`` bounds how far a pose is extrapolated: after a longer gap (a stalled camera, the
first search at start-up taking several frame intervals on a loaded machine) the frame is searched.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from edgecal.camera import StereoRig
from edgecal.config import setting
from edgecal.detection.types import CornerPrediction, Detection
from edgecal.pose.predict import extrapolate_pose, predict_corners
from edgecal.pose.types import Pose
from edgecal.targets import Target


@dataclass(frozen=True)
class TrackingSettings:
    """When the loop may verify predicted corners instead of searching the images (configs/robot.yaml).

    enabled:                 false: every frame is searched in full (the detector alone).
    max_gap_s:               predictions only from a pose whose frame is at most this much older than
                             the new one (a longer gap, e.g. a stalled camera, and the motion is unknown).
    min_confirmed_fraction:  share of the predicted corners (left and right together) of the boards the
                             last frame found that the detector must confirm for the tracked frame to stand;
                             fewer and the frame is searched. A board verification lost is first searched for
                             around its prediction; one not found there does not count (the pipeline's
                             FramePipeline._tracked_pose).
    """

    enabled: bool = setting(True, doc="false: search every frame in full")
    max_gap_s: float = setting(0.5, doc="predict only from a pose at most this much older (s)", positive=True,
                               maximum=10.0)
    min_confirmed_fraction: float = setting(0.6, doc="share of the predicted corners to confirm, else search",
                                            positive=True, maximum=1.0)


def confirmed_fraction(predictions: list[CornerPrediction], detections: list[Detection]) -> float:
    """Share of the predicted corners that the detections confirmed (0 when nothing was predicted)."""
    n_pred = sum(len(p.ids) for p in predictions)
    return sum(len(d.ids) for d in detections) / n_pred if n_pred else 0.0


class BoardTracker:
    """The last two valid poses of the stream and the corner predictions made from them."""

    def __init__(self, target: Target, cameras: StereoRig, settings: TrackingSettings) -> None:
        self.target = target
        self.cameras = cameras
        self.settings = settings
        self._poses: list[tuple[np.ndarray, np.ndarray, int]] = []   # (R, t_m, stamp_ns), oldest first

    def reset(self) -> None:
        """Forget the motion (after an invalid pose, a reopened camera or a reload)."""
        self._poses.clear()

    def _expected_pose(self, stamp_ns: int) -> tuple[np.ndarray, np.ndarray] | None:
        """T_rig_robot (R, t in metres) expected at ``stamp_ns``, or None when there is no recent pose to
        predict from (the frame must then be searched)."""
        if not self.settings.enabled or not self._poses:
            return None
        R_last, t_last, stamp_last = self._poses[-1]
        if not 0 <= stamp_ns - stamp_last <= self.settings.max_gap_s * 1e9:
            return None
        if len(self._poses) == 2:
            R_prev, t_prev, stamp_prev = self._poses[0]
            return extrapolate_pose(R_prev, t_prev, stamp_prev, R_last, t_last, stamp_last, stamp_ns)
        return R_last, t_last

    def predict(self, stamp_ns: int) -> tuple[list[CornerPrediction], list[CornerPrediction]] | None:
        """The corners expected in the left and right images of the frame captured at ``stamp_ns``, or None
        when there is no recent pose or no board is expected in either image."""
        expected = self._expected_pose(stamp_ns)
        if expected is None:
            return None
        left, right = (predict_corners(*expected, self.cameras, side, self.target) for side in ("left", "right"))
        return (left, right) if left or right else None

    def update(self, pose: Pose, stamp_ns: int) -> None:
        """Take the frame's pose: a valid one becomes the newest of the two kept, an invalid one resets."""
        if not pose.valid or not np.all(np.isfinite(pose.t_m)):
            self.reset()
            return
        if self._poses and stamp_ns <= self._poses[-1][2]:
            self.reset()                 # the stream went back in time (a replay that loops)
        self._poses = self._poses[-1:] + [(np.array(pose.R, dtype=np.float64), np.array(pose.t_m, dtype=np.float64),
                                           int(stamp_ns))]
