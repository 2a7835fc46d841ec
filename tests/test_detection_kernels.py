"""The detector's numba passes that replaced numpy or per-point code give exactly the old results.

Each test keeps a plain numpy (or per-point OpenCV) reference of what the pass computes and requires
bit-identical output on inputs that exercise every branch: the detections must not move when the code
only gets faster.
"""

from __future__ import annotations

import cv2
import numpy as np

from edgecal.detection.board_corners import _kinked_corners
from edgecal.detection.candidates import (
    _local_maxima,
    gradients,
    gradients_near,
    min_eigen_image,
)
from edgecal.detection.completion import _predict_from_dense, _ring_offsets, dense_labels
from edgecal.detection.grouping import CROSS_RATIO_EQUAL_STEPS, cross_ratio_strikes
from edgecal.detection.levels import Level
from edgecal.detection.subpixel import SEARCH_CRITERIA, refine_corners, subpixel_window


def _maxima_reference(lam: np.ndarray, thr: float, b: int = 2) -> tuple[np.ndarray, np.ndarray]:
    dil = cv2.dilate(lam, np.ones((5, 5), np.uint8))
    mask = (lam >= dil) & (lam > thr)
    mask[:b] = mask[-b:] = False
    mask[:, :b] = mask[:, -b:] = False
    ys, xs = np.nonzero(mask)
    return np.stack([xs, ys], axis=1).astype(np.float64), lam[ys, xs]


def test_local_maxima_match_the_dilation_reference() -> None:
    rng = np.random.default_rng(3)
    for shape in ((120, 170), (5, 9), (6, 6), (4, 30), (37, 8)):  # widths on and off whole 8-byte words
        lam = rng.random(shape).astype(np.float32)
        if shape[0] > 50:
            lam[40:44, 50:55] = 2.0  # a plateau: every pixel of it is a maximum
            lam[:, 3] = 3.0  # maxima near the border (kept 2 px in) and along a whole column
        for thr in (0.05, 0.5, 0.97, 1.5):  # from most pixels above to a few
            thr32 = float(np.float32(thr))
            for border in (2, 3):
                ref_pts, ref_resp = _maxima_reference(lam, thr32, border)
                pts, resp = _local_maxima(lam, thr32, border)
                assert np.array_equal(pts, ref_pts) and np.array_equal(resp, ref_resp)
                assert resp.dtype == np.float32


def _strikes_reference(pts: np.ndarray, labels: np.ndarray, tolerance: float) -> np.ndarray:
    strikes = np.zeros(len(pts), dtype=np.int64)
    for comp in np.unique(labels[:, 0]):
        if comp < 0:
            continue
        members = np.nonzero(labels[:, 0] == comp)[0]
        uv = labels[members, 1:] - labels[members, 1:].min(axis=0)
        index = np.full((uv[:, 1].max() + 1, uv[:, 0].max() + 1), -1, dtype=np.int64)
        index[uv[:, 1], uv[:, 0]] = members
        for lines in (index, index.T):
            for line in lines:
                for s in range(len(line) - 3):
                    run = line[s:s + 4]
                    if (run < 0).any():
                        continue
                    steps = np.hypot(*(pts[run[1:]] - pts[run[:-1]]).T)
                    x2, x3, x4 = steps[0], steps[0] + steps[1], steps[0] + steps[1] + steps[2]
                    with np.errstate(divide="ignore", invalid="ignore"):
                        cr = x3 * (x4 - x2) / ((x3 - x2) * x4)
                    if not abs(cr - CROSS_RATIO_EQUAL_STEPS) / CROSS_RATIO_EQUAL_STEPS <= tolerance:
                        strikes[run] += 1
    return strikes


def test_min_eigen_image_repeats_opencvs_box_sums_with_an_exact_root() -> None:
    # the numba pass's box sums are cv2.boxFilter's to the bit; only the root is the correctly rounded one,
    # where cv2.magnitude (IPP) is within 2 float32 ulp of it
    rng = np.random.default_rng(5)
    for shape in ((3, 3), (4, 7), (61, 97), (128, 160)):
        img = cv2.GaussianBlur((255 * rng.random(shape)).astype(np.float32), (5, 5), 1.0)
        gx, gy = gradients(img)
        a = cv2.boxFilter(cv2.multiply(gx, gx), -1, (3, 3), normalize=False)
        c = cv2.boxFilter(cv2.multiply(gy, gy), -1, (3, 3), normalize=False)
        b = cv2.boxFilter(cv2.multiply(gx, gy), -1, (3, 3), normalize=False)
        half = np.float32(0.5)
        d = a * half - c * half
        root = np.sqrt(d.astype(np.float64) ** 2 + b.astype(np.float64) ** 2).astype(np.float32)
        lam = min_eigen_image(gx, gy, 3)
        assert lam.dtype == np.float32 and np.array_equal(lam, (a * half + c * half) - root)
        opencv = cv2.subtract(cv2.addWeighted(a, 0.5, c, 0.5, 0.0), cv2.magnitude(d, b))
        assert np.abs(lam - opencv).max() <= 1e-5 * np.abs(opencv).max()


def test_gradients_near_points_are_the_whole_images_gradients_there() -> None:
    # discs at the borders and corners of the image too, where Sobel mirrors the image (BORDER_REFLECT_101)
    rng = np.random.default_rng(11)
    smooth = cv2.GaussianBlur((255 * rng.random((90, 130))).astype(np.float32), (5, 5), 1.0)
    pts = np.array([[0.0, 0.0], [129.6, 89.7], [0.4, 50.0], [64.2, 44.9], [120.0, 1.0], [64.0, 46.0]])
    reach = np.array([3.0, 5.5, 2.0, 9.0, 4.0, 0.5])
    gx, gy = gradients(smooth)
    near_x, near_y = gradients_near(smooth, pts, reach)
    yy, xx = np.mgrid[0:90, 0:130]
    inside = np.zeros(smooth.shape, bool)
    for (x, y), r in zip(pts, reach):
        inside |= np.hypot(xx - x, yy - y) <= r + 1.0  # what a probe of radius r reads (bilinear cells)
    scale = np.abs(gx).max()
    assert np.abs(near_x - gx)[inside].max() <= 1e-6 * scale and np.abs(near_y - gy)[inside].max() <= 1e-6 * scale
    # beyond each point's box (reach + 2 px each way) nothing is computed
    far = np.all(np.hypot(xx[..., None] - pts[:, 0], yy[..., None] - pts[:, 1]) > np.sqrt(2.0) * (reach + 3.0), axis=2)
    assert np.all(near_x[far] == 0.0) and np.all(near_y[far] == 0.0)


def test_a_level_gives_its_whole_gradients_once_made_else_the_discs_only() -> None:
    rng = np.random.default_rng(12)
    level = Level((255 * rng.random((120, 160))).astype(np.uint8), 2.0)
    pts, reach = np.array([[40.0, 50.0], [120.5, 60.5]]), np.array([6.0, 6.0])
    near_x, near_y = level.gradients_near(pts, reach)
    assert near_x[50, 40] != 0.0 and near_x[5, 5] == 0.0 and near_y[110, 150] == 0.0
    whole = gradients(level.smooth)[0]
    assert np.abs(near_x[44:57, 34:47] - whole[44:57, 34:47]).max() <= 1e-6 * np.abs(whole).max()
    # a later call's discs go into the same images, the earlier ones kept
    more_x, _more_y = level.gradients_near(np.array([[80.0, 20.0]]), np.array([5.0]))
    assert more_x is near_x and near_x[50, 40] != 0.0 and near_x[20, 80] != 0.0
    assert level.gx is not None  # (the whole images made)
    whole_x, whole_y = level.gradients_near(pts, reach)  # now: the level's own images
    assert whole_x is level.gx and whole_y is level.gy
    # discs covering most of a level: the whole images straight away
    fresh = Level(level.grey, 2.0)
    assert fresh.gradients_near(pts, np.array([60.0, 60.0]))[0] is fresh.gx


def test_cross_ratio_strikes_match_the_reference() -> None:
    rng = np.random.default_rng(5)
    u, v = np.meshgrid(np.arange(7), np.arange(5), indexing="ij")
    grid = np.stack([u.ravel(), v.ravel()], axis=1)
    pts = 30.0 * grid + rng.normal(0, 0.3, grid.shape)
    pts[8] += (6.0, -4.0)        # a corner far off its lines
    pts[20] = pts[19]            # two corners on one spot: a zero step
    labels = np.concatenate([np.zeros((len(grid), 1), np.int64), grid - 3], axis=1)
    labels[[3, 17]] = (-1, 0, 0)  # points not in a grid
    # a second component: one short row and one line of four
    extra = np.array([[500.0, 10.0], [530.0, 10.0], [560.0, 11.0], [590.0, 60.0], [620.0, 10.0]])
    pts = np.concatenate([pts, extra])
    labels = np.concatenate([labels, [[1, 0, 0], [1, 1, 0], [1, 2, 0], [1, 3, 0], [1, 0, 1]]])
    for tol in (0.01, 0.05, 0.3):
        assert np.array_equal(cross_ratio_strikes(pts, labels, tol), _strikes_reference(pts, labels, tol))


def _holes_reference(dense: np.ndarray, lo: np.ndarray, hl: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The numpy formulation _predict_from_dense replaced (batched normalised DLT per hole)."""
    span = np.array(dense.shape[:2])
    out_p = np.full((len(hl), 2), np.nan)
    out_s = np.full(len(hl), np.nan)
    todo = np.ones(len(hl), dtype=bool)
    probe = np.c_[np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0], [1.0, -1.0]]), np.ones(5)]
    for reach in (1, 2):
        off = _ring_offsets(reach)
        idx = np.nonzero(todo)[0]
        if len(idx) == 0:
            break
        lab = hl[idx, None, :] + off[None]
        iu, iv = lab[..., 0] - lo[0], lab[..., 1] - lo[1]
        inside = (iu >= 0) & (iv >= 0) & (iu < span[0]) & (iv < span[1])
        dst = np.where(inside[..., None], dense[np.clip(iu, 0, span[0] - 1), np.clip(iv, 0, span[1] - 1)], np.nan)
        valid = np.isfinite(dst).all(axis=2)
        src = np.broadcast_to(off[None].astype(np.float64), lab.shape)
        spread = (np.where(valid[..., None], src, np.inf).min(axis=1)
                  < np.where(valid[..., None], src, -np.inf).max(axis=1)).all(axis=1)
        usable = (valid.sum(axis=1) >= 4) & spread
        if not usable.any():
            continue
        b = np.nonzero(usable)[0]
        s_b, d_b, v_b = src[b], np.nan_to_num(dst[b]), valid[b]
        w = v_b.astype(np.float64)[..., None]
        n = np.maximum(w.sum(axis=1), 1.0)
        mean = (d_b * w).sum(axis=1) / n
        scale = np.sqrt(2.0) / np.maximum((np.linalg.norm(d_b - mean[:, None], axis=2) * w[..., 0]).sum(axis=1)
                                          / n[:, 0], 1e-9)
        d = (d_b - mean[:, None]) * scale[:, None, None]
        x, y = s_b[..., 0], s_b[..., 1]
        one, zero = np.ones_like(x), np.zeros_like(x)
        r1 = np.stack([x, y, one, zero, zero, zero, -d[..., 0] * x, -d[..., 0] * y, -d[..., 0]], axis=2)
        r2 = np.stack([zero, zero, zero, x, y, one, -d[..., 1] * x, -d[..., 1] * y, -d[..., 1]], axis=2)
        a = np.concatenate([r1, r2], axis=1) * np.concatenate([w, w], axis=1)
        h = np.linalg.svd(a)[2][:, -1].reshape(-1, 3, 3)
        t_inv = np.zeros_like(h)
        t_inv[:, 0, 0] = t_inv[:, 1, 1] = 1.0 / scale
        t_inv[:, 0, 2], t_inv[:, 1, 2] = mean[:, 0], mean[:, 1]
        t_inv[:, 2, 2] = 1.0
        q = np.einsum("bij,kj->bki", t_inv @ h, probe)
        with np.errstate(divide="ignore", invalid="ignore"):
            q = q[..., :2] / q[..., 2:3]
        out_p[idx[b]] = q[:, 0]
        out_s[idx[b]] = np.linalg.norm(q[:, 1:] - q[:, :1], axis=2).min(axis=1)
        todo[idx[b]] = False
    return out_p, out_s


def test_hole_predictions_match_the_numpy_dlt() -> None:
    """The batched kernels give the plain numpy DLT's predictions (its SVD's null vector; the kernels take
    A^T A's eigenvector, the same to ~1e-14)."""
    rng = np.random.default_rng(11)
    h_true = np.array([[31.0, 4.0, 200.0], [-3.0, 27.0, 150.0], [0.002, -0.001, 1.0]])
    grid = {}
    for u in range(-2, 6):
        for v in range(0, 6):
            p = h_true @ (u, v, 1.0)
            grid[(u, v)] = p[:2] / p[2] + rng.normal(0, 0.2, 2)
    for gone in [(0, 1), (1, 1), (3, 4), (5, 0), (5, 1), (-2, 5), (2, 2), (2, 3), (3, 2)]:
        del grid[gone]
    grid[(-2, 0)] = grid[(-2, 0)] + 1e-7  # a value with a full mantissa
    dense, lo = dense_labels(grid)
    holes = np.argwhere(~np.isfinite(dense[2:-2, 2:-2, 0])) + lo + 2
    got_p, got_s = _predict_from_dense(dense, lo, holes)
    ref_p, ref_s = _holes_reference(dense, lo, holes)
    assert np.isfinite(got_p).all()  # every hole here has a usable neighbourhood (some only the 5x5 one)
    assert np.abs(got_p - ref_p).max() < 1e-9 and np.abs(got_s - ref_s).max() < 1e-9


def test_refine_corners_refines_each_point_as_on_its_own() -> None:
    """One call over many points (sorted and batched by window size) gives each point what a call on it
    alone gives: the property completion's reuse of verified predictions rests on."""
    img = np.zeros((200, 260), np.uint8)
    for r in range(7):
        for c in range(9):
            if (r + c) % 2 == 0:
                img[10 + 25 * r:35 + 25 * r, 15 + 25 * c:40 + 25 * c] = 220
    smooth = cv2.GaussianBlur(img.astype(np.float32), (5, 5), 1.0)
    rng = np.random.default_rng(2)
    corners = np.array([[15 + 25 * c, 10 + 25 * r] for r in range(1, 7) for c in range(1, 9)], np.float64)
    pts = corners + rng.uniform(-1.5, 1.5, corners.shape)
    pts[3] = (1.0, 1.0)            # window outside the image: kept as it is
    pts[5] = (np.nan, 40.0)        # not finite: kept
    spacing = rng.choice([6.0, 9.0, 14.0, 25.0, 40.0], len(pts))
    spacing[7] = np.nan
    for criteria, max_move in ((SEARCH_CRITERIA, None), (SEARCH_CRITERIA, 0.3)):
        together = refine_corners(smooth, pts, spacing, max_move_px=max_move, criteria=criteria)
        for i in range(len(pts)):
            alone = refine_corners(smooth, pts[i:i + 1], spacing[i:i + 1], max_move_px=max_move, criteria=criteria)
            assert np.array_equal(together[i], alone[0], equal_nan=True)
        half = subpixel_window(np.where(np.isfinite(spacing), spacing, 6.0))
        one = np.array(pts[0:1], np.float32).reshape(-1, 1, 2)
        cv2.cornerSubPix(smooth, one, (int(half[0]), int(half[0])), (-1, -1), criteria)
        moved = float(np.hypot(*(one[0, 0] - pts[0].astype(np.float32))))
        limit = max_move if max_move is not None else max(1.5, half[0] / 2)
        assert np.array_equal(together[0], one[0, 0].astype(np.float64)) == (moved < limit)


def test_the_slide_screen_flags_a_slid_corner_not_a_lens_bend() -> None:
    """resettle_slid_corners' screen on a 9x6 grid of 30 px squares bent as a fisheye bends it (each line a
    smooth curve, 48-68 px deep over the grid): no corner flagged (second differences alone flagged them all);
    one corner slid 5 px along a row: it is flagged, and no corner off its row and column."""
    rows, cols, step = 6, 9, 30.0
    c, r = np.meshgrid(np.arange(cols, dtype=np.float64), np.arange(rows, dtype=np.float64))
    u, v = (c - 4.0) / 4.0, (r - 2.5) / 2.5
    dense = np.stack([100.0 + step * c + 40.0 * v ** 2 + 8.0 * v ** 4, 100.0 + step * r + 60.0 * u ** 2 + 8.0 * u ** 4],
                     axis=2)
    spacing = np.full((rows, cols), step)
    assert not _kinked_corners(dense, spacing).any()
    dense[3, 4, 0] += 5.0
    flagged = _kinked_corners(dense, spacing)
    assert flagged[3, 4] and all(r == 3 or c == 4 for r, c in np.argwhere(flagged).tolist())
