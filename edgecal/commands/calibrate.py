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
from dataclasses import replace
from pathlib import Path

from edgecal.calibration.assign import symmetry_warnings
from edgecal.calibration.from_images import calibrate_images, calibration_problems, provenance, solve
from edgecal.calibration.io import camera_info_paths, write_calibration
from edgecal.calibration.report import format_summary, write_report
from edgecal.calibration.results import calibration_json
from edgecal.calibration.settings import DISTORTION_CHOICES, load_calibration_settings
from edgecal.calibration.views import View, corners_path, corners_text, name_views, read_corners
from edgecal.commands.argtypes import pixel_count, positive_float
from edgecal.errors import CalibrationRejected, ConfigError, InputError
from edgecal.fileio import check_outputs
from edgecal.images import DEFAULT_MAX_PIXELS, expand_image_args
from edgecal.targets import load_target, parse_board_spec

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
    if args.corners:
        cal = solve(target, views, corners, size, settings)
    else:
        cal, corners, size = calibrate_images(target, views, settings, args.max_pixels)
    problems = calibration_problems(cal, target, views, settings, args.max_pixels, detected=not args.corners)
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
