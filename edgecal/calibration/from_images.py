"""Calibration from images: detect the target in every view, assign its corners, solve, judge the result.

The work behind ``edgecal calibrate`` and ``edgecal demo`` as plain functions (the commands only read
arguments, print and write files). Views are named by their image files (calibration.views); a box
takes one view, a planar board many.
"""

from __future__ import annotations

import logging
import time
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np

from edgecal.calibration.acceptance import acceptance_problems
from edgecal.calibration.assign import assign, assign_stereo
from edgecal.calibration.lens_choice import choose_lens_model
from edgecal.calibration.mirror import mirrored_face_hint
from edgecal.calibration.mono import calibrate_box_mono
from edgecal.calibration.planar import calibrate_planar
from edgecal.calibration.settings import CalibrationSettings
from edgecal.calibration.stereo import calibrate_box_stereo
from edgecal.calibration.types import Calibration, CornerSet
from edgecal.calibration.views import View, camera_names, corner_set
from edgecal.detection.types import Detection
from edgecal.errors import ConfigError, EdgecalError, InputError
from edgecal.images import DEFAULT_MAX_PIXELS, load_grey
from edgecal.progress import Progress
from edgecal.targets import Target
from edgecal.version import __version__

log = logging.getLogger(__name__)


def detect_target(image: np.ndarray, target: Target, path: object = None) -> list[Detection]:
    """The detections of one image; the detector's notes (a grid of another size than the target's) are
    logged, and a board seen more than once is left out: which copy is the target's would be a guess."""
    try:
        # imported late so a re-solve from a corners file works without the detector
        from edgecal.detection.detector import detect_debug
    except ImportError as exc:
        raise EdgecalError(f"the chessboard detector is not available in this install ({exc})") from None
    debug = detect_debug(image, target)
    where = f"{path}: " if path is not None else ""
    for note in debug.notes:
        log.warning("%s%s", where, note)
    copied = {d.board for d in debug.detections if d.copy > 0}
    for name in sorted(copied):
        n = sum(d.board == name for d in debug.detections)
        log.warning("%s%d boards of %s's size in the image: not used for it (which one is the target's is "
                    "ambiguous)", where, n, name)
    return [d for d in debug.detections if d.board not in copied]


def _planar_corners(dets: list, target: Target) -> CornerSet:
    a = assign(dets, target)
    if a is None:
        return corner_set(target, [], np.zeros((0, 2)))
    return corner_set(target, list(a.corners.keys), a.corners.image_px, a.corners.image_cov_px2)


def detect_views(views: list[View], target: Target, max_pixels: int = DEFAULT_MAX_PIXELS
                 ) -> tuple[list[list[CornerSet]], tuple[int, int]]:
    """Detect and assign the target in every view: corners ``[camera][view]`` and the image size.

    A box view's corners come from the joint assignment of both images (assign_stereo). Images of
    different sizes are an InputError naming both files. Shows progress when stderr is a terminal.
    """
    n_cams = len(views[0].files)
    corners: list[list[CornerSet]] = [[] for _ in range(n_cams)]
    size: tuple[int, int] | None = None
    first = ""
    with Progress("detecting", len(views)) as bar:
        for i, view in enumerate(views):
            bar.update(i, view.name)
            images = [load_grey(f, max_pixels) for f in view.files]
            for img, f in zip(images, view.files):
                h, w = img.shape[:2]
                if size is None:
                    size, first = (w, h), f
                elif (w, h) != size:
                    raise InputError(f"{f}: the image is {w}x{h} but {first} is {size[0]}x{size[1]}; "
                                     f"all images must come from cameras of one size")
            dets = [detect_target(img, target, f) for img, f in zip(images, view.files)]
            if target.is_planar:
                found = [_planar_corners(d, target) for d in dets]
            elif n_cams == 1:
                a = assign(dets[0], target)
                found = [a.corners if a is not None else corner_set(target, [], np.zeros((0, 2)))]
            else:
                pair = assign_stereo(dets[0], dets[1], target)
                found = [a.corners if a is not None else corner_set(target, [], np.zeros((0, 2))) for a in pair]
            for c in range(n_cams):
                corners[c].append(found[c])
    assert size is not None
    return corners, size


def solve(target: Target, views: list[View], corners: list[list[CornerSet]], size: tuple[int, int],
          settings: CalibrationSettings) -> Calibration:
    """Calibrate from the corners of every view; errors name the image that is missing a board.

    ``distortion: auto`` fits each candidate lens model and keeps the simplest the data supports.
    """
    if settings.refine.distortion == "auto":
        return choose_lens_model(lambda o: solve(target, views, corners, size, replace(settings, refine=o)),
                                 settings.refine, settings.acceptance)
    names = camera_names(len(corners))
    if target.is_planar:
        if len(target.boards) != 1:
            raise ConfigError(f"{target.source}: planar calibration needs a target of exactly one board")
        right = corners[1] if len(corners) == 2 else None
        with Progress("solving", None) as bar:
            bar.update(0, f"{len(views)} views", force=True)
            return calibrate_planar(corners[0], right, size, settings.refine, settings.planar,
                                    view_names=[v.name for v in views])
    if len(views) != 1:
        raise InputError(f"a box calibration takes one image per camera (got {len(views)} views); "
                         f"use --board for many views")
    for c, name in enumerate(names):
        if not len(corners[c][0]):
            side = "" if len(names) == 1 else f" in the {name} image"
            raise InputError(f"{views[0].files[c]}: no board of target {target.name!r} found{side}")
    if len(names) == 1:
        return calibrate_box_mono(corners[0][0], size, settings.refine)
    return calibrate_box_stereo(corners[0][0], corners[1][0], size, settings.refine)


def calibrate_images(target: Target, views: list[View], settings: CalibrationSettings,
                     max_pixels: int = DEFAULT_MAX_PIXELS
                     ) -> tuple[Calibration, list[list[CornerSet]], tuple[int, int]]:
    """Detect the target in every view and calibrate: (calibration, corners ``[camera][view]``, image size)."""
    corners, size = detect_views(views, target, max_pixels)
    return solve(target, views, corners, size, settings), corners, size


def calibration_problems(cal: Calibration, target: Target, views: list[View], settings: CalibrationSettings,
                         max_pixels: int = DEFAULT_MAX_PIXELS, detected: bool = True) -> list[str]:
    """Why ``cal`` is not acceptable (empty: it is), by the bounds of ``settings.acceptance``.

    A box that fits badly from ``detected`` images is checked for a face described mirrored (its one
    pair detected again: cheap).
    """
    problems = acceptance_problems(cal, settings.acceptance)
    if problems and not target.is_planar and detected:
        hint = mirrored_face_hint(target, [detect_target(load_grey(f, max_pixels), target) for f in views[0].files])
        if hint:
            problems.append(hint)
    return problems


def provenance(target: Target, views: list[View], cal: Calibration, settings: CalibrationSettings,
               config: str | None, corners_file: Path) -> dict:
    """What produced a calibration, for rig.yaml and the JSON: target, views, version, time, settings."""
    squares = sorted({b.square_mm for b in target.boards})
    used = set(cal.view_index) if cal.view_index else set(range(len(views)))
    prov: dict = {
        "edgecal_version": __version__,
        "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "target": target.name,
        "target_source": target.source,
        "boards": [{"name": b.name, "inner_corners": [b.cols, b.rows], "square_mm": b.square_mm}
                   for b in target.boards],
    }
    if len(squares) == 1:
        prov["square_mm"] = squares[0]
    prov["cameras"] = list(cal.camera_names)
    prov["views"] = [{"view": v.name, "files": list(v.files), "used": i in used} for i, v in enumerate(views)]
    prov["corners_file"] = str(corners_file)
    prov["settings"] = {"config": config or "configs/calibration.yaml (packaged)",
                        "refine": asdict(settings.refine), "acceptance": asdict(settings.acceptance),
                        "planar": asdict(settings.planar)}
    return prov
