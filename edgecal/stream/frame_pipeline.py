"""The work on one stereo frame: check the two images, track or search the boards, estimate the pose.

Everything here is per frame and knows nothing of the camera, the sockets, reloads or status: the live
loop (edgecal.stream.loop) supervises, calls :meth:`FramePipeline.process` once per frame, then has the
message built (edgecal.publish.messages.pose_message) and hands it to the sinks. What the pipeline carries
from one frame to the next is the tracker's recent poses and the worker thread for the right image.

Each image is checked once, when it arrives (:func:`grey_image`): the rig's size, then the detector's
own check and conversion to 8-bit grey; tracking and the full search both work on that grey image (a
colour frame is converted once, not once per detector call).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import cv2
import numpy as np

from edgecal.camera import StereoRig
from edgecal.detection.detector import detect
from edgecal.detection.params import DetectorParams
from edgecal.detection.tracking import TrackedBoards, search_near, track_boards, verify_boards
from edgecal.detection.types import CornerPrediction, Detection
from edgecal.drivers.base import StereoFrame
from edgecal.errors import InputError
from edgecal.images import as_grey
from edgecal.pose import Pose, estimate_pose
from edgecal.pose.types import PoseSettings
from edgecal.stream.tracker import BoardTracker, TrackingSettings, confirmed_fraction
from edgecal.targets import Target

CLOCK_PLAUSIBLE_NS = 60 * 10**9   # a capture stamp further than this from monotonic now is on another clock


def capture_time_ns(frame: StereoFrame, now_ns: int, recorded: bool) -> tuple[int, str]:
    """The host-monotonic time the pair was captured, and what it is based on.

    Device stamps mapped to CLOCK_MONOTONIC are used as they are ("capture"). A replay's stamps are the
    recorded ones (``recorded``), and a device clock that was not mapped is far from now; for both, the
    time the frame reached edgecal is used instead ("receive").
    """
    stamp = frame.stamp_ns
    if not recorded and 0 <= now_ns - stamp < CLOCK_PLAUSIBLE_NS:
        return stamp, "capture"
    return min(frame.left.recv_ns, frame.right.recv_ns), "receive"


def grey_image(image: object, size: tuple[int, int], side: str) -> tuple[np.ndarray | None, str | None]:
    """``image`` as the detector's 8-bit grey image, or None and why it cannot be used: not an array, not
    the rig's size (``size`` = width, height; 0 = unknown), or a type or shape the detector does not read."""
    if not isinstance(image, np.ndarray):
        return None, f"{side} image is {type(image).__name__}, not an array"
    w, h = size
    if w and h and image.ndim >= 2 and (image.shape[1], image.shape[0]) != (w, h):
        return None, f"{side} image is {image.shape[1]}x{image.shape[0]}, the rig was calibrated at {w}x{h}"
    try:
        return as_grey(image, f"{side} image"), None
    except InputError as exc:
        return None, str(exc)


def warm_up_image(size: tuple[int, int], cols: int, rows: int, outer: float = 0.4) -> np.ndarray:
    """A grey image of ``size`` (width, height) with a slightly blurred chessboard of ``cols`` x ``rows``
    inner corners in its middle, its outer squares cut to ``outer`` of a square: something for every stage
    of the detector to work on, the rim refinement's kernels (subpixel.refine_rim) included."""
    w, h = size
    square = int(max(8, min(40, w // (cols + 3), h // (rows + 3))))
    image = np.full((h, w), 200, np.uint8)
    x0, y0 = (w - (cols + 1) * square) // 2, (h - (rows + 1) * square) // 2
    cut = int(round((1.0 - outer) * square))
    for r in range(rows + 1):
        for c in range(cols + 1):
            if (r + c) % 2 == 0:
                xa = x0 + c * square + (cut if c == 0 else 0)
                xb = x0 + (c + 1) * square - (cut if c == cols else 0)
                ya = y0 + r * square + (cut if r == 0 else 0)
                yb = y0 + (r + 1) * square - (cut if r == rows else 0)
                image[ya:yb, xa:xb] = 40
    return cv2.GaussianBlur(image, (5, 5), 1.0)


@dataclass
class FrameResult:
    """What the pipeline made of one stereo frame.

    detections:    the boards found (tracked or searched) in the left and right image.
    tracked:       True when the predicted corners were verified; False when the images were searched.
    failed_images: readable images (0-2) in which no board was found.
    problems:      why an image could not be used (a corrupt frame), one line per image.
    error:         an unexpected exception (a bug) met on the way; the pose is then invalid.
    """

    pose: Pose
    detections: tuple[list[Detection], list[Detection]] = field(default_factory=lambda: ([], []))
    tracked: bool = False
    failed_images: int = 0
    problems: list[str] = field(default_factory=list)
    error: Exception | None = None

    @property
    def detection(self) -> str:
        """How the boards were found: "tracked" or "searched" (the pose message's quality.detection)."""
        return "tracked" if self.tracked else "searched"


class FramePipeline:
    """Poses from stereo frames, one call per frame. The target, rig, detector, pose and tracking settings are
    fixed for its lifetime (a reload makes a new one with :meth:`reconfigured`)."""

    def __init__(self, target: Target, cameras: StereoRig, detector: DetectorParams | None, pose: PoseSettings,
                 tracking: TrackingSettings, pool: ThreadPoolExecutor | None = None) -> None:
        self.target = target
        self.cameras = cameras
        self.detector = detector
        self.pose_settings = pose
        self.tracking = tracking
        self.tracker = BoardTracker(target, cameras, tracking)
        # The boards (names) found in the left and right image of the last frame with a valid pose.
        self._seen: tuple[set[str], set[str]] = (set(), set())
        # A full search does the right image in this thread while the caller's thread does the left one
        # (no thread is started before the first search).
        self._pool = pool or ThreadPoolExecutor(max_workers=1, thread_name_prefix="detect-right")

    def reconfigured(self, target: Target, cameras: StereoRig, detector: DetectorParams | None,
                     pose: PoseSettings, tracking: TrackingSettings) -> FramePipeline:
        """A pipeline with other settings that shares this one's worker thread (and starts without motion)."""
        return FramePipeline(target, cameras, detector, pose, tracking, self._pool)

    def close(self) -> None:
        """Stop the worker thread (waits for a search in progress)."""
        self._pool.shutdown(wait=True)

    def reset(self) -> None:
        """Forget the motion (a reopened camera): the next frame is searched."""
        self.tracker.reset()

    def warm_up(self) -> None:
        """Run the whole per-frame path once - a full search, the verification of predicted corners - on a
        drawn chessboard at the cameras' size, so that numba's cache loads, OpenCV's first calls and the
        first large buffers are not paid by the first camera frame."""
        w, h = self.cameras.image_size
        board = self.target.boards[0]
        image = warm_up_image((w or 640, h or 480), board.cols, board.rows)
        for det in detect(image, self.target, self.detector):
            moved = [CornerPrediction(self.target.board(det.board), det.ids, det.corners + 0.7)]
            track_boards(image, moved, self.detector)

    def process(self, frame: StereoFrame) -> FrameResult:
        """The pose of one stereo frame.

        With a recent pose the predicted corners are verified (tracking); when the tracked result is in
        doubt, both images are searched around the predicted corners, and without a recent pose, or when that
        gives no pose or fewer boards than verification confirmed, in full. A corrupt image (unreadable, wrong size or
        type) is reported in ``problems``; the other camera alone still gives a (mono) pose. An unexpected
        exception is caught (a daemon must not die of one frame): an invalid pose and ``error``.
        """
        size = self.cameras.image_size
        left, bad_left = grey_image(frame.left.image, size, "left")
        right, bad_right = grey_image(frame.right.image, size, "right")
        result = FrameResult(Pose.invalid("not processed"))
        try:
            pose = None
            if left is not None and right is not None:
                predicted = self.tracker.predict(frame.stamp_ns)
                if predicted is not None:
                    pose = self._tracked_pose(predicted, left, right, result)
            if pose is not None:
                result.tracked = True
            else:
                pose = self._searched_pose(left, right, bad_left, bad_right, result)
            result.pose = pose
            self.tracker.update(pose, frame.stamp_ns)
            self._seen = ({d.board for d in result.detections[0]}, {d.board for d in result.detections[1]}) \
                if pose.valid else (set(), set())
        except Exception as exc:  # noqa: BLE001 - a bug must not kill a daemon that runs for weeks
            result.pose = Pose.invalid(f"internal error: {type(exc).__name__}")
            result.error = exc
            result.tracked = False
            result.failed_images = 0
            self.tracker.reset()
            self._seen = (set(), set())
        return result

    def _track(self, image: np.ndarray, predicted: list[CornerPrediction]) -> TrackedBoards:
        """The predicted boards confirmed in one image (tracking; see edgecal.stream.tracker)."""
        return verify_boards(image, predicted, self.detector) if predicted else TrackedBoards([])

    def _tracked_pose(self, predicted: tuple[list[CornerPrediction], list[CornerPrediction]], left: np.ndarray,
                      right: np.ndarray, result: FrameResult) -> Pose | None:
        """The pose from verifying the tracker's predicted corners (left, right) in both images, or None when
        the result is in doubt (then the frame is searched)."""
        left_pred, right_pred = predicted
        # One thread for both images: verification is mostly Python, and two threads contend for the GIL
        # (each OpenCV call hands it over and waits to get it back). Measured again on e4c4de0 (bench/live.py's
        # hard sequence, load 3-5): per frame in the pipeline, two threads took ~2x the median wall time of
        # one at Python's default 5 ms switch interval and about the same at 0.5 ms; tracking alone, best of
        # 7 per frame, 1.03-1.04x the wall of one thread at 5, 0.5 and 0.1 ms, and 1.19x with the right image
        # in a worker process. The full search below, mostly in GIL-free kernels, does gain.
        left_tracked = self._track(left, left_pred)
        right_tracked = self._track(right, right_pred)
        left_det, right_det = left_tracked.detections, right_tracked.detections
        # A board the last frame found that verification lost is searched for (with all the search's checks)
        # around where it was predicted only: the boards move as one body with those confirmed, the rest of
        # the image cannot hold it, and it costs 10-20x less than the whole image. Not a board verification
        # found in place (TrackedBoards.in_place: its corners where predicted, too scattered to frame the
        # squares its colour check needs): the search would look at the same corners (on bench/live.py's
        # hard sequence it found none of 41 such boards, at 2-13 ms of CPU each).
        seen = self._seen
        lost = [[p for p in preds if p.board.name in names - {d.board for d in dets}]
                for preds, dets, names in ((left_pred, left_det, seen[0]), (right_pred, right_det, seen[1]))]
        search = [[p for p in lost_k if p.board.name not in tracked.in_place]
                  for lost_k, tracked in zip(lost, (left_tracked, right_tracked))]
        verified = [bool(left_det), bool(right_det)]
        if search[0] or search[1]:
            right_job = self._pool.submit(self._search_lost, right, search[1], right_det) if search[1] else None
            left_det = self._search_lost(left, search[0], left_det) if search[0] else left_det
            right_det = right_job.result() if right_job is not None else right_det
        result.detections = (left_det, right_det)
        # A camera that saw boards in the last frame and none now has lost the track: the full search decides.
        if (seen[0] and not left_det) or (seen[1] and not right_det):
            return None
        # The share is taken over the boards the last frame found, less those not found around where they
        # must be: a board not found (too steep for the checks, half occluded) is still looked for, but
        # searching the whole image for it finds it no more than searching where it is. "Where they must
        # be" only holds in an image where verification confirmed a board where it was predicted: in one
        # where it confirmed none (the robot jumped, the view is blocked) every board still counts.
        found = [{d.board for d in left_det}, {d.board for d in right_det}]
        still = [names - {p.board.name for p in lost_k} | (names & found_k) if held else names
                 for names, lost_k, found_k, held in zip(seen, lost, found, verified)]
        expected = [p for p in left_pred if p.board.name in still[0]] + \
            [p for p in right_pred if p.board.name in still[1]]
        confirmed = [d for d in left_det if d.board in still[0]] + [d for d in right_det if d.board in still[1]]
        if not expected:
            expected, confirmed = left_pred + right_pred, left_det + right_det
        if confirmed_fraction(expected, confirmed) < self.tracking.min_confirmed_fraction:
            return None
        pose = estimate_pose(left_det, right_det, self.target, self.cameras, self.pose_settings)
        # A misfit board or an invalid pose may be a tracking failure: the full search decides.
        return pose if pose.valid and not pose.rejected else None

    def _search_lost(self, image: np.ndarray, lost: list[CornerPrediction], tracked: list[Detection]
                     ) -> list[Detection]:
        """``tracked`` and the ``lost`` boards (not among them) that the search finds around their predicted
        corners (edgecal.detection.tracking.search_near)."""
        names = {p.board.name for p in lost}
        found = search_near(image, lost, self.target, self.detector) or []
        return tracked + [d for d in found if d.board in names]

    def _detect(self, image: np.ndarray | None) -> list[Detection]:
        """The boards searched in one grey image (none for an image that could not be used)."""
        return detect(image, self.target, self.detector) if image is not None else []

    def _searched_pose(self, left: np.ndarray | None, right: np.ndarray | None, bad_left: str | None,
                       bad_right: str | None, result: FrameResult) -> Pose:
        """The pose from searching both images in full (the right one in the worker thread)."""
        right_job = self._pool.submit(self._detect, right)
        left_det = self._detect(left)
        right_det = right_job.result()
        result.detections = (left_det, right_det)
        result.problems = [p for p in (bad_left, bad_right) if p]
        if len(result.problems) == 2:
            return Pose.invalid(f"corrupt frame: {'; '.join(result.problems)}")
        result.failed_images = int(not left_det and left is not None) + int(not right_det and right is not None)
        pose = estimate_pose(left_det, right_det, self.target, self.cameras, self.pose_settings)
        if result.problems and not pose.valid:
            pose.reason = f"{pose.reason}; corrupt frame: {result.problems[0]}"
        return pose
