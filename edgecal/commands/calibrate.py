"""``edgecal calibrate``: one-shot box calibration (mono or stereo) or planar multi-view calibration.

    edgecal calibrate --target configs/targets/box-100mm.yaml --left L.png --right R.png --out rig.yaml
    edgecal calibrate --board 9x6 --square-mm 30 --left left/ --right right/ --out rig.yaml
    edgecal calibrate --target box.yaml --left L.png --out camera.yaml          # one camera
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import numpy as np

from edgecal.calibration.acceptance import acceptance_problems
from edgecal.calibration.assign import assign, assign_stereo, symmetry_warnings
from edgecal.calibration.io import camera_info_paths, write_calibration
from edgecal.calibration.mono import calibrate_box_mono
from edgecal.calibration.planar import calibrate_planar
from edgecal.calibration.refine import DISTORTION_MODELS
from edgecal.calibration.report import format_summary, write_report
from edgecal.calibration.settings import load_calibration_settings
from edgecal.calibration.stereo import calibrate_box_stereo
from edgecal.calibration.types import Calibration, CornerSet
from edgecal.errors import CalibrationRejected, ConfigError, EdgecalError, InputError
from edgecal.fileio import check_outputs
from edgecal.images import expand_image_args, load_grey
from edgecal.targets import Target, load_target, parse_board_spec

log = logging.getLogger(__name__)


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register ``calibrate``."""
    p = subparsers.add_parser(
        "calibrate", help="calibrate one camera or a stereo pair (one shot of a box, or many views of a board)",
        description="One image per camera of a calibration box (--target) gives intrinsics, distortion and "
                    "the stereo pose; with --board CxR --square-mm S and several images per camera, planar "
                    "multi-view calibration. Results are refused, not written, when outside the bounds of "
                    "configs/calibration.yaml.")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--target", help="target YAML (configs/targets/*.yaml)")
    src.add_argument("--board", help="flat board of COLSxROWS inner corners, e.g. 9x6 (planar multi-view)")
    p.add_argument("--square-mm", type=float, help="square size in mm (with --board)")
    p.add_argument("--left", nargs="+", required=True, help="left (or only) camera image(s) or a folder")
    p.add_argument("--right", nargs="+", help="right camera image(s) or a folder (pairs matched by order)")
    p.add_argument("--out", required=True, help="rig.yaml to write (plus NAME.*.camera_info.yaml beside it)")
    p.add_argument("--report", help="folder for overlays, residual histogram, per-board error, summary.txt")
    p.add_argument("--config", help="calibration settings (default: the packaged configs/calibration.yaml)")
    p.add_argument("--distortion", choices=tuple(DISTORTION_MODELS), help="override the config's distortion model")
    p.add_argument("--force", action="store_true", help="replace existing output files")
    return p


def _load_images(paths: list[Path]) -> list[np.ndarray]:
    return [load_grey(p) for p in paths]


def _check_sizes(images: list[np.ndarray], paths: list[Path]) -> tuple[int, int]:
    h, w = images[0].shape[:2]
    for img, p in zip(images, paths):
        if img.shape[:2] != (h, w):
            raise InputError(f"{p}: the image is {img.shape[1]}x{img.shape[0]} but {paths[0]} is {w}x{h}; "
                             f"all images must come from cameras of one size")
    return w, h


def _detect(image: np.ndarray, target: Target) -> list:
    try:
        from edgecal import detect  # the lead's detector; imported late so calibrate's other paths work without it
    except ImportError as exc:
        raise EdgecalError(f"the chessboard detector is not available in this install ({exc})") from None
    return detect(image, target)


def _planar_corners(dets: list, target: Target) -> CornerSet:
    a = assign(dets, target)
    if a is None:
        return CornerSet(np.zeros((0, 3)), np.zeros((0, 2)), ())
    board = target.boards[0]
    ids = np.array([k[1:] for k in a.corners.keys], dtype=np.int64).reshape(-1, 2)
    return CornerSet(board.board_points_mm(ids), a.corners.image_px, a.corners.keys)


def calibrate_images(target: Target, left: list[np.ndarray], right: list[np.ndarray] | None,
                     left_paths: list[Path], right_paths: list[Path] | None, settings) -> Calibration:
    """Detect, assign and calibrate; errors name the image that is missing a board."""
    size = _check_sizes(left + (right or []), left_paths + (right_paths or []))
    if target.is_planar:
        if len(target.boards) != 1:
            raise ConfigError(f"{target.source}: planar calibration needs a target of exactly one board")
        views_l = [_planar_corners(_detect(img, target), target) for img in left]
        views_r = [_planar_corners(_detect(img, target), target) for img in right] if right is not None else None
        return calibrate_planar(views_l, views_r, size, settings.refine, settings.planar)
    if len(left) != 1 or (right is not None and len(right) != 1):
        raise InputError(f"a box calibration takes one image per camera (got {len(left)} left"
                         + (f", {len(right)} right" if right is not None else "") + "); use --board for many views")
    dets_l = _detect(left[0], target)
    if right is None:
        a = assign(dets_l, target)
        if a is None:
            raise InputError(f"{left_paths[0]}: no board of target {target.name!r} found in the image")
        log.info("left: %s (DLT residual %.3f px)", a.describe(), a.rms_px)
        return calibrate_box_mono(a.corners, size, settings.refine)
    dets_r = _detect(right[0], target)
    a_l, a_r = assign_stereo(dets_l, dets_r, target)
    for a, p, side in ((a_l, left_paths[0], "left"), (a_r, right_paths[0], "right")):
        if a is None:
            raise InputError(f"{p}: no board of target {target.name!r} found in the {side} image")
        log.info("%s: %s (DLT residual %.3f px)", side, a.describe(), a.rms_px)
    return calibrate_box_stereo(a_l.corners, a_r.corners, size, settings.refine)


def run(args: argparse.Namespace) -> int:
    """Calibrate, print the summary, write the report and (if acceptable) the rig file."""
    settings = load_calibration_settings(args.config)
    if args.distortion:
        from dataclasses import replace
        settings = replace(settings, refine=replace(settings.refine, distortion=args.distortion))
    if args.board:
        if args.square_mm is None or args.square_mm <= 0:
            raise ConfigError("--board needs --square-mm S, the square size in millimetres (> 0)")
        target = parse_board_spec(args.board, args.square_mm)
    else:
        target = load_target(args.target)
        for w in symmetry_warnings(target):
            log.warning("%s", w)
    left_paths = expand_image_args(args.left)
    right_paths = expand_image_args(args.right) if args.right else None
    out = Path(args.out)
    # Refuse to clobber, or to work for a folder that cannot be written, before any work is done.
    check_outputs([out, *camera_info_paths(out, right_paths is not None)], args.force)
    if args.report:
        check_outputs([Path(args.report) / "summary.txt"], args.force, create_folders=True)
    left = _load_images(left_paths)
    right = _load_images(right_paths) if right_paths else None
    cal = calibrate_images(target, left, right, left_paths, right_paths, settings)
    print(format_summary(cal))
    if args.report:
        images = [left] + ([right] if right is not None else [])
        if target.is_planar:  # planar views may have been skipped: map the kept corners back to their images
            images = _planar_report_images(cal, images)
        for p in write_report(cal, images, args.report, args.force):
            log.info("wrote %s", p)
    problems = acceptance_problems(cal, settings.acceptance)
    if problems:
        raise CalibrationRejected(f"calibration refused, {out} not written (bounds in "
                                  f"{args.config or 'configs/calibration.yaml'}): " + "; ".join(problems))
    for p in write_calibration(cal, out, args.force):
        print(f"wrote {p}")
    return 0


def _planar_report_images(cal: Calibration, images: list[list[np.ndarray]]) -> list[list[np.ndarray]]:
    """The images of the views that were kept, in the calibration's view order."""
    return [[imgs[i] for i in cal.view_index] for imgs in images]
