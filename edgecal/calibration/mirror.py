"""Is a face of a box target described mirrored? The likeliest mistake in one's own target file.

A face whose x_axis × y_axis points out of the box instead of in, or whose x_axis and y_axis are swapped,
describes the mirror image of the printed board: no camera can see that, so every fit is poor (tens of
pixels) and the refusal alone does not say why. Each face is mirrored in turn, in the three ways a
person gets it wrong (x reversed, y reversed, x and y swapped, each keeping the face where it is); when
the image corners fit one such target far better, the message names the face and the values to write.

Scoring uses the DLT residual of the assignment (assign.py), which needs no lens model: a correct target
fits the corners projectively within the distortion, a mirrored face by tens of pixels.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from edgecal.calibration.assign import assign
from edgecal.detection.types import Detection
from edgecal.targets import Board, Target

FAR_BETTER = 0.25  # a mirrored variant must fit at least 4x better than the target as written


def _vec(v: np.ndarray) -> str:
    return "[" + ", ".join(f"{float(x):g}" for x in np.round(v, 6) + 0.0) + "]"


def mirrored_faces(board: Board) -> list[tuple[str, Board]]:
    """The board's three mirror images covering the same face: x reversed, y reversed, x and y swapped.

    Each comes with the change to write in the target file, e.g. ``x_axis [-1, 0, 0] and origin_mm [...]``.
    """
    s = board.square_mm
    flip_x = replace(board, x_axis=-board.x_axis, origin_mm=board.origin_mm + (board.cols - 1) * s * board.x_axis)
    flip_y = replace(board, y_axis=-board.y_axis, origin_mm=board.origin_mm + (board.rows - 1) * s * board.y_axis)
    swap = replace(board, x_axis=board.y_axis.copy(), y_axis=board.x_axis.copy())
    return [
        (f"x_axis {_vec(flip_x.x_axis)} and origin_mm {_vec(flip_x.origin_mm)} (instead of x_axis "
         f"{_vec(board.x_axis)}, origin_mm {_vec(board.origin_mm)})", flip_x),
        (f"y_axis {_vec(flip_y.y_axis)} and origin_mm {_vec(flip_y.origin_mm)} (instead of y_axis "
         f"{_vec(board.y_axis)}, origin_mm {_vec(board.origin_mm)})", flip_y),
        (f"x_axis {_vec(swap.x_axis)} and y_axis {_vec(swap.y_axis)} (swapped)", swap),
    ]


def _fit_px(detections: list[list[Detection]], target: Target) -> float:
    """The worst camera's DLT residual (px) of the best assignment of its detections to ``target``."""
    worst = 0.0
    for dets in detections:
        a = assign(dets, target)
        if a is None or not np.isfinite(a.rms_px):
            return float("inf")
        worst = max(worst, a.rms_px)
    return worst


def mirrored_face_hint(target: Target, detections: list[list[Detection]]) -> str | None:
    """A sentence naming the mirrored face and the fix, when mirroring one face fits far better; else None.

    ``detections[camera]`` are the detections of the box view in each camera.
    """
    if target.is_planar or len(target.boards) < 2:
        return None
    written = _fit_px(detections, target)
    best: tuple[float, int, str] | None = None
    for i, board in enumerate(target.boards):
        for change, variant in mirrored_faces(board):
            fit = _fit_px(detections, replace(target, boards=target.boards[:i] + (variant,) + target.boards[i + 1:]))
            if best is None or fit < best[0]:
                best = (fit, i, change)
    if best is None or not np.isfinite(best[0]) or not best[0] <= FAR_BETTER * written:
        return None
    fit, i, change = best
    where = f" in {target.source}" if target.source else ""
    return (f"board {target.boards[i].name!r} looks mirrored (its x_axis × y_axis must point into the box): with "
            f"{change} the corners fit {fit:.2f} px instead of {written:.2f} px; change boards[{i}]{where}")
