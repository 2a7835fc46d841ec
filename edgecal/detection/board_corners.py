"""A found board's final corners: refined once more (cornerSubPix, the rim again, the saddle fit) and
corners that slid along an edge put back where their neighbours say."""

from __future__ import annotations

import numpy as np

from edgecal.detection.completion import predict_holes
from edgecal.detection.params import DetectorParams
from edgecal.detection.subpixel import nearest_spacing, refine_corners, refine_rim, saddle_refine

# A final corner further than this fraction of a square from where its neighbours put it slid along an edge.
SLID_FRACTION = 0.2


def final_corners(smooth: np.ndarray, xy: np.ndarray, ids: np.ndarray, p: DetectorParams,
                   spacing: np.ndarray | None = None) -> np.ndarray:
    """A board's final corners: cornerSubPix with the window from the grid's own spacing (``spacing``, or
    the corners' nearest-neighbour distances), the corners on the board's rim again with a smaller window
    where that continues the grid's lines better (refine_rim), then (refiner "saddle") the saddle fit."""
    spacing = nearest_spacing(xy) if spacing is None else spacing
    xy, window = refine_rim(smooth, refine_corners(smooth, xy, spacing), ids, spacing)
    return saddle_refine(smooth, xy, window) if p.subpixel_refiner == "saddle" else xy


def resettle_slid_corners(smooth: np.ndarray, ids: np.ndarray, xy: np.ndarray, p: DetectorParams) -> np.ndarray:
    """Corners that slid along an edge, refined again from where their neighbours put them.

    On a steeply slanted board cornerSubPix is ill-conditioned along thin squares and can slide a corner
    along one of its edges by a good part of a square; the grid checks barely see a sideways slip of an
    outer corner. Each corner is predicted from a local homography of its neighbours (leaving it out, all
    corners in one batch); one further than SLID_FRACTION of a square from its prediction is refined again
    from the prediction, and the new position is kept when it agrees with the prediction better.
    """
    out = xy.copy()
    cols, rows = int(ids[:, 0].max()) + 1, int(ids[:, 1].max()) + 1
    if len(ids) != cols * rows or min(cols, rows) < 3:
        return out
    spacing = nearest_spacing(xy)
    index = {(int(c), int(r)): i for i, (c, r) in enumerate(ids)}
    for _ in range(3):  # a slid corner misleads its neighbours' predictions: repeat once it is back
        # cheap screen first: second differences along rows and columns (ends take their neighbours')
        dense = np.empty((rows, cols, 2))
        dense[ids[:, 1], ids[:, 0]] = out
        bend = np.zeros((rows, cols))
        for axis in (0, 1):
            g = np.moveaxis(dense, axis, 0)
            d2 = np.linalg.norm(g[:-2] - 2.0 * g[1:-1] + g[2:], axis=-1)
            b = np.zeros(g.shape[:2])
            b[1:-1] = d2
            b[0], b[-1] = d2[0], d2[-1]
            bend = np.maximum(bend, np.moveaxis(b, 0, axis))
        flagged = bend[ids[:, 1], ids[:, 0]] > np.maximum(SLID_FRACTION * spacing, 1.5)
        if not flagged.any():
            break
        grid = {k: out[i] for k, i in index.items()}
        preds, keys, _sp = predict_holes(grid, [k for k, i in index.items() if flagged[i]])
        if not keys:
            break
        sel = np.array([index[k] for k in keys])
        pred = np.asarray(preds)
        off = np.linalg.norm(out[sel] - pred, axis=1)
        slid = off > np.maximum(SLID_FRACTION * spacing[sel], 1.5)
        if not slid.any():
            break
        again = final_corners(smooth, pred[slid], ids[sel][slid], p, spacing[sel][slid])
        better = np.linalg.norm(again - pred[slid], axis=1) < off[slid]
        if not better.any():
            break
        out[sel[slid][better]] = again[better]
    return out
