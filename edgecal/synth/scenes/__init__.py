"""Ready-made scenes for tests, the demo and the benchmarks, each deterministic from a seed.

The package face: views (one camera), box (the calibration box in stereo), robot (the robot sequence),
common (seeds, random cameras, board placement).

- :func:`planar_view`: one board, random tilt / roll / position, square size given in pixels;
- :func:`hard_view`, :func:`partial_view`, :func:`occluded_view`: the same in poor conditions, cut by the
  image border, partly hidden behind a plate;
- :func:`negative_view`: clutter with checker-like distractors and no board;
- :func:`multi_view`: 2..3 boards of different grids in one image;
- :func:`box_stereo`: the calibration box (configs/targets/box-100mm.yaml) seen by a stereo pair;
- :func:`robot_sequence`: a stereo rig at 30 fps watching a robot that carries three boards
  (configs/targets/robot-3boards.yaml), with the true T_rig_robot of every frame.

The square size in pixels is the *nominal* one: focal length x square_mm / depth of the board centre
(before tilt foreshortening), so a test can ask for "8 px squares" directly.
"""

from edgecal.synth.scenes.box import StereoView, box_stereo, box_target
from edgecal.synth.scenes.common import FloatOrRange, SeedLike, place_board, random_camera
from edgecal.synth.scenes.robot import (
    ROBOT_BODY_MM,
    ROBOT_HFOV_DEG,
    RobotFrame,
    RobotRig,
    robot_pose_world,
    robot_rig,
    robot_sequence,
    robot_target,
)
from edgecal.synth.scenes.views import (
    MULTI_GRIDS,
    hard_view,
    multi_view,
    negative_view,
    occluded_view,
    partial_view,
    planar_view,
)

__all__ = ["FloatOrRange", "MULTI_GRIDS", "ROBOT_BODY_MM", "ROBOT_HFOV_DEG", "RobotFrame", "RobotRig", "SeedLike",
           "StereoView", "box_stereo", "box_target", "hard_view", "multi_view", "negative_view", "occluded_view",
           "partial_view", "place_board", "planar_view", "random_camera", "robot_pose_world", "robot_rig",
           "robot_sequence", "robot_target"]
