"""Assign detected grids to the target's boards and orientations by geometric consistency.

The detector numbers each grid and names a board of the right size, but when several boards share a
size (the three faces of a box) or a board's two 180° orientations look alike (cols + rows even), only
geometry can tell them apart. Every consistent assignment — each detection to a distinct board of
the same size, in each orientation the board allows — is scored by the residual of a DLT fit of all
the corners at once (a wrong assignment is not a projective image of the target); the smallest wins.

A target that is itself symmetric (a rigid motion maps it onto a relabelling of itself) makes two
assignments fit exactly as well; :func:`symmetry_warnings` finds that when the target is loaded.
"""

from __future__ import annotations

import itertools
import logging
from dataclasses import dataclass

import numpy as np

from edgecal.calibration.checks import DegenerateInput
from edgecal.calibration.dlt import calibrate_dlt, dlt_projection_matrix
from edgecal.calibration.types import CornerSet
from edgecal.detection.corner_covariance import without_light_shift
from edgecal.detection.types import Detection
from edgecal.targets import Board, Target

log = logging.getLogger(__name__)

MAX_ASSIGNMENTS = 20000
ROTATION_DEG = (0, 90, 180, 270)


def rotate_ids(ids: np.ndarray, cols: int, rows: int, deg: int) -> np.ndarray:
    """Corner ids of a ``cols`` x ``rows`` board after an in-plane rotation by ``deg`` (a multiple of 90).

    90 and 270 turn the board into a ``rows`` x ``cols`` one; these are rotations, never mirror images
    (a board seen from the front cannot appear mirrored).
    """
    c, r = ids[:, 0], ids[:, 1]
    if deg == 0:
        out = (c, r)
    elif deg == 180:
        out = (cols - 1 - c, rows - 1 - r)
    elif deg == 90:
        out = (rows - 1 - r, c)
    elif deg == 270:
        out = (r, cols - 1 - c)
    else:
        raise ValueError(f"rotation {deg} is not a multiple of 90")
    return np.stack(out, axis=1).astype(np.int64)


def allowed_rotations(board: Board) -> tuple[int, ...]:
    """Orientations the detector cannot tell apart: none when cols + rows is odd (the colours decide),
    0/180 for an even non-square board, all four for a square one (docs/conventions.md)."""
    if (board.cols + board.rows) % 2:
        return (0,)
    return ROTATION_DEG if board.cols == board.rows else (0, 180)


def _candidates(source: Board, target: Target) -> list[tuple[Board, int]]:
    """(board, rotation) pairs onto which a grid numbered on ``source`` can map."""
    out = []
    for b in target.boards:
        for deg in allowed_rotations(source):
            dims = (source.cols, source.rows) if deg in (0, 180) else (source.rows, source.cols)
            if dims == (b.cols, b.rows):
                out.append((b, deg))
    return out


@dataclass(frozen=True)
class Assignment:
    """Detections mapped onto the target: the matched corners, what went where, and the fit residual."""

    corners: CornerSet
    mapping: tuple[tuple[int, str, int], ...]   # (detection index, board name, rotation deg)
    rms_px: float                               # DLT residual of all corners (inf when not scored)

    def describe(self) -> str:
        """E.g. ``grid 0 -> top, grid 1 -> front (180°)``."""
        return ", ".join(f"grid {i} -> {b}" + (f" ({d}°)" if d else "") for i, b, d in self.mapping)


def _corner_set(dets: list[Detection], target: Target, choice: tuple[tuple[Board, int], ...]) -> CornerSet:
    """The usable corners of ``dets`` on the boards ``choice`` names, with their covariances when every
    detection has them (less the light's shift each view's pose absorbs: without_light_shift)."""
    objs, imgs, covs, keys = [], [], [], []
    for det, (board, deg) in zip(dets, choice):
        src = target.board(det.board)
        ok = det.usable()
        ids = rotate_ids(np.asarray(det.ids, dtype=np.int64).reshape(-1, 2)[ok], src.cols, src.rows, deg)
        objs.append(board.target_points_mm(ids))
        imgs.append(np.asarray(det.corners, dtype=np.float64).reshape(-1, 2)[ok])
        covs.append(None if det.covariance is None else without_light_shift(det.covariance, det.light_gradient,
                                                                            det.alternating_px2)[ok])
        keys += [(board.name, int(c), int(r)) for c, r in ids]
    known = [c for c in covs if c is not None]
    cov = np.concatenate(known) if len(known) == len(covs) else None
    return CornerSet(np.concatenate(objs), np.concatenate(imgs), tuple(keys), cov)


def _dlt_residual(obj: np.ndarray, img: np.ndarray) -> float:
    """RMS reprojection error of the DLT camera of these matches (inf when degenerate or behind)."""
    try:
        p = dlt_projection_matrix(obj, img)
    except DegenerateInput:
        return float("inf")
    h = np.c_[obj, np.ones(len(obj))] @ p.T
    if h[:, 2].min() <= 0:
        return float("inf")  # a wrong assignment can put corners behind the camera
    return float(np.sqrt(np.mean(np.sum((h[:, :2] / h[:, 2:3] - img) ** 2, axis=1))))


def rank_assignments(detections: list[Detection], target: Target, keep: int = 8) -> list[Assignment]:
    """Consistent assignments of ``detections`` to ``target``, best (smallest DLT residual) first.

    Detections naming a board the target does not have are ignored. A single detection, or a planar
    target, cannot be scored by a non-coplanar fit: the detector's own labelling is returned.
    """
    dets = [d for d in detections if any(b.name == d.board for b in target.boards) and len(d.ids)]
    if not dets:
        return []
    per_det = [_candidates(target.board(d.board), target) for d in dets]
    as_named = tuple((target.board(d.board), 0) for d in dets)
    if len(dets) == 1 or target.is_planar:
        cs = _corner_set(dets, target, as_named)
        return [Assignment(cs, tuple((i, b.name, deg) for i, (b, deg) in enumerate(as_named)), float("inf"))]
    combos = itertools.product(*per_det)
    n_combos = int(np.prod([len(p) for p in per_det]))
    if n_combos > MAX_ASSIGNMENTS:
        log.warning("%d possible assignments of %d grids: trying only the detector's board names",
                    n_combos, len(dets))
        combos = itertools.product(*[[c for c in p if c[0].name == d.board] for p, d in zip(per_det, dets)])
    # Object points of every (detection, board, rotation) once; each combination only stacks them.
    cache: dict[tuple[int, str, int], np.ndarray] = {}
    for i, (d, cands) in enumerate(zip(dets, per_det)):
        src = target.board(d.board)
        for b, deg in cands:
            ids = rotate_ids(np.asarray(d.ids, dtype=np.int64).reshape(-1, 2), src.cols, src.rows, deg)
            cache[(i, b.name, deg)] = b.target_points_mm(ids)
    img = np.concatenate([np.asarray(d.corners, dtype=np.float64).reshape(-1, 2) for d in dets])
    scored_choices: list[tuple[float, tuple[tuple[Board, int], ...]]] = []
    for choice in combos:
        names = [b.name for b, _ in choice]
        if len(set(names)) != len(names):
            continue
        obj = np.concatenate([cache[(i, b.name, deg)] for i, (b, deg) in enumerate(choice)])
        rms = _dlt_residual(obj, img)
        if np.isfinite(rms):
            scored_choices.append((rms, choice))
    scored_choices.sort(key=lambda sc: sc[0])
    scored: list[Assignment] = []
    for _, choice in scored_choices[:keep]:
        cs = _corner_set(dets, target, choice)
        try:  # the full DLT (distortion-free camera, points in front) confirms the quick score
            rms = calibrate_dlt(cs.object_mm, cs.image_px).rms_px
        except DegenerateInput:
            continue
        scored.append(Assignment(cs, tuple((i, b.name, deg) for i, (b, deg) in enumerate(choice)), rms))
    scored.sort(key=lambda a: a.rms_px)
    if not scored:
        cs = _corner_set(dets, target, as_named)
        return [Assignment(cs, tuple((i, b.name, 0) for i, (b, _) in enumerate(as_named)), float("inf"))]
    return scored[:keep]


def _warn_if_ambiguous(ranked: list[Assignment], what: str) -> None:
    ties = _tie(ranked) if ranked and np.isfinite(ranked[0].rms_px) else ranked[:1]
    if len(ties) > 1:
        log.warning("%s: %d assignments of the grids fit about equally well (%s px): kept %s; the target "
                    "may be (nearly) symmetric", what, len(ties),
                    ", ".join(f"{a.rms_px:.3f}" for a in ties), ties[0].describe())


def assign(detections: list[Detection], target: Target) -> Assignment | None:
    """The best assignment of one image's detections (None when nothing of the target was seen)."""
    ranked = rank_assignments(detections, target)
    _warn_if_ambiguous(ranked, "image")
    return ranked[0] if ranked else None


def _tie(candidates: list[Assignment]) -> list[Assignment]:
    """The assignments that fit about as well as the best (a symmetric target, or a noisy tie)."""
    best = candidates[0].rms_px
    return [a for a in candidates if a.rms_px <= 1.5 * best + 0.05]


def assign_stereo(left: list[Detection], right: list[Detection],
                  target: Target) -> tuple[Assignment | None, Assignment | None]:
    """Assignments for both images of a stereo pair that label the same physical boards alike.

    When several assignments of the right image fit about equally (a symmetric target), the one whose
    left->right rotation is smallest is kept: the two cameras of a rig look the same way.
    """
    rl, rr = rank_assignments(left, target), rank_assignments(right, target)
    if not rl or not rr:
        return (rl[0] if rl else None), (rr[0] if rr else None)
    a_l = rl[0]
    _warn_if_ambiguous(rl, "left image")
    ties = _tie(rr)
    if len(ties) == 1 or not np.isfinite(a_l.rms_px):
        return a_l, rr[0]
    r_left = calibrate_dlt(a_l.corners.object_mm, a_l.corners.image_px).rotation

    def angle(a: Assignment) -> float:
        r = calibrate_dlt(a.corners.object_mm, a.corners.image_px).rotation @ r_left.T
        return float(np.arccos(np.clip((np.trace(r) - 1) / 2, -1, 1)))

    return a_l, min(ties, key=angle)


def symmetry_warnings(target: Target) -> list[str]:
    """Messages for every relabelling of the target's boards that a rigid motion reproduces exactly.

    Such a target lets two assignments fit equally well; the message says which boards to change.
    """
    if len(target.boards) < 2 or target.is_planar:
        return []
    pts = np.concatenate([b.target_points_mm() for b in target.boards])
    scale = float(np.abs(pts - pts.mean(axis=0)).max())
    per_board = [_candidates(b, target) for b in target.boards]
    out = []
    for choice in itertools.product(*per_board):
        names = [b.name for b, _ in choice]
        if len(set(names)) != len(names):
            continue
        if all(b.name == src.name and deg == 0 for src, (b, deg) in zip(target.boards, choice)):
            continue
        mapped = np.concatenate([b.target_points_mm(rotate_ids(src.ids(), src.cols, src.rows, deg))
                                 for src, (b, deg) in zip(target.boards, choice)])
        # Kabsch: is there a proper rotation + translation taking pts onto mapped?
        a, m = pts - pts.mean(axis=0), mapped - mapped.mean(axis=0)
        u, _, vt = np.linalg.svd(a.T @ m)
        d = np.sign(np.linalg.det(u @ vt))
        rot = (u @ np.diag([1, 1, d]) @ vt).T
        if np.abs(a @ rot.T - m).max() < 1e-6 * scale:
            moves = ", ".join(f"{src.name}->{b.name}" + (f" ({deg}°)" if deg else "")
                              for src, (b, deg) in zip(target.boards, choice)
                              if src.name != b.name or deg)
            changed = next(src.name for src, (b, deg) in zip(target.boards, choice) if src.name != b.name or deg)
            out.append(f"target {target.name!r} is symmetric: relabelling {moves} fits the images exactly as well, "
                       f"so calibration cannot tell these boards apart; give board {changed!r} a different size "
                       f"or placement (e.g. one more column)")
    return out
