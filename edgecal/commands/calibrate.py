"""``edgecal calibrate``: one-shot box calibration (mono or stereo) or planar multi-view calibration.

    edgecal calibrate --target configs/targets/box-100mm.yaml --left L.png --right R.png --out rig.yaml
    edgecal calibrate --board 9x6 --square-mm 30 --left left/ --right right/ --out rig.yaml
    edgecal calibrate --board 9x6 --square-mm 30 --left views/ --out rig.yaml   # an edgecal recording
    edgecal calibrate --board 9x6 --square-mm 30 --corners rig.corners.csv --out rig2.yaml  # no detection
    edgecal calibrate --target box.yaml --left L.png --out camera.yaml          # one camera

Views are named by their image files everywhere (messages, report, JSON). Beside rig.yaml go the
camera_info files and NAME.corners.csv, the corners found (views/ module), so ``--corners`` re-solves.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np

from edgecal.calibration.acceptance import acceptance_problems
from edgecal.calibration.assign import assign, assign_stereo, symmetry_warnings
from edgecal.calibration.io import camera_info_paths, write_calibration
from edgecal.calibration.lens_choice import choose_lens_model
from edgecal.calibration.mirror import mirrored_face_hint
from edgecal.calibration.mono import calibrate_box_mono
from edgecal.calibration.planar import calibrate_planar
from edgecal.calibration.report import format_summary, write_report
from edgecal.calibration.results import calibration_json
from edgecal.calibration.settings import DISTORTION_CHOICES, CalibrationSettings, load_calibration_settings
from edgecal.calibration.stereo import calibrate_box_stereo
from edgecal.calibration.types import Calibration, CornerSet
from edgecal.calibration.views import (
    View,
    camera_names,
    corner_set,
    corners_path,
    corners_text,
    name_views,
    read_corners,
)
from edgecal.commands.argtypes import pixel_count, positive_float
from edgecal.errors import CalibrationRejected, ConfigError, EdgecalError, InputError
from edgecal.fileio import check_outputs
from edgecal.images import DEFAULT_MAX_PIXELS, expand_image_args, load_grey
from edgecal.progress import Progress
from edgecal.targets import Target, load_target, parse_board_spec

log = logging.getLogger(__name__)


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register ``calibrate``."""
    p = subparsers.add_parser(
        "calibrate", help="calibrate one camera or a stereo pair (one shot of a box, or many views of a board)",
        description="One image per camera of a calibration box (--target) gives intrinsics, distortion and "
                    "the stereo pose; with --board CxR --square-mm S and several images per camera, planar "
                    "multi-view calibration. Results are refused, not written, when outside the bounds of "
                    "configs/calibration.yaml. Writes rig.yaml (with its provenance), the camera_info files "
                    "and NAME.corners.csv, the corners found, which --corners re-solves without detecting.")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--target", help="target YAML (configs/targets/*.yaml)")
    src.add_argument("--board", help="flat board of COLSxROWS inner corners, e.g. 9x6 (planar multi-view)")
    p.add_argument("--square-mm", type=positive_float, help="square size in mm (with --board)")
    views = p.add_mutually_exclusive_group(required=True)
    views.add_argument("--left", nargs="+", help="left (or only) camera image(s), a folder, or an edgecal "
                                                 "recording folder (edgecal collect/record)")
    views.add_argument("--corners", metavar="FILE", help="re-solve from a corners file (NAME.corners.csv "
                                                         "written by an earlier calibrate) without detecting")
    p.add_argument("--right", nargs="+", help="right camera image(s) or a folder (pairs matched by order)")
    p.add_argument("--out", required=True, help="rig.yaml to write (plus NAME.*.camera_info.yaml and "
                                                "NAME.corners.csv beside it)")
    p.add_argument("--report", metavar="DIR", help="write a report into DIR (index.html, figures, summary.txt)")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout (parameters, sigma, "
                                                       "RMS, bounds and verdict, every view); text goes to stderr")
    p.add_argument("--camera-name", nargs="+", metavar="NAME",
                   help="camera_name in the camera_info files, one per camera (the name your camera driver "
                        "uses; camera_info_manager warns when it does not match)")
    p.add_argument("--config", help="calibration settings (default: the packaged configs/calibration.yaml)")
    p.add_argument("--distortion", choices=DISTORTION_CHOICES, help="override the config's lens model: radtan terms "
                   "(none ... k1k2p1p2k3), rational, fisheye, or auto (the simplest the data supports)")
    p.add_argument("--force", action="store_true", help="replace existing output files")
    p.add_argument("--max-pixels", type=pixel_count, default=DEFAULT_MAX_PIXELS, metavar="N",
                   help="refuse images of more pixels, from the header before decoding "
                        f"(default {DEFAULT_MAX_PIXELS} = 2^26)")
    return p


def _recording_files(folder: Path) -> tuple[list[Path], list[Path] | None] | None:
    """The left (or only) and right image files of an edgecal recording, or None if ``folder`` is not one."""
    from edgecal.drivers.recording import MANIFEST, load_manifest
    if not (folder / MANIFEST).is_file():
        return None
    manifest = load_manifest(folder)
    if manifest["layout"] == "stereo":
        return ([folder / e["left"]["file"] for e in manifest["frames"]],
                [folder / e["right"]["file"] for e in manifest["frames"]])
    return [folder / e["file"] for e in manifest["frames"]], None


def input_views(left: list[str], right: list[str] | None) -> list[View]:
    """The views of ``--left``/``--right``: files, folders (natural order) or one recording folder."""
    rec = _recording_files(Path(left[0])) if len(left) == 1 and Path(left[0]).is_dir() else None
    if rec is not None and right is None:
        left_paths, right_paths = rec
        if not left_paths:
            raise InputError(f"{left[0]}: the recording holds no frames")
    else:
        left_paths = expand_image_args(left)
        right_paths = expand_image_args(right) if right else None
    if right_paths is not None and len(right_paths) != len(left_paths):
        raise InputError(f"{len(left_paths)} left and {len(right_paths)} right images: pairs are matched by "
                         f"order, give the same number of each")
    files = [(lp,) if right_paths is None else (lp, right_paths[i]) for i, lp in enumerate(left_paths)]
    return name_views(files)


def _detect(image: np.ndarray, target: Target, path: object = None) -> list:
    """The detections of one image; the detector's notes (a grid of another size than the target's) are
    logged, and a board seen more than once is left out: which copy is the target's would be a guess."""
    try:
        from edgecal import detect_debug  # imported late so calibrate's other paths work without the detector
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
            dets = [_detect(img, target, f) for img, f in zip(images, view.files)]
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


def provenance(target: Target, views: list[View], cal: Calibration, settings: CalibrationSettings,
               config: str | None, corners_file: Path) -> dict:
    """What produced a calibration, for rig.yaml and the JSON: target, views, version, time, settings."""
    from edgecal import __version__
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


def run(args: argparse.Namespace) -> int:
    """Calibrate, print the summary (or JSON), write the report and (if acceptable) the rig files."""
    settings = load_calibration_settings(args.config)
    if args.distortion:
        settings = replace(settings, refine=replace(settings.refine, distortion=args.distortion))
    if args.board:
        if args.square_mm is None:
            raise ConfigError("--board needs --square-mm S, the square size in millimetres (> 0)")
        target = parse_board_spec(args.board, args.square_mm)
    else:
        target = load_target(args.target)
        for w in symmetry_warnings(target):
            log.warning("%s", w)
    if args.corners and args.right:
        raise InputError("--right goes with --left; a corners file already holds both cameras")
    out = Path(args.out)
    if args.corners:
        loaded = read_corners(args.corners, target)
        views, corners, size = loaded.views, loaded.corners, loaded.image_size
    else:
        views = input_views(args.left, args.right)
    n_cams = len(views[0].files)
    if not target.is_planar and len(views) != 1:
        raise InputError(f"a box calibration takes one image per camera (got {len(views)} views); "
                         f"use --board for many views")
    if args.camera_name and len(args.camera_name) != n_cams:
        raise InputError(f"--camera-name needs one name per camera ({n_cams}), got {len(args.camera_name)}")
    corners_out = corners_path(out)
    outputs = [out, *camera_info_paths(out, n_cams == 2)]
    # A re-solve names the corners file it read in the provenance; only a detection writes one.
    write_corners = not args.corners
    if write_corners:
        outputs.append(corners_out)
    # Refuse to clobber, or to work for a folder that cannot be written, before any work is done.
    check_outputs(outputs, args.force)
    if args.report:
        check_outputs([Path(args.report) / "summary.txt"], args.force, create_folders=True)
    if not args.corners:
        corners, size = detect_views(views, target, args.max_pixels)
    cal = solve(target, views, corners, size, settings)
    problems = acceptance_problems(cal, settings.acceptance)
    if problems and not target.is_planar and not args.corners:
        # a box that fits badly: is one of its faces described mirrored? (detected again: one pair, cheap)
        hint = mirrored_face_hint(target, [_detect(load_grey(f, args.max_pixels), target) for f in views[0].files])
        if hint:
            problems.append(hint)
    text = sys.stderr if args.json else sys.stdout
    print(format_summary(cal), file=text)
    prov = provenance(target, views, cal, settings, args.config,
                      corners_out if write_corners else Path(args.corners))
    if args.report:
        for p in write_report(cal, views, args.report, args.force, problems=problems,
                              bounds=settings.acceptance, provenance=prov, max_pixels=args.max_pixels):
            log.info("wrote %s", p)
    if args.json:
        print(json.dumps(calibration_json(cal, views, problems, settings.acceptance, prov)), flush=True)
    if problems:
        raise CalibrationRejected(f"calibration refused, {out} not written (bounds in "
                                  f"{args.config or 'configs/calibration.yaml'}): " + "; ".join(problems))
    also = {corners_out: corners_text(views, corners, size, target).encode("utf-8")} if write_corners else {}
    for p in write_calibration(cal, out, args.force, provenance=prov, camera_names=args.camera_name, also=also):
        print(f"wrote {p}", file=text)
    return 0
