#!/usr/bin/env python3
"""Calibration benchmark: edgecal's one-shot box calibration against OpenCV on the same corners, single thread.

    .venv/bin/python bench/calibrate.py [--pairs 8] [--draws 2] [--noise 0,0.1,0.3] [--distortion k1k2p1p2]
                                        [--json out/bench_calibrate.json] [--force]

Box stereo pairs are rendered by edgecal.synth (100 mm box, 250-350 mm away, 1280x800, known truth),
edgecal.detect finds the corners and calibration.assign labels them. Two corner sources are scored:
"exact" = the true projections of the detected corners plus Gaussian noise (the calibration alone), and
"detected" = the detector's corners plus the same extra noise (detector error included). On each:

- edgecal: Tsai and DLT starts, robust refinement, joint stereo refinement (calibration.stereo);
- OpenCV: calibrateCamera with CALIB_USE_INTRINSIC_GUESS from a DLT start (OpenCV cannot start from a
  non-planar target alone), per camera, then stereoCalibrateExtended with CALIB_USE_INTRINSIC_GUESS;

and printed as medians over pairs x draws: focal error (%), principal point error (px), k1 error,
rotation error (deg), baseline error (mm), reprojection RMS (px), 3-D reconstruction error (mm, mean
over corners, as the paper's Table 2), CPU time (ms; process time, single thread, so a loaded machine
does not inflate it) and the ratio OpenCV / edgecal. For edgecal also the
z-scores |error| / reported std of fx and of T (honest std: median z ~ 0.67), and Tsai vs DLT starts.

Lens models (--lens-views, --lens-draws): planar stereo calibrations of simulated views (exact
projections + 0.1 px) through a radtan, a rational and a 160 deg fisheye rig, scored against the truth
(focal %, principal point px, largest distortion parameter error, baseline mm, |error|/σ).
Planar renders (--planar-sets 6): mono calibrations of rendered hand-held sessions (edgecal.synth.handheld,
640x480, 9x6 board, one frame per pose, the detector's corners) with the corners weighted by the detector's
covariances and without, scored against the truth (|error|/σ over fx fy cx cy k1 k2).
Scale (--scale 300): one planar stereo calibration of that many view pairs in a fresh process: seconds
and peak RSS.

Real sets (skipped when ../shared/data is absent): opencv_stereo_9x6 (planar multi-view, edgecal's
detector and planar path vs OpenCV's findChessboardCorners + stereoCalibrate, against Bouguet's
published result), ortho3_box_stereo (one-shot, against the authors' K and T) and
ocamcalib_urban_fisheye1 (edgecal's fisheye/rational models vs OpenCV's calibrateCamera default and
rational and cv2.fisheye.calibrate on edgecal's corners). --only box|lenses|scale|real picks sections.
"""

from __future__ import annotations

import os

for _var in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

cv2.setNumThreads(1)

import edgecal  # noqa: E402
from edgecal.calibration.assign import assign_stereo  # noqa: E402
from edgecal.calibration.dlt import calibrate_dlt  # noqa: E402
from edgecal.calibration.mono import linear_start  # noqa: E402
from edgecal.calibration.planar import calibrate_planar, opencv_flags  # noqa: E402
from edgecal.calibration.refine import RefineOptions  # noqa: E402
from edgecal.calibration.stereo import calibrate_box_stereo, triangulate  # noqa: E402
from edgecal.calibration.types import CornerSet, RigidTransform  # noqa: E402
from edgecal.camera import CameraModel  # noqa: E402
from edgecal.images import load_grey  # noqa: E402
from edgecal.runtime import tune_allocator  # noqa: E402
from edgecal.synth.scenes import box_stereo, box_target  # noqa: E402
from edgecal.targets import load_target, planar_target  # noqa: E402

REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"
METRICS = ("focal_pct", "pp_px", "k1_abs", "rot_deg", "baseline_mm", "rms_px", "recon_mm", "ms")


def _common(left: CornerSet, right: CornerSet) -> tuple[CornerSet, CornerSet]:
    keys = [k for k in left.keys if k in set(right.keys)]
    il = [left.keys.index(k) for k in keys]
    ir = [right.keys.index(k) for k in keys]
    return (CornerSet(left.object_mm[il], left.image_px[il], tuple(keys)),
            CornerSet(right.object_mm[ir], right.image_px[ir], tuple(keys)))


def _truth(pair: dict) -> dict:
    out = {}
    for side in ("left", "right"):
        c = pair[side]
        out[side] = CameraModel.from_opencv(np.array(c["K"]), np.array(c["dist"], dtype=float), tuple(c["image_size"]),
                                            c.get("lens", "radtan"))
        out[side + "_pose"] = RigidTransform.from_rt(np.array(c["R_cam_world"]), np.array(c["t_cam_world_mm"]))
    out["R"] = np.array(pair["R_right_left"])
    out["T"] = np.array(pair["T_right_left_mm"])
    return out


def _exact(cs: CornerSet, cam: CameraModel, pose: RigidTransform) -> CornerSet:
    px, _ = cv2.projectPoints(cs.object_mm, pose.rvec, pose.tvec, cam.camera_matrix, cam.dist_coeffs)
    return CornerSet(cs.object_mm, px.reshape(-1, 2), cs.keys)


def _noisy(cs: CornerSet, sigma: float, rng: np.random.Generator) -> CornerSet:
    """``cs`` plus Gaussian noise of ``sigma`` px; the detector's covariances (if any) grow by it."""
    cov = None if cs.image_cov_px2 is None else cs.image_cov_px2 + sigma ** 2 * np.eye(2)
    return CornerSet(cs.object_mm, cs.image_px + rng.normal(0.0, sigma, cs.image_px.shape), cs.keys, cov)


def _plain(cs: CornerSet) -> CornerSet:
    """``cs`` without its covariances: the solve weighs every corner alike."""
    return CornerSet(cs.object_mm, cs.image_px, cs.keys)


def _angle_deg(r: np.ndarray) -> float:
    """Rotation angle of ``r`` (made orthonormal first: published matrices are rounded), accurate near 0."""
    u, _, vt = np.linalg.svd(r)
    return float(np.degrees(np.linalg.norm(cv2.Rodrigues(u @ vt)[0])))


def _score(cams: list[CameraModel], r: np.ndarray, t: np.ndarray, box_pose: RigidTransform, rms: float, truth: dict,
           left: CornerSet, right: CornerSet, ms: float) -> dict:
    tc = [truth["left"], truth["right"]]
    focal = np.mean([abs(c.camera_matrix[i, i] / g.camera_matrix[i, i] - 1) * 100 for c, g in zip(cams, tc)
                     for i in (0, 1)])
    pp = np.mean([np.linalg.norm(c.camera_matrix[:2, 2] - g.camera_matrix[:2, 2]) for c, g in zip(cams, tc)])
    k1 = np.mean([abs(c.dist_coeffs[0] - g.dist_coeffs[0]) for c, g in zip(cams, tc)])
    lc, rc = _common(left, right)
    est = triangulate(cams[0], cams[1], RigidTransform.from_rt(r, t), lc.image_px, rc.image_px)
    recon = float(np.mean(np.linalg.norm(est - box_pose.apply(lc.object_mm), axis=1)))
    return {"focal_pct": float(focal), "pp_px": float(pp), "k1_abs": float(k1),
            "rot_deg": _angle_deg(r @ truth["R"].T), "baseline_mm": float(np.linalg.norm(t - truth["T"])),
            "rms_px": float(rms), "recon_mm": recon, "ms": ms}


def run_edgecal(left: CornerSet, right: CornerSet, size: tuple[int, int], truth: dict, options: RefineOptions) -> dict:
    t0 = time.process_time()
    cal = calibrate_box_stereo(left, right, size, options)
    ms = 1e3 * (time.process_time() - t0)
    s = _score(cal.cameras, cal.rotation, cal.translation_mm, cal.view_poses[0], cal.rms_px, truth, left, right, ms)
    fx_err = abs(cal.cameras[0].camera_matrix[0, 0] - truth["left"].camera_matrix[0, 0])
    s["z_fx"] = float(fx_err / cal.camera_std[0]["fx"])
    s["z_T"] = float(np.mean(np.abs(cal.translation_mm - truth["T"]) / cal.translation_std_mm))
    # |error| / sigma of every intrinsic (fx, fy, cx, cy, k1 of both cameras) and of T: median over them
    z = []
    for c, g, std in zip(cal.cameras, (truth["left"], truth["right"]), cal.camera_std):
        for name, i, j in (("fx", 0, 0), ("fy", 1, 1), ("cx", 0, 2), ("cy", 1, 2)):
            z.append(abs(c.camera_matrix[i, j] - g.camera_matrix[i, j]) / std[name])
        z.append(abs(c.dist_coeffs[0] - g.dist_coeffs[0]) / std["k1"])
    z += list(np.abs(cal.translation_mm - truth["T"]) / cal.translation_std_mm)
    s["z_all"] = float(np.median(z))
    s["dropped"] = len(cal.dropped)
    for info in cal.init.values():
        for m in ("tsai", "dlt"):
            s[f"kept_{m}"] = s.get(f"kept_{m}", 0) + int(bool(info.get("chosen_" + m)))
    return s


def run_opencv(left: CornerSet, right: CornerSet, size: tuple[int, int], truth: dict, distortion: str) -> dict:
    t0 = time.process_time()
    flags = opencv_flags(distortion) | cv2.CALIB_USE_INTRINSIC_GUESS
    cams, poses = [], []
    for cs in (left, right):
        lin = calibrate_dlt(cs.object_mm, cs.image_px)
        _, k, d, rv, tv = cv2.calibrateCamera([cs.object_mm.astype(np.float32)],
                                              [cs.image_px.astype(np.float32).reshape(-1, 1, 2)], size,
                                              lin.camera_matrix.copy(), np.zeros(5), flags=flags)
        cams.append(CameraModel.from_opencv(k, np.ravel(d)[:5]))
        poses.append(RigidTransform(np.ravel(rv[0]), np.ravel(tv[0])))
    lc, rc = _common(left, right)
    out = cv2.stereoCalibrateExtended([lc.object_mm.astype(np.float32)],
                                      [lc.image_px.astype(np.float32).reshape(-1, 1, 2)],
                                      [rc.image_px.astype(np.float32).reshape(-1, 1, 2)],
                                      cams[0].camera_matrix, cams[0].dist_coeffs, cams[1].camera_matrix,
                                      cams[1].dist_coeffs, size, np.eye(3), np.zeros((3, 1)),
                                      flags=opencv_flags(distortion) | cv2.CALIB_USE_INTRINSIC_GUESS)
    rms, k1, d1, k2, d2, rot, t = out[:7]
    rvecs, tvecs = out[9], out[10]
    ms = 1e3 * (time.process_time() - t0)
    cams = [CameraModel.from_opencv(k1, np.ravel(d1)[:5]), CameraModel.from_opencv(k2, np.ravel(d2)[:5])]
    box_pose = RigidTransform(np.ravel(rvecs[0]), np.ravel(tvecs[0]))
    return _score(cams, rot, np.ravel(t), box_pose, rms, truth, left, right, ms)


def _linear_errors(cs: CornerSet, size: tuple[int, int], cam: CameraModel) -> dict:
    out = {}
    for m in ("tsai", "dlt"):
        try:
            lin = linear_start(cs, size, m)
            out[f"{m}_focal_pct"] = float(abs(lin.camera_matrix[0, 0] / cam.camera_matrix[0, 0] - 1) * 100)
            out[f"{m}_rms_px"] = lin.rms_px
        except edgecal.errors.EdgecalError:
            out[f"{m}_focal_pct"] = float("nan")
    return out


def _median_table(rows: list[dict], keys: tuple[str, ...]) -> dict:
    return {k: float(np.nanmedian([r[k] for r in rows])) for k in keys if rows and k in rows[0]}


def synthetic(args: argparse.Namespace) -> dict:
    target = box_target()
    options = RefineOptions(distortion=args.distortion)
    noises = [float(v) for v in args.noise.split(",")]
    results: dict = {"pairs": 0, "failed": [], "detector_rms_px": [], "sets": {}}
    linear: list[dict] = []
    rng = np.random.default_rng(12345)
    for seed in range(args.pairs):
        view = box_stereo(seed, size=(1280, 800), distance_mm=(250.0, 350.0))
        truth = _truth(view.pair)
        size = tuple(view.pair["left"]["image_size"])
        dl, dr = edgecal.detect(view.left.image, target), edgecal.detect(view.right.image, target)
        a_l, a_r = assign_stereo(dl, dr, target)
        if a_l is None or a_r is None or len(a_l.corners) < 40 or len(a_r.corners) < 40:
            results["failed"].append(seed)
            continue
        results["pairs"] += 1
        exact = (_exact(a_l.corners, truth["left"], truth["left_pose"]),
                 _exact(a_r.corners, truth["right"], truth["right_pose"]))
        for d, e in zip((a_l.corners, a_r.corners), exact):
            results["detector_rms_px"].append(float(np.sqrt(np.mean(np.sum((d.image_px - e.image_px) ** 2, axis=1)))))
        linear.append(_linear_errors(_noisy(exact[0], 0.1, rng), size, truth["left"]))
        for source, base in (("exact", exact), ("detected", (a_l.corners, a_r.corners))):
            for sigma in noises:
                for _ in range(args.draws if sigma > 0 or source == "exact" else 1):
                    left, right = _noisy(base[0], sigma, rng), _noisy(base[1], sigma, rng)
                    key = f"{source} +{sigma:g}px"
                    bucket = results["sets"].setdefault(key, {"edgecal": [], "unweighted": [], "opencv": []})
                    runs = [("edgecal", left, right)]
                    if left.image_cov_px2 is not None:   # the same corners, every one weighing alike
                        runs.append(("unweighted", _plain(left), _plain(right)))
                    for method, a, b in runs:
                        try:
                            bucket[method].append(run_edgecal(a, b, size, truth, options))
                        except edgecal.errors.EdgecalError as exc:
                            print(f"seed {seed} {key}: {method} failed: {exc}", file=sys.stderr)
                    try:
                        bucket["opencv"].append(run_opencv(left, right, size, truth, args.distortion))
                    except cv2.error as exc:
                        print(f"seed {seed} {key}: OpenCV failed: {str(exc).splitlines()[-1]}", file=sys.stderr)
                    if sigma == 0 and source == "exact":
                        break
    results["linear_starts_0.1px"] = _median_table(linear,
                                                   ("tsai_focal_pct", "dlt_focal_pct", "tsai_rms_px", "dlt_rms_px"))
    return results


def planar_synthetic(n_sets: int, n_poses: int = 12, photometric: str = "normal") -> dict:
    """Mono planar calibration from rendered hand-held sessions (edgecal.synth.handheld, 640x480, 9x6
    board, one held frame per pose) through the rig's radtan lens (model k1k2p1p2) and through a fisheye
    (Kannala-Brandt, 150-200 deg): errors of fx, fy, cx, cy and the first two lens parameters against the
    truth and |error| / sigma, with the detector's corner covariances as weights and without.

    Seeds are tried in turn until ``n_sets`` sessions of each lens calibrate (at most 4 n_sets seeds: in
    a wide fisheye the held board often leaves the image, and a session needs 6 views)."""
    from dataclasses import replace as dc_replace

    from edgecal.calibration.assign import assign
    from edgecal.calibration.planar import coverage
    from edgecal.calibration.views import corner_set
    from edgecal.synth.handheld import handheld_rig, handheld_sequence
    from edgecal.synth.scenes import random_camera

    out: dict = {}
    for lens, distortion in (("radtan", "k1k2p1p2"), ("fisheye", "fisheye")):
        res: dict = {"sets": 0, "seeds_tried": 0, "weighted": [], "unweighted": []}
        out[lens] = res
        for seed in range(4 * n_sets):
            if res["sets"] >= n_sets:
                break
            res["seeds_tried"] += 1
            rig = handheld_rig([seed, 31], (640, 480), stereo=False)
            if lens == "fisheye":
                rig = dc_replace(rig, left=random_camera(np.random.default_rng([seed, 32]), (640, 480),
                                                         distortion="fisheye"))
            target = planar_target(rig.board.cols, rig.board.rows, rig.board.square_mm, name=rig.board.name)
            views = []
            try:
                for fr in handheld_sequence([seed, 31], rig, n_poses=n_poses, hold_frames=1, move_frames=0,
                                            photometric=photometric):
                    a = assign(edgecal.detect(fr.left.image, target), target)
                    if a is not None:
                        views.append(corner_set(target, list(a.corners.keys), a.corners.image_px,
                                                a.corners.image_cov_px2))
            except ValueError as exc:            # the board does not fit this camera's view
                print(f"planar {lens} seed {seed}: {exc}", file=sys.stderr)
                continue
            if len(views) < 6:
                continue
            truth = rig.left
            names = ("fx", "fy", "cx", "cy") + truth.param_names[:2]
            true = dict(zip(truth.intrinsic_names, truth.intrinsics))
            rows = {}
            for key, vs in (("weighted", views), ("unweighted", [_plain(v) for v in views])):
                try:
                    cal = calibrate_planar(vs, None, (640, 480), RefineOptions(distortion=distortion))
                except edgecal.errors.EdgecalError as exc:
                    print(f"planar {lens} seed {seed} {key}: edgecal failed: {exc}", file=sys.stderr)
                    break
                cam, std = cal.cameras[0], cal.camera_std[0]
                est = dict(zip(cam.intrinsic_names, cam.intrinsics))
                rows[key] = {"seed": seed, "views": len(cal.view_index),
                             "image_coverage": coverage(cal.corners[0], (640, 480)),
                             "focal_pct": 50 * (abs(est["fx"] / true["fx"] - 1) + abs(est["fy"] / true["fy"] - 1)),
                             "pp_px": float(np.hypot(est["cx"] - true["cx"], est["cy"] - true["cy"])),
                             "rms_px": cal.rms_px, "dropped": len(cal.dropped),
                             "z": [float(abs(est[n] - true[n]) / std[n]) for n in names]}
            if len(rows) == 2:                   # scored only when both solves ran: the rows stay paired
                res["sets"] += 1
                for key, row in rows.items():
                    res[key].append(row)
    return out


def print_planar(res: dict) -> None:
    for lens, r in res.items():
        print(f"\n== planar mono, {lens} lens, {r['sets']} rendered hand-held sessions of {r['seeds_tried']} seeds "
              f"(640x480, 9x6 board, one frame per pose)")
        for key in ("weighted", "unweighted"):
            rows = r[key]
            if not rows:
                continue
            z = np.concatenate([x["z"] for x in rows])
            print(f"{key:<11} focal {np.median([x['focal_pct'] for x in rows]):.4f} %, principal point "
                  f"{np.median([x['pp_px'] for x in rows]):.3f} px, "
                  f"RMS {np.median([x['rms_px'] for x in rows]):.3f} px, "
                  f"dropped {np.mean([x['dropped'] for x in rows]):.1f}/session; |error| / sigma over fx fy cx cy and "
                  f"two lens parameters ({len(z)}): median {np.median(z):.2f}, p90 {np.percentile(z, 90):.2f} "
                  f"(consistent: 0.67, 1.64), within 1 sigma {100 * np.mean(z < 1):.0f} %, within 2 sigma "
                  f"{100 * np.mean(z < 2):.0f} % (consistent: 68 %, 95 %); image coverage median "
                  f"{100 * np.median([x['image_coverage'] for x in rows]):.0f} %, views median "
                  f"{np.median([x['views'] for x in rows]):.0f}")


def print_synthetic(res: dict) -> None:
    print(f"\n== box stereo, {res['pairs']} rendered pairs (1280x800, 100 mm box at 250-350 mm), "
          f"failed detections: {res['failed'] or 'none'}; detector corner RMS vs truth (median) "
          f"{np.median(res['detector_rms_px']):.3f} px")
    head = (f"{'corners':<18}{'method':<9}" + "".join(f"{m:>12}" for m in METRICS)
            + f"{'z_fx':>7}{'z_T':>7}{'z_all':>7}")
    print(head)
    for key, bucket in res["sets"].items():
        med = {}
        for method in ("edgecal", "unweighted", "opencv"):
            rows = bucket.get(method, [])
            if not rows:
                continue
            med[method] = _median_table(rows, METRICS + (("z_fx", "z_T", "z_all") if method != "opencv" else ()))
            line = f"{key:<18}{method[:8]:<9}" + "".join(f"{med[method][m]:>12.4f}" for m in METRICS)
            if method != "opencv":
                line += f"{med[method]['z_fx']:>7.2f}{med[method]['z_T']:>7.2f}{med[method]['z_all']:>7.2f}"
            print(line)
        if "edgecal" in med and "opencv" in med:
            print(f"{'':<18}{'ratio':<9}" + "".join(
                f"{med['opencv'][m] / med['edgecal'][m]:>12.2f}" if med["edgecal"][m] > 1e-6 else f"{'-':>12}"
                for m in METRICS))
        if bucket.get("unweighted"):
            # paired over the same pairs and draws: weighted / unweighted error, median and how often lower
            for m in ("focal_pct", "rot_deg", "baseline_mm", "recon_mm"):
                w = np.array([r[m] for r in bucket["edgecal"]])
                u = np.array([r[m] for r in bucket["unweighted"]])
                if len(w) == len(u):
                    print(f"{'':<18}weighted vs unweighted {m}: median {np.median(w):.4f} / {np.median(u):.4f}, "
                          f"mean {np.mean(w):.4f} / {np.mean(u):.4f}, weighted lower in {np.sum(w < u)}/{len(w)}")
        n = len(bucket["edgecal"])
        if n:
            kept = {m: sum(r.get(f"kept_{m}", 0) for r in bucket["edgecal"]) for m in ("tsai", "dlt")}
            p90 = {m: float(np.percentile([r[m] for r in bucket["edgecal"]], 90))
                   for m in ("focal_pct", "baseline_mm", "recon_mm")}
            print(f"{'':<18}edgecal p90: focal {p90['focal_pct']:.3f} %, baseline {p90['baseline_mm']:.3f} mm, "
                  f"recon {p90['recon_mm']:.4f} mm; start kept: tsai {kept['tsai']}, dlt {kept['dlt']} (of {2 * n}); "
                  f"corners dropped per pair (mean) {np.mean([r['dropped'] for r in bucket['edgecal']]):.1f}")
    lin = res["linear_starts_0.1px"]
    print(f"linear starts alone (exact +0.1 px, left camera, median): Tsai focal error {lin['tsai_focal_pct']:.2f} % "
          f"(RMS {lin['tsai_rms_px']:.2f} px), DLT {lin['dlt_focal_pct']:.2f} % (RMS {lin['dlt_rms_px']:.2f} px)")


def _cv_corners(path: Path, board) -> CornerSet | None:
    g = load_grey(path)
    ok, c = cv2.findChessboardCorners(g, (board.cols, board.rows),
                                      flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
    if not ok:
        return None
    c = cv2.cornerSubPix(g, c, (11, 11), (-1, -1), (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.01))
    return CornerSet(board.board_points_mm(), c.reshape(-1, 2).astype(float),
                     tuple((board.name, int(a), int(b)) for a, b in board.ids()))


def _edgecal_corners(path: Path, target) -> CornerSet:
    board = target.boards[0]
    dets = [d for d in edgecal.detect(load_grey(path), target) if d.complete]
    if not dets:
        return CornerSet(np.zeros((0, 3)), np.zeros((0, 2)), ())
    d = dets[0]
    ok = d.usable()
    return CornerSet(board.board_points_mm(d.ids[ok]), np.asarray(d.corners, float)[ok],
                     tuple((board.name, int(a), int(b)) for a, b in d.ids[ok]),
                     None if d.covariance is None else d.covariance[ok])


def _kept_residuals(cal) -> dict:
    """(camera, input view, corner key) -> residual (2,) px of every corner a calibration kept."""
    out = {}
    for c, per_view in enumerate(cal.corners):
        for k, cs in enumerate(per_view):
            for key, r, ok in zip(cs.keys, cal.residuals_px[c][k], cal.inliers[c][k]):
                if ok:
                    out[(c, cal.view_index[k], key)] = r
    return out


def bouguet(args: argparse.Namespace) -> dict | None:
    """Bouguet's stereo set: edgecal (its corners, weighted by their covariances and unweighted) and OpenCV
    (findChessboardCorners + cornerSubPix, stereoCalibrate); the edgecal solutions also on the corners both
    kept (an RMS over more corners is not comparable)."""
    d = REAL / "opencv_stereo_9x6"
    if not d.is_dir():
        print("\n== opencv_stereo_9x6: absent, skipped")
        return None
    target = planar_target(9, 6, 30.0)
    lp, rp = sorted(d.glob("left*.jpg")), sorted(d.glob("right*.jpg"))
    out = {}
    cals = {}
    for name, getter in (("edgecal", lambda p: _edgecal_corners(p, target)),
                         ("unweighted", lambda p: _plain(_edgecal_corners(p, target))),
                         ("opencv", lambda p: _cv_corners(p, target.boards[0]))):
        t0 = time.perf_counter()
        left = [getter(p) for p in lp]
        right = [getter(p) for p in rp]
        t_det = time.perf_counter() - t0
        empty = CornerSet(np.zeros((0, 3)), np.zeros((0, 2)), ())
        left = [c if c is not None else empty for c in left]
        right = [c if c is not None else empty for c in right]
        found = sum(len(c) > 0 for c in left + right)
        t0 = time.perf_counter()
        if name != "opencv":
            cal = calibrate_planar(left, right, (640, 480), RefineOptions(distortion="k1k2p1p2k3"))
            cals[name] = cal
            k = [c.camera_matrix for c in cal.cameras]
            t_vec, om, rms = cal.translation_mm, cv2.Rodrigues(cal.rotation)[0].ravel(), cal.rms_px
            extra = {"T_std_mm": cal.translation_std_mm.tolist(), "fx_std": cal.camera_std[0]["fx"],
                     "fy_std": cal.camera_std[0]["fy"], "cc_std": [cal.camera_std[0]["cx"], cal.camera_std[0]["cy"]],
                     "om_std_rad": cal.rotation_std_rad.tolist(),
                     "recon_mm": cal.reconstruction.mean_mm, "epipolar_rms_px": cal.rectification.epipolar_rms_px,
                     "dropped": len(cal.dropped), "pairs": len(cal.view_index),
                     "noise_floor_px": float(getattr(cal, "noise_floor_px", 0.0)),
                     "corners_kept": int(sum(int(m.sum()) for per in cal.inliers for m in per))}
        else:
            pairs = [(a, b) for a, b in zip(left, right) if len(a) and len(b)]
            obj = [a.object_mm.astype(np.float32) for a, _ in pairs]
            il = [a.image_px.astype(np.float32).reshape(-1, 1, 2) for a, _ in pairs]
            ir = [b.image_px.astype(np.float32).reshape(-1, 1, 2) for _, b in pairs]
            _, k1, d1, _, _, std1, *_ = cv2.calibrateCameraExtended(obj, il, (640, 480), None, None)
            _, k2, d2, _, _ = cv2.calibrateCamera(obj, ir, (640, 480), None, None)
            rms, k1, d1, k2, d2, r, t = cv2.stereoCalibrate(obj, il, ir, k1, d1, k2, d2, (640, 480),
                                                            flags=cv2.CALIB_USE_INTRINSIC_GUESS)[:7]
            k, t_vec, om = [k1, k2], np.ravel(t), cv2.Rodrigues(r)[0].ravel()
            # calibrateCamera's own sigma of the left intrinsics (its stereoCalibrate reports none)
            std1 = np.ravel(std1)
            extra = {"pairs": len(pairs), "fx_std": float(std1[0]), "fy_std": float(std1[1]),
                     "cc_std": [float(std1[2]), float(std1[3])], "corners_kept": 2 * 54 * len(pairs)}
        t_cal = time.perf_counter() - t0
        out[name] = {"found": found, "detect_s": t_det, "calibrate_s": t_cal, "fx_left": k[0][0, 0],
                     "fy_left": k[0][1, 1], "cc_left": k[0][:2, 2].tolist(), "fx_right": k[1][0, 0],
                     "T_mm": np.ravel(t_vec).tolist(), "om_rad": om.tolist(), "rms_px": float(rms), **extra}
    # Like for like: both edgecal solutions on the corners both kept.
    a, b = _kept_residuals(cals["edgecal"]), _kept_residuals(cals["unweighted"])
    common = sorted(set(a) & set(b))
    for name, res in (("edgecal", a), ("unweighted", b)):
        r = np.array([res[key] for key in common])
        out[name]["rms_common_px"] = float(np.sqrt(np.mean(np.sum(r ** 2, axis=1))))
        out[name]["corners_common"] = len(common)
    return out


def print_bouguet(res: dict | None) -> None:
    if res is None:
        return
    print("\n== opencv_stereo_9x6 (13 pairs, 30 mm squares), planar stereo; Bouguet published: left fc (533.00, "
          "533.15), cc (341.59, 234.26); right fc 536.98; T (-99.80, 1.12, 0.05) ± (0.14, 0.11, 0.50) mm; "
          "om (0.00669, 0.00452, -0.00350) rad")
    for name, r in res.items():
        t = r["T_mm"]
        line = (f"{name:<10} boards found {r['found']}/26, pairs used {r['pairs']}, corners kept {r['corners_kept']}, "
                f"left fc ({r['fx_left']:.2f}, {r['fy_left']:.2f}) ± ({r['fx_std']:.2f}, {r['fy_std']:.2f}) "
                f"cc ({r['cc_left'][0]:.2f}, {r['cc_left'][1]:.2f}) ± ({r['cc_std'][0]:.2f}, {r['cc_std'][1]:.2f}), "
                f"right fx {r['fx_right']:.2f}, "
                f"T ({t[0]:.2f}, {t[1]:.2f}, {t[2]:.2f}) mm, om ({', '.join(f'{v:.5f}' for v in r['om_rad'])}), "
                f"RMS {r['rms_px']:.3f} px, detect {r['detect_s']:.2f} s, calibrate {r['calibrate_s']:.2f} s")
        if "T_std_mm" in r:
            line += (f"\n{'':<10} T std ({', '.join(f'{v:.2f}' for v in r['T_std_mm'])}) mm, om std "
                     f"({', '.join(f'{v:.5f}' for v in r['om_std_rad'])}), "
                     f"reconstruction {r['recon_mm']:.3f} mm, epipolar RMS {r['epipolar_rms_px']:.3f} px, "
                     f"{r['dropped']} corners dropped, covariances widened by {r['noise_floor_px']:.3f} px; "
                     f"RMS on the {r['corners_common']} corners both edgecal solves kept {r['rms_common_px']:.3f} px")
        print(line)


def ortho3() -> dict | None:
    d = REAL / "ortho3_box_stereo"
    if not d.is_dir():
        print("\n== ortho3_box_stereo: absent, skipped")
        return None
    target = load_target(Path(__file__).resolve().parents[1] / "configs" / "targets" / "ortho3-corner.yaml")
    out = {}
    for model in ("none", "k1k2"):
        li, ri = load_grey(d / "left.jpg"), load_grey(d / "right.jpg")
        a_l, a_r = assign_stereo(edgecal.detect(li, target), edgecal.detect(ri, target), target)
        cal = calibrate_box_stereo(a_l.corners, a_r.corners, (li.shape[1], li.shape[0]),
                                   RefineOptions(distortion=model, outlier_sigmas=1e9))
        out[model] = {"K_left": cal.cameras[0].camera_matrix.tolist(), "K_right": cal.cameras[1].camera_matrix.tolist(),
                      "std_left": cal.camera_std[0], "T_mm": cal.translation_mm.tolist(),
                      "T_std_mm": cal.translation_std_mm.tolist(),
                      "rot_deg_vs_authors": _angle_deg(cal.rotation @ np.array(
                          [[0.9038, -0.2757, 0.3275], [0.2804, 0.9593, 0.0336], [-0.3234, 0.0615, 0.9443]]).T),
                      "rms_px": cal.rms_px, "recon_mm": cal.reconstruction.mean_mm,
                      "corners": [len(a_l.corners), len(a_r.corners)]}
    return out


def print_ortho3(res: dict | None) -> None:
    if res is None:
        return
    print("\n== ortho3_box_stereo (one shot, 1600x1200); authors (Hall linear, no distortion): K1 f (1649.4, 1654.1) "
          "c (793.3, 614.4); K2 f (1631.7, 1625.7) c (789.1, 634.8); T (-229.2, -17.5, 38.2) mm")
    for model, r in res.items():
        kl, kr, t, ts = np.array(r["K_left"]), np.array(r["K_right"]), r["T_mm"], r["T_std_mm"]
        print(f"edgecal distortion={model:<5} corners {r['corners']}: K1 f ({kl[0, 0]:.1f}, {kl[1, 1]:.1f}) ± "
              f"{r['std_left']['fx']:.1f} c ({kl[0, 2]:.1f}, {kl[1, 2]:.1f}); K2 f ({kr[0, 0]:.1f}, {kr[1, 1]:.1f}) "
              f"c ({kr[0, 2]:.1f}, {kr[1, 2]:.1f}); T ({t[0]:.1f}, {t[1]:.1f}, {t[2]:.1f}) "
              f"± ({ts[0]:.1f}, {ts[1]:.1f}, {ts[2]:.1f}) mm; "
              f"R differs from the authors' by {r['rot_deg_vs_authors']:.3f} deg; RMS {r['rms_px']:.2f} px; "
              f"reconstruction {r['recon_mm']:.2f} mm")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--pairs", type=int, default=8, help="rendered box pairs (default 8)")
    p.add_argument("--draws", type=int, default=2, help="noise draws per pair and level (default 2)")
    p.add_argument("--noise", default="0,0.1,0.3", help="extra corner noise levels in px (default 0,0.1,0.3)")
    p.add_argument("--distortion", default="k1k2p1p2", help="distortion model of both methods (the renderer's "
                   "cameras have k1 k2 p1 p2)")
    p.add_argument("--json", help="also write the raw results here")
    p.add_argument("--force", action="store_true", help="replace an existing --json file")
    p.add_argument("--no-real", action="store_true", help="skip the real data sets")
    p.add_argument("--lens-views", type=int, default=20, help="view pairs per lens-model calibration (default 20)")
    p.add_argument("--lens-draws", type=int, default=3, help="noise draws per lens model (default 3)")
    p.add_argument("--scale", default="300", help="view pairs of the scale runs, comma-separated (default 300)")
    p.add_argument("--only", choices=("box", "planar", "lenses", "scale", "real"), action="append",
                   help="run only these sections (repeatable; default all)")
    p.add_argument("--scale-child", type=int, help=argparse.SUPPRESS)
    p.add_argument("--planar-sets", type=int, default=6, help="rendered hand-held planar sessions (default 6)")
    args = p.parse_args()
    if args.scale_child:
        _scale_child(args.scale_child)
        return 0
    if args.json and Path(args.json).exists() and not args.force:
        print(f"bench/calibrate.py: error: {args.json} exists; pass --force to replace it", file=sys.stderr)
        return 2
    t0 = time.perf_counter()
    only = set(args.only or ("box", "planar", "lenses", "scale", "real"))
    res: dict = {}
    if "box" in only:
        res["synthetic"] = synthetic(args)
        print_synthetic(res["synthetic"])
    if "planar" in only and args.planar_sets:
        res["planar"] = planar_synthetic(args.planar_sets)
        print_planar(res["planar"])
    if "lenses" in only:
        res["lens_models"] = lens_models(args)
        print_lens_models(res["lens_models"], args.lens_views)
    if "scale" in only:
        res["scale"] = scale([int(v) for v in args.scale.split(",")])
        print_scale(res["scale"])
    if "real" in only and not args.no_real:
        res["bouguet"] = bouguet(args)
        print_bouguet(res["bouguet"])
        res["ortho3"] = ortho3()
        print_ortho3(res["ortho3"])
        res["urban_fisheye1"] = urban_fisheye()
        print_urban(res["urban_fisheye1"])
    print(f"\n(total {time.perf_counter() - t0:.0f} s, single thread, OpenCV {cv2.__version__})")
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(args.json).with_suffix(".tmp")
        tmp.write_text(json.dumps(res, indent=1, default=float))
        os.replace(tmp, args.json)
    return 0



# ------------------------------------------------------------------------------------------------ lens models

def _planar_sim_views(left: CameraModel, right: CameraModel, rig: RigidTransform, size: tuple[int, int], n: int,
                      noise: float, seed: int, spread: float = 1.0) -> tuple[list[CornerSet], list[CornerSet]]:
    """``n`` stereo views of a 9x6 board (30 mm) whose corners are all in both images, exact + noise."""
    from edgecal.synth.corners import project_target
    target = planar_target(9, 6, 30.0)
    rng = np.random.default_rng(seed)
    centre = np.array([120.0, 75.0, 0.0])
    out_l: list[CornerSet] = []
    out_r: list[CornerSet] = []
    while len(out_l) < n:
        tilt = np.radians(rng.uniform(-45, 45, 2))
        eye = centre + rng.uniform(300.0, 500.0) * np.array([np.sin(tilt[0]), np.sin(tilt[1]),
                                                             -np.cos(tilt[0]) * np.cos(tilt[1])])
        aim = centre + rng.uniform(-1, 1, 3) * np.array([220.0, 150.0, 0.0]) * spread
        pl = RigidTransform.looking_at(eye, aim, up=np.array([0.0, -1.0, 0.0]))
        pr = RigidTransform.from_rt(rig.rotation @ pl.rotation, rig.rotation @ pl.tvec + rig.tvec)
        a = project_target(target, left, pl, size, noise, rng)
        b = project_target(target, right, pr, size, noise, rng)
        if len(a) == 54 and len(b) == 54:
            out_l.append(a)
            out_r.append(b)
    return out_l, out_r


def _lens_truth(lens: str) -> tuple[CameraModel, CameraModel, RigidTransform, tuple[int, int]]:
    """The benchmark rig of a lens model, 1280x800, 80 mm baseline: radtan 70 deg, rational 95 deg, fisheye 160 deg."""
    size = (1280, 800)
    rot = cv2.Rodrigues(np.array([0.01, -0.03, 0.004]))[0]
    t = np.array([-80.0, 0.5, 1.0])
    if lens == "fisheye":
        f = 640 / np.radians(80.0)
        cams = [CameraModel(f, f * 1.001, 641.0, 398.0, "fisheye", np.array([0.03, -0.012, 0.004, -0.0008]), size),
                CameraModel(f * 1.01, f * 1.011, 633.0, 404.0, "fisheye", np.array([0.028, -0.01, 0.003, -0.0005]),
                            size)]
    elif lens == "rational":
        cams = [CameraModel(600.0, 600.5, 641.0, 398.0, "rational",
                            np.array([0.4, -0.05, 0.0008, -0.0005, 0.01, 0.75, 0.02, 0.004]), size),
                CameraModel(606.0, 606.6, 633.0, 404.0, "rational",
                            np.array([0.38, -0.04, -0.0006, 0.0004, 0.008, 0.73, 0.025, 0.003]), size)]
    else:
        cams = [CameraModel(915.0, 915.6, 641.0, 398.0, "radtan", np.array([-0.21, 0.09, 0.0008, -0.0005, 0.0]), size),
                CameraModel(925.0, 925.3, 633.0, 404.0, "radtan", np.array([-0.2, 0.08, -0.0006, 0.0004, 0.0]), size)]
    return cams[0], cams[1], RigidTransform.from_rt(rot, t), size


LENS_ROWS = (("radtan", "k1k2p1p2"), ("rational", "rational"), ("fisheye", "fisheye"))


def lens_models(args: argparse.Namespace) -> dict:
    """Planar stereo calibration per lens model on simulated views (exact projections + noise), vs truth."""
    out: dict = {}
    for lens, distortion in LENS_ROWS:
        left, right, rig, size = _lens_truth(lens)
        rows = []
        for seed in range(args.lens_draws):
            vl, vr = _planar_sim_views(left, right, rig, size, args.lens_views, 0.1, 100 + seed)
            t0 = time.process_time()
            cal = calibrate_planar(vl, vr, size, RefineOptions(distortion=distortion))
            ms = 1e3 * (time.process_time() - t0)
            z, row = [], {}
            for c, truth in enumerate((left, right)):
                est = cal.cameras[c]
                for i, name in enumerate(truth.intrinsic_names):
                    std = cal.camera_std[c].get(name, float("nan"))
                    if np.isfinite(std) and std > 0:
                        z.append(abs(est.intrinsics[i] - truth.intrinsics[i]) / std)
            pairs = list(zip(cal.cameras, (left, right)))
            row["focal_pct"] = float(np.mean([abs(c.fx / g.fx - 1) * 100 for c, g in pairs]))
            row["pp_px"] = float(np.mean([np.hypot(c.cx - g.cx, c.cy - g.cy) for c, g in pairs]))
            row["dist_err_max"] = float(max(np.max(np.abs(c.params - g.params)) for c, g in pairs))
            row["baseline_mm"] = float(np.linalg.norm(cal.translation_mm - rig.tvec))
            zt = np.abs(cal.translation_mm - rig.tvec) / cal.translation_std_mm
            z += list(zt)
            row["baseline_z_max"] = float(np.max(zt))
            row["rms_px"] = cal.rms_px
            row["z_median"] = float(np.median(z))
            row["ms"] = ms
            rows.append(row)
        out[lens] = rows
    return out


def print_lens_models(res: dict, views: int) -> None:
    print(f"\n== lens models: planar stereo, {views} simulated view pairs per calibration "
          "(exact projections + 0.1 px), "
          "1280x800, 80 mm baseline; medians over draws; |err|/σ over every intrinsic and T")
    keys = ("focal_pct", "pp_px", "dist_err_max", "baseline_mm", "baseline_z_max", "rms_px", "z_median", "ms")
    print(f"{'lens':<10}" + "".join(f"{k:>15}" for k in keys))
    for lens, rows in res.items():
        med = _median_table(rows, keys)
        print(f"{lens:<10}" + "".join(f"{med[k]:>15.4f}" for k in keys))


def _scale_child(n_pairs: int) -> None:
    """One planar stereo calibration of ``n_pairs`` views (this process's peak RSS is the measure)."""
    import resource
    left, right, rig, size = _lens_truth("radtan")
    vl, vr = _planar_sim_views(left, right, rig, size, n_pairs, 0.1, 7)
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    t0, c0 = time.perf_counter(), time.process_time()
    cal = calibrate_planar(vl, vr, size, RefineOptions(distortion="k1k2p1p2"))
    seconds, cpu = time.perf_counter() - t0, time.process_time() - c0
    print(json.dumps({"pairs": len(cal.view_index), "seconds": seconds, "cpu_seconds": cpu, "rss_before_mb": rss0,
                      "rss_peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
                      "rms_px": cal.rms_px, "focal_pct": abs(cal.cameras[0].fx / left.fx - 1) * 100,
                      "corners": 2 * 54 * len(cal.view_index)}))


def scale(pairs: list[int]) -> list[dict]:
    """Time and peak memory of planar stereo calibrations of many view pairs, each in a fresh process."""
    import subprocess
    out = []
    for n in pairs:
        p = subprocess.run([sys.executable, __file__, "--scale-child", str(n)], capture_output=True, text=True,
                           check=True)
        out.append(json.loads(p.stdout.strip().splitlines()[-1]))
    return out


def print_scale(res: list[dict]) -> None:
    print("\n== scale: planar stereo calibration (k1k2p1p2, simulated 9x6 views), one fresh process each; sparse "
          "Jacobian, scipy least_squares")
    for r in res:
        print(f"{r['pairs']:>5} pairs ({r['corners']} corners): {r['cpu_seconds']:.1f} s CPU "
              f"({r['seconds']:.1f} s wall), peak RSS {r['rss_peak_mb']:.0f} MB "
              f"({r['rss_before_mb']:.0f} MB before the calibration), RMS {r['rms_px']:.3f} px, "
              f"focal error {r['focal_pct']:.4f} %")


def urban_fisheye() -> dict | None:
    """ocamcalib_urban_fisheye1 (6x8, 32.5 mm, 15 views): edgecal's lens models vs OpenCV's on edgecal's corners."""
    from edgecal.calibration.settings import PlanarSettings
    d = REAL / "ocamcalib_urban_fisheye1"
    if not d.is_dir():
        print("\n== ocamcalib_urban_fisheye1: absent, skipped")
        return None
    target = planar_target(6, 8, 32.5)
    files = sorted(d.glob("Fisheye1_*.jpg"), key=lambda p: int(p.stem.split("_")[1]))
    views = [_edgecal_corners(p, target) for p in files]
    size = tuple(int(v) for v in load_grey(files[0]).shape[::-1])
    full = [v for v in views if len(v) == 48]
    out: dict = {"views_found": len(full), "views": len(files), "edgecal": {}, "opencv": {}}
    keep_all = PlanarSettings(max_view_rms_factor=1e9)
    for label, distortion, planar, opts in (
            ("fisheye", "fisheye", PlanarSettings(), {}),
            ("fisheye, every corner", "fisheye", keep_all, {"outlier_sigmas": 1e9}),
            ("rational", "rational", PlanarSettings(), {}),
            ("rational, every corner", "rational", keep_all, {"outlier_sigmas": 1e9}),
            ("k1k2p1p2k3, every corner", "k1k2p1p2k3", keep_all, {"outlier_sigmas": 1e9})):
        try:
            cal = calibrate_planar(full, None, size, RefineOptions(distortion=distortion, **opts), planar)
            out["edgecal"][label] = {"rms_px": cal.rms_px, "views": len(cal.view_index), "dropped": len(cal.dropped),
                                     "fx": cal.cameras[0].fx, "fx_std": cal.camera_std[0]["fx"]}
        except edgecal.errors.EdgecalError as exc:
            out["edgecal"][label] = {"error": str(exc)[:120]}
    obj = [v.object_mm.astype(np.float32) for v in full]
    img = [v.image_px.astype(np.float32).reshape(-1, 1, 2) for v in full]
    for label, flags in (("k1k2p1p2k3", 0), ("rational", cv2.CALIB_RATIONAL_MODEL)):
        rms, k, *_ = cv2.calibrateCamera(obj, img, size, None, None, flags=flags)
        out["opencv"][label] = {"rms_px": float(rms), "fx": float(k[0, 0])}
    try:
        # (1, N, 3) / (1, N, 2) float64 and a 4x1 D: the layout cv2.fisheye.calibrate accepts in OpenCV 5
        rms, k, *_ = cv2.fisheye.calibrate([o.reshape(1, -1, 3).astype(np.float64) for o in obj],
                                           [i.reshape(1, -1, 2).astype(np.float64) for i in img], size, np.eye(3),
                                           np.zeros((4, 1)), flags=cv2.CALIB_RECOMPUTE_EXTRINSIC | cv2.CALIB_FIX_SKEW,
                                           criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-10))
        out["opencv"]["fisheye"] = {"rms_px": float(rms), "fx": float(k[0, 0])}
    except cv2.error as exc:
        out["opencv"]["fisheye"] = {"error": str(exc).strip().splitlines()[-1][:120]}
    return out


def print_urban(res: dict | None) -> None:
    if res is None:
        return
    print(f"\n== ocamcalib_urban_fisheye1 (1032x778, 6x8, 32.5 mm): edgecal's corners, complete board in "
          f"{res['views_found']}/{res['views']} views; OpenCV calibrateCamera / fisheye.calibrate on the same corners")
    for who in ("edgecal", "opencv"):
        for label, r in res[who].items():
            if "error" in r:
                print(f"{who:<8} {label:<26} failed: {r['error']}")
                continue
            extra = (f", {r['views']} views used, {r['dropped']} corners dropped, fx {r['fx']:.2f} ± {r['fx_std']:.2f}"
                     if who == "edgecal" else f", fx {r['fx']:.2f}")
            print(f"{who:<8} {label:<26} RMS {r['rms_px']:.3f} px{extra}")


if __name__ == "__main__":
    tune_allocator()  # as every edgecal command does (importing edgecal does not)
    sys.exit(main())
