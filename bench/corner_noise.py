#!/usr/bin/env python3
"""Corner covariance benchmark: does each corner's reported 2x2 covariance match its real error?

    .venv/bin/python bench/corner_noise.py [--views 80] [--json FILE]

Planar 9x6 views are rendered by edgecal.synth (640x480, exact truth) in five photometric conditions:
clean, normal, hard (noise 3-8, blur 1-2.5 px, low contrast, JPEG, small squares), uneven light (light
gradients of 40-70 % across the image and vignetting) and strong foreshortening (boards tilted up to
78 deg). edgecal.detect finds the boards; every corner it reports as usable is matched to the truth
corner nearest to it (within 1.5 px) and its normalised error e^T Sigma^-1 e computed with the
covariance the detector reports (2 on average for a consistent 2-D covariance; target mean 1.5-3).
Printed per condition: corners, RMS error (px), RMS reported sigma (px), normalised error mean, median
and p95, the covariance's shape (the mean squared error along its minor and major axis over the variance
there, 1 each when consistent, and the median ratio of its major to minor sigma), and the unusable
corners. The same on the tracked path (edgecal.detection.tracking, predictions
from the truth corners moved by 0.3 px).
"""

from __future__ import annotations

import os

for _var in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

import edgecal  # noqa: E402
from edgecal.detection.tracking import track_boards  # noqa: E402
from edgecal.detection.types import CornerPrediction, Detection  # noqa: E402
from edgecal.runtime import tune_allocator  # noqa: E402
from edgecal.synth.photometric import Photometric  # noqa: E402
from edgecal.synth.scenes import planar_view  # noqa: E402
from edgecal.synth.view import RenderedView  # noqa: E402
from edgecal.targets import planar_target  # noqa: E402

TARGET = planar_target(9, 6, 25.0)
TARGET_RANGE = (1.5, 3.0)


def uneven_light(rng: np.random.Generator) -> Photometric:
    """A strong light gradient across the image (40-70 % to the side edges) with vignetting, noise 2."""
    sign = rng.choice([-1.0, 1.0], size=2)
    return Photometric(blur_sigma=float(rng.uniform(0.5, 1.0)),
                       gradient=(float(sign[0] * rng.uniform(0.4, 0.7)), float(sign[1] * rng.uniform(0.3, 0.6))),
                       vignetting=float(rng.uniform(0.3, 0.6)), black_level=10.0, white_level=240.0,
                       noise_sigma=2.0)


def render(condition: str, k: int) -> RenderedView:
    """The k-th view of one condition."""
    if condition == "uneven light":
        return planar_view([k, 5], photometric=uneven_light(np.random.default_rng([k, 99])))
    kw = {"clean": dict(photometric="clean"), "normal": dict(photometric="normal"),
          "hard": dict(photometric="hard", square_px=(10.0, 30.0), tilt_max_deg=60.0),
          "foreshortened": dict(photometric="normal", tilt_max_deg=78.0)}[condition]
    return planar_view([k, 11, len(condition)], **kw)


CONDITIONS = ("clean", "normal", "hard", "uneven light", "foreshortened")


def corner_errors(det: Detection, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """(errors (M, 2), covariances (M, 2, 2), unusable count) of a detection's usable corners that lie
    within 1.5 px of a truth corner."""
    usable = det.usable()
    xy, cov = det.corners[usable], det.covariance[usable]
    d = np.linalg.norm(xy[:, None] - truth[None], axis=2)
    j = d.argmin(axis=1)
    near = d[np.arange(len(j)), j] < 1.5
    return xy[near] - truth[j[near]], cov[near], int((~usable).sum())


def summarise(errors: list[np.ndarray], covs: list[np.ndarray], unusable: int, views: int) -> dict:
    """The figures of one condition."""
    if not errors or not sum(len(e) for e in errors):
        return {"views": views, "corners": 0}
    e, c = np.concatenate(errors), np.concatenate(covs)
    nees = np.einsum("ni,nij,nj->n", e, np.linalg.inv(c), e)
    # The covariance's shape: the error along its minor and major axis, each normalised by the sigma there
    # (1 each when consistent; a shape that is too elongated shows > 1 on the minor axis, < 1 on the major).
    w, v = np.linalg.eigh(c)
    along = np.einsum("nji,nj->ni", v, e)
    axis = np.mean(along ** 2 / w, axis=0)
    return {"views": views, "corners": int(len(e)), "unusable": unusable,
            "nees_minor_axis": float(axis[0]), "nees_major_axis": float(axis[1]),
            "sigma_major_over_minor": float(np.median(np.sqrt(w[:, 1] / w[:, 0]))),
            "rms_error_px": float(np.sqrt(np.mean(e ** 2))),
            "rms_sigma_px": float(np.sqrt(np.mean(np.trace(c, axis1=1, axis2=2) / 2))),
            "nees_mean": float(nees.mean()), "nees_median": float(np.median(nees)),
            "nees_p95": float(np.percentile(nees, 95))}


def run(condition: str, n_views: int, tracked: bool) -> dict:
    """Detect (or track) n_views renders of ``condition`` and score the covariances."""
    errors, covs, unusable = [], [], 0
    rng = np.random.default_rng(3)
    for k in range(n_views):
        view = render(condition, k)
        if not view.truth["boards"]:
            continue                     # the board turned edge-on out of sight
        truth = view.corners(0)
        if tracked:
            pred = CornerPrediction(TARGET.boards[0], view.ids(0), truth + rng.normal(0, 0.3, truth.shape))
            dets = track_boards(view.image, [pred])
        else:
            dets = edgecal.detect(view.image, TARGET)
        for det in dets:
            e, c, u = corner_errors(det, truth)
            errors.append(e)
            covs.append(c)
            unusable += u
    return summarise(errors, covs, unusable, n_views)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--views", type=int, default=80, help="renders per condition (default 80)")
    ap.add_argument("--json", default=None, help="write the results here as JSON")
    args = ap.parse_args()
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=Path(__file__).parent).stdout.strip()
    results: dict = {"commit": commit, "views": args.views, "search": {}, "tracked": {}}
    print(f"corner covariance vs truth, {args.views} renders per condition (640x480, 9x6 board), commit {commit}")
    print(f"{'path':8s} {'condition':14s} {'corners':>7s} {'unusable':>8s} {'rms err':>8s} {'rms sigma':>9s} "
          f"{'NEES mean':>9s} {'median':>7s} {'p95':>6s} {'minor':>6s} {'major':>6s} {'shape':>6s}  "
          f"target mean {TARGET_RANGE[0]}-{TARGET_RANGE[1]}")
    for path in ("search", "tracked"):
        for cond in CONDITIONS:
            r = run(cond, args.views, path == "tracked")
            results[path][cond] = r
            if not r["corners"]:
                print(f"{path:8s} {cond:14s} no corners")
                continue
            ok = TARGET_RANGE[0] <= r["nees_mean"] <= TARGET_RANGE[1]
            print(f"{path:8s} {cond:14s} {r['corners']:7d} {r['unusable']:8d} {r['rms_error_px']:8.4f} "
                  f"{r['rms_sigma_px']:9.4f} {r['nees_mean']:9.2f} {r['nees_median']:7.2f} {r['nees_p95']:6.1f} "
                  f"{r['nees_minor_axis']:6.2f} {r['nees_major_axis']:6.2f} {r['sigma_major_over_minor']:6.2f}  "
                  f"{'met' if ok else 'NOT met'}", flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2))
    return 0


if __name__ == "__main__":
    tune_allocator()  # as every edgecal command does (importing edgecal does not)
    sys.exit(main())
