"""Planar multi-view calibration (mono and stereo) from many images of one flat board.

OpenCV starts the pinhole lenses (calibrateCamera per camera; radtan and rational); the fisheye
lens starts from a per-view pose on points undistorted with a guessed equidistant focal length (the
guess that fits best), because cv2.fisheye.calibrate fails on boards near the image rim (its
InitExtrinsics assertion) or diverges. edgecal checks that the views cover the image, rejects views that
fit much worse than the others, and computes the optimum and every parameter's standard deviation with
its own refinement (refine.py).
"""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np

from edgecal.calibration.checks import DegenerateInput
from edgecal.calibration.mono import relative_pose
from edgecal.calibration.refine import (
    Observation,
    RefineOptions,
    calibration_from_result,
    lens_of,
    observations_for,
    refine,
)
from edgecal.calibration.settings import PlanarSettings
from edgecal.calibration.stereo import finish_stereo
from edgecal.calibration.types import Calibration, CornerSet, RigidTransform
from edgecal.camera import CameraModel, project, undistort_points

MIN_CORNERS_PER_VIEW = 6


def coverage(corners: list[CornerSet], image_size: tuple[int, int], cells: tuple[int, int] = (8, 6)) -> float:
    """Share of an ``cells`` grid over the image that holds at least one corner of some view."""
    hit = np.zeros((cells[1], cells[0]), dtype=bool)
    for cs in corners:
        if len(cs):
            ix = np.clip((cs.image_px[:, 0] / image_size[0] * cells[0]).astype(int), 0, cells[0] - 1)
            iy = np.clip((cs.image_px[:, 1] / image_size[1] * cells[1]).astype(int), 0, cells[1] - 1)
            hit[iy, ix] = True
    return float(hit.mean())


def opencv_flags(distortion: str) -> int:
    """calibrateCamera flags that free exactly the distortion terms of ``distortion`` (a radtan or rational model)."""
    lens, free = lens_of(distortion)
    if lens == "rational":
        return cv2.CALIB_RATIONAL_MODEL
    flags = 0
    if "k1" not in free:
        flags |= cv2.CALIB_FIX_K1
    if "k2" not in free:
        flags |= cv2.CALIB_FIX_K2
    if "p1" not in free:
        flags |= cv2.CALIB_ZERO_TANGENT_DIST
    if "k3" not in free:
        flags |= cv2.CALIB_FIX_K3
    return flags


def _board_points(cs: CornerSet) -> np.ndarray:
    """Board-plane points for OpenCV: the target points of a flat board with z = 0."""
    obj = cs.object_mm.astype(np.float32).copy()
    if np.abs(obj[:, 2]).max() > 1e-9:
        raise DegenerateInput("planar calibration needs a flat board (all z = 0 in the board frame)")
    return obj


def _per_view_rms(views: list[CornerSet], cam: CameraModel, poses: list[RigidTransform]) -> np.ndarray:
    out = []
    for v, p in zip(views, poses):
        r = project(p.apply(v.object_mm), cam) - v.image_px
        out.append(float(np.sqrt(np.nanmean(np.sum(r ** 2, axis=1)))) if np.isfinite(r).any() else np.inf)
    return np.array(out)


def _calibrate_opencv(views: list[CornerSet], image_size: tuple[int, int], distortion: str
                      ) -> tuple[CameraModel, list[RigidTransform], np.ndarray]:
    obj = [_board_points(v) for v in views]
    img = [v.image_px.astype(np.float32).reshape(-1, 1, 2) for v in views]
    _, k, d, rvecs, tvecs = cv2.calibrateCamera(obj, img, tuple(image_size), None, None, flags=opencv_flags(distortion))
    cam = CameraModel.from_opencv(k, np.ravel(d)[:8], image_size, lens_of(distortion)[0])
    poses = [RigidTransform(np.ravel(r), np.ravel(t)) for r, t in zip(rvecs, tvecs)]
    return cam, poses, _per_view_rms(views, cam, poses)


# Equidistant focal lengths tried for a fisheye start: the image half-width spans 25..125 degrees.
_FISHEYE_HALF_FOV_DEG = np.linspace(25.0, 125.0, 21)


def _view_pose(view: CornerSet, cam: CameraModel) -> RigidTransform | None:
    """The board pose in a camera from one view, by PnP on the corners undistorted with ``cam``."""
    xn = undistort_points(view.image_px, cam)
    ok = np.all(np.isfinite(xn), axis=1)
    if ok.sum() < 4:
        return None
    found, r, t = cv2.solvePnP(view.object_mm[ok], xn[ok], np.eye(3), None, flags=cv2.SOLVEPNP_IPPE)
    return RigidTransform(np.ravel(r), np.ravel(t)) if found else None


def _calibrate_fisheye(views: list[CornerSet], image_size: tuple[int, int], distortion: str
                       ) -> tuple[CameraModel, list[RigidTransform], np.ndarray]:
    """A fisheye camera and view poses from a robust start: the best equidistant focal guess, then refine."""
    w, h = image_size
    best: tuple[float, CameraModel, list[RigidTransform]] | None = None
    for half_fov in _FISHEYE_HALF_FOV_DEG:
        f = 0.5 * w / np.radians(half_fov)
        cam = CameraModel(f, f, (w - 1) / 2.0, (h - 1) / 2.0, "fisheye", np.zeros(4), image_size)
        found = [_view_pose(v, cam) for v in views]
        poses = [p for p in found if p is not None]
        if len(poses) < len(found):   # PnP failed on a view
            continue
        score = float(np.median(_per_view_rms(views, cam, poses)))
        if best is None or score < best[0]:
            best = (score, cam, poses)
    if best is None:
        raise DegenerateInput("no fisheye start fits the views (too few corners per view?)")
    _, cam, start = best
    obs = [Observation(0, i, v.object_mm, v.image_px) for i, v in enumerate(views)]
    res = refine(obs, [cam], start, options=replace(RefineOptions(distortion=distortion), max_rounds=1))
    return res.cameras[0], res.view_poses, _per_view_rms(views, res.cameras[0], res.view_poses)


def _calibrate_start(views: list[CornerSet], image_size: tuple[int, int], distortion: str
                     ) -> tuple[CameraModel, list[RigidTransform], np.ndarray]:
    """A camera, view poses and per-view RMS to start the refinement from."""
    if lens_of(distortion)[0] == "fisheye":
        return _calibrate_fisheye(views, image_size, distortion)
    return _calibrate_opencv(views, image_size, distortion)


def _usable(views: list[CornerSet]) -> list[int]:
    return [i for i, v in enumerate(views) if len(v) >= MIN_CORNERS_PER_VIEW]


def calibrate_planar(views_left: list[CornerSet], views_right: list[CornerSet] | None,
                     image_size: tuple[int, int], options: RefineOptions = RefineOptions(),
                     planar: PlanarSettings = PlanarSettings(), view_names: list[str] | None = None) -> Calibration:
    """Mono (``views_right`` None) or stereo calibration from views of one flat board.

    Stereo views are pairs matched by order; a pair is used when the board is found in both images.
    ``view_names`` (one per input view, e.g. its file name) name the views in notes and corner labels.
    Raises DegenerateInput naming what is missing (too few views).
    """
    stereo = views_right is not None
    notes: list[str] = []
    skipped: dict[int, str] = {}
    names = list(view_names) if view_names is not None else [f"view {i}" for i in range(len(views_left))]
    if views_right is not None:   # stereo
        if len(views_left) != len(views_right):
            raise DegenerateInput(f"{len(views_left)} left and {len(views_right)} right images: pairs are "
                                  f"matched by order, give the same number of each")
        keep = []
        for i, (a, b) in enumerate(zip(views_left, views_right)):
            common = set(a.keys) & set(b.keys)
            if len(common) >= MIN_CORNERS_PER_VIEW:
                keep.append(i)
            else:
                side = ("either image" if len(a) < MIN_CORNERS_PER_VIEW and len(b) < MIN_CORNERS_PER_VIEW
                        else "the left image" if len(a) < MIN_CORNERS_PER_VIEW
                        else "the right image" if len(b) < MIN_CORNERS_PER_VIEW else "both images at once")
                skipped[i] = f"board not found in {side}"
        # stereoCalibrate needs the same corners in both images of a pair
        pairs = []
        for i in keep:
            a, b = views_left[i], views_right[i]
            shared = [k for k in a.keys if k in set(b.keys)]
            ia = [a.keys.index(k) for k in shared]
            ib = [b.keys.index(k) for k in shared]
            pairs.append((a.take(ia), b.take(ib)))
        cams_views = [[p[0] for p in pairs], [p[1] for p in pairs]]
        index = keep
    else:
        index = _usable(views_left)
        for i in sorted(set(range(len(views_left))) - set(index)):
            skipped[i] = "board not found"
        cams_views = [[views_left[i] for i in index]]
    what = "stereo pairs" if stereo else "views"
    if len(index) < planar.min_views:
        raise DegenerateInput(f"the board was found in only {len(index)} {what}; planar calibration needs at least "
                              f"{planar.min_views} (tilt the board differently in each)")
    # Reject views that fit far worse than the rest (a blurred or misdetected image), then solve again.
    for _ in range(2):
        per_cam = [_calibrate_start(v, image_size, options.distortion) for v in cams_views]
        worst = np.max([pc[2] for pc in per_cam], axis=0)
        limit = planar.max_view_rms_factor * max(float(np.median(worst)), 0.05)
        bad = np.flatnonzero(worst > limit)
        if not len(bad) or len(index) - len(bad) < planar.min_views:
            break
        for k in bad:
            skipped[index[k]] = f"fits far worse than the others: RMS {worst[k]:.2f} px > {limit:.2f} px"
        good = [i for i in range(len(index)) if i not in set(bad)]
        cams_views = [[v[i] for i in good] for v in cams_views]
        index = [index[i] for i in good]
    if len(per_cam[0][1]) != len(index):
        # the last rejection round removed views: solve once more on the views that are kept
        per_cam = [_calibrate_start(v, image_size, options.distortion) for v in cams_views]
    for c, v in enumerate(cams_views):
        cov = coverage(v, image_size)
        notes.append(f"{'left' if c == 0 else 'right' if stereo else 'camera'} coverage {100 * cov:.0f} % of the image")
        if cov < planar.min_coverage:
            notes.append(f"WARNING: the corners cover only {100 * cov:.0f} % of the image (< "
                         f"{100 * planar.min_coverage:.0f} %): distortion at the edges is extrapolated; "
                         f"add views with the board near the corners")
    cameras = [pc[0] for pc in per_cam]
    view_poses = per_cam[0][1]
    rigs: list[RigidTransform] = []
    if stereo:
        # The rig pose from each view's two board poses; the median is robust to a poorly posed view. (Not
        # cv2.stereoCalibrate: its dense Jacobian grows with the cube of the views - 300 pairs take minutes -
        # and the joint refinement below finds the optimum from this start.)
        rel = [relative_pose(a, b) for a, b in zip(per_cam[0][1], per_cam[1][1])]
        rigs = [RigidTransform(np.median([np.ravel(r.rvec) for r in rel], axis=0),
                               np.median([np.ravel(r.tvec) for r in rel], axis=0))]
    corners = cams_views
    res = refine(observations_for(corners, [names[i] for i in index]), cameras, view_poses, rigs, options)
    cal = calibration_from_result("planar-stereo" if stereo else "planar-mono", image_size, corners, res)
    cal.view_index = list(index)
    cal.skipped_views = dict(sorted(skipped.items()))
    cal.notes = ([f"{names[i]}: skipped, {why}" for i, why in cal.skipped_views.items()] + notes + cal.notes
                 + [f"{len(index)} of {len(names)} {what} used"])
    return finish_stereo(cal) if stereo else cal
