"""The saddle fit's shift by an uneven light field: read off the board's squares, predicted per corner.

A light field over the board (a lamp's fall-off, vignetting, a shadow's soft edge) multiplies the printed
pattern, so the image around a corner is not point-symmetric and the saddle fit (subpixel.saddle_refine)
moves off the corner, by the same amount and direction at neighbouring corners: a bias the board's
corners share, which averaging over them does not remove. It is predicted here from first principles
and the detector takes it off its corners (detector.add_covariances); corner_covariance keeps a share of
it as model error.

The light field. With a sensor black level b0 and any gamma, a pixel's value above the black level is
proportional to a power of the light, so a light field varying as exp(u . x) changes every pixel by
dI = (I - b0) (u . x) to first order (u: the gradient of log light, per px, including 1/gamma).
Diagonally opposite squares of a corner have the same colour, so the difference of the image at their
centres, (I+ - I-) / 2 = (I_sq - b0) (u . d), d half the diagonal between them, reads u along two
directions at each corner, once on the white and once on the black squares: over a board's corners one
least-squares fit gives u (affine over the board: vignetting bends it) and b0 u (hence b0, needed because
the black squares, close to b0, read the light far weaker than the white ones: taking b0 = 0 under-read
it by ~20 % on renders with a black level of 10).

The shift. The fit's linear terms (d, e) are its rows applied to the fit window; the light adds the
rows applied to dI over the window, m, and moves the saddle by -H^-1 m. Because the light multiplies the
scene before the optics and the detector smooth it, a Gaussian smoothing of sigma s^2 turns
(u . x) S(x) into (u . x) (G * S) + s^2 u . grad(G * S): dI = (u . x)(I - b0) + s^2 u . grad I on the
fit window I, s^2 the detector's and the fit's own smoothing (the optics' blur, unknown here, is left out:
it adds ~2 % on renders). Measured on bench/corner_noise.py's renders (80 views each) against exact truth,
the searched path's corners: uneven light (gradients of 40-70 % across the image, vignetting 0.3-0.6)
RMS error 0.042 -> 0.013 px; normal 0.019 -> 0.016, foreshortened 0.026 -> 0.023, hard 0.110 -> 0.107;
clean unchanged; what is left correlates with the prediction with a gain of 1.0-1.1.

Pure functions: the detector's smoothed image and the corners in, shifts out.
"""

from __future__ import annotations

import numpy as np

from edgecal.detection.subpixel import saddle_fit_setup

# Where the squares are read: at +-LIGHT_PROBE x (a +- b) from the corner (a, b its steps to the next
# column and row): about the squares' centres, as far from every edge (and its blur) as the board allows
# (0.25, half way, read perspective and blur as light on strongly foreshortened boards: the shift
# predicted there was 3x the real one; the mean of each square's four corners, only inside the grid, lost
# half the readings and was less accurate on every render set: hard 0.107 -> 0.115 px).
LIGHT_PROBE = 0.5
# Readings (two per corner) a board needs for a light field whose log gradient u is quadratic over it
# (14 unknowns: vignetting bends u across a board: an affine u was off by 7-11 % at the median under
# vignetting 0.6, 2 % with a linear gradient alone), affine (8) or uniform (4): fewer, and the board gets
# no shift.
MIN_READINGS_QUADRATIC = 48
MIN_READINGS_AFFINE = 24
MIN_READINGS_UNIFORM = 8
# A square this bright (grey levels, 8 bit) may be clipped: it does not follow the light.
SATURATED = 250.0
# Alternations of the black level and the light field's fit (each linear given the other; 5 settle b0 to
# a tenth of a grey level on renders).
BLACK_LEVEL_ITERATIONS = 5
# A reading of squares outside the grid is kept when it is within this many robust sigmas (1.4826 MAD of
# the inner readings' residuals) of the light fitted to the inner ones: on a board whose outer squares are
# cut short (0.45 of a square, then the background), they read the cut edge as a light gradient and moved
# the inner corners by up to 0.28 px.
REJECT_MADS = 4.0
# ... plus this (grey levels), so that on a noise-free image the light field's own curvature beyond the
# fitted terms (vignetting towards a board's corners: a few tenths) does not count as disagreement.
REJECT_FLOOR = 1.0
# A predicted shift beyond this (px) is outside the first-order model (a board misread, a hard shadow edge
# across a corner): that corner is not moved.
MAX_LIGHT_SHIFT_PX = 0.5


def fit_windows(smooth: np.ndarray, corners: np.ndarray, spacing: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The saddle fit's windows at each corner, as saddle_refine fits them (resampled at the corner, smoothed
    once more): (N, n, n) grey levels, n = 2 x the fit's half-width + 1; (N,) bool inside the image; the
    fit's pseudo-inverse (6, n^2); (N,) the extra smoothing sigma (px)."""
    fit, half, blur_half, blur = saddle_fit_setup(spacing)
    n_fit = 2 * half + 1
    r0 = half + blur_half
    corners = np.asarray(corners, dtype=np.float64).reshape(-1, 2)
    h, w = smooth.shape
    inside = (np.isfinite(corners).all(axis=1) & (corners[:, 0] >= r0 + 1) & (corners[:, 1] >= r0 + 1)
              & (corners[:, 0] <= w - r0 - 2) & (corners[:, 1] <= h - r0 - 2))
    xy = np.where(inside[:, None], corners, r0 + 1.0)
    x0 = np.floor(xy).astype(np.int64)
    f = xy - x0
    off = np.arange(-r0, r0 + 1)
    ys = x0[:, 1, None] + off[None]
    xs = x0[:, 0, None] + off[None]
    img = np.asarray(smooth, dtype=np.float64)
    fx, fy = f[:, 0, None, None], f[:, 1, None, None]
    top = img[ys[:, :, None], xs[:, None, :]] * (1 - fx) + img[ys[:, :, None], xs[:, None, :] + 1] * fx
    bottom = img[ys[:, :, None] + 1, xs[:, None, :]] * (1 - fx) + img[ys[:, :, None] + 1, xs[:, None, :] + 1] * fx
    patch = top * (1 - fy) + bottom * fy
    k = np.arange(-blur_half, blur_half + 1)
    kern = np.exp(-k[None] ** 2 / (2.0 * blur[:, None] ** 2))
    kern /= kern.sum(axis=1, keepdims=True)
    rows = sum(patch[:, :, j:j + n_fit] * kern[:, j, None, None] for j in range(len(k)))
    win = sum(rows[:, j:j + n_fit, :] * kern[:, j, None, None] for j in range(len(k)))
    return win, inside, fit, blur


def _bilinear(img: np.ndarray, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """img sampled at pts (M, 2) px, bilinear; and (M,) bool inside."""
    h, w = img.shape
    ok = np.isfinite(pts).all(axis=1) & (pts[:, 0] >= 0) & (pts[:, 1] >= 0) & (pts[:, 0] < w - 1) & (pts[:, 1] < h - 1)
    p = np.where(ok[:, None], pts, 0.0)
    i = np.floor(p).astype(np.int64)
    f = p - i
    v = ((img[i[:, 1], i[:, 0]] * (1 - f[:, 0]) + img[i[:, 1], i[:, 0] + 1] * f[:, 0]) * (1 - f[:, 1])
         + (img[i[:, 1] + 1, i[:, 0]] * (1 - f[:, 0]) + img[i[:, 1] + 1, i[:, 0] + 1] * f[:, 0]) * f[:, 1])
    return v, ok


def _fit_light(dd: np.ndarray, lv: np.ndarray, rhs: np.ndarray, tq: np.ndarray, darkest: float
               ) -> tuple[np.ndarray, float] | None:
    """One board's light field from its readings: (k, 2) coefficients of u over the terms tq (M, k) and
    the black level; None when the readings do not determine them. dd (M, 2) half diagonals, lv (M,) the
    squares' mean level, rhs (M,) half their difference.

    (I+ - I-) / 2 = (I_sq - b0) (u(q) . d), u(q) = sum_j terms_j(q) u_j: linear in u for a given b0 and in
    b0 for a given u. Started from b0 u(q) ~ b0 u0 (linear in both), then alternated."""
    k = tq.shape[1]
    design = np.concatenate([-dd] + [lv[:, None] * dd * tq[:, j, None] for j in range(k)], axis=1)
    sol, _res, rank, _sv = np.linalg.lstsq(design, rhs, rcond=None)
    if rank < design.shape[1] or not np.all(np.isfinite(sol)):
        return None
    coef = sol[2:].reshape(k, 2)
    black = float(sol[:2] @ coef[0] / (coef[0] @ coef[0])) if coef[0] @ coef[0] > 0 else 0.0
    for _ in range(BLACK_LEVEL_ITERATIONS):
        # a black level cannot lie below 0 or above the darkest squares
        black = float(np.clip(black, 0.0, darkest))
        design = np.concatenate([(lv - black)[:, None] * dd * tq[:, j, None] for j in range(k)], axis=1)
        sol, _res, rank, _sv = np.linalg.lstsq(design, rhs, rcond=None)
        if rank < design.shape[1]:
            break
        coef = sol.reshape(k, 2)
        ud = np.sum(dd * (tq @ coef), axis=1)
        if ud @ ud <= 0:
            break
        black = float((lv * ud - rhs) @ ud / (ud @ ud))
    return coef, float(np.clip(black, 0.0, darkest))


def _order(count: int) -> int:
    """How many terms of u over the board (1 uniform, 3 affine, 6 quadratic) ``count`` readings carry."""
    return 6 if count >= MIN_READINGS_QUADRATIC else 3 if count >= MIN_READINGS_AFFINE else 1


def board_light_field(smooth: np.ndarray, corners: np.ndarray, steps: np.ndarray, groups: np.ndarray,
                      inside: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The light field at each corner, fitted over its group's squares (see the module docstring).

    smooth: (H, W) the detector's smoothed image; corners (N, 2) px; steps (N, 2, 2) the board's local steps
    to the next column and row (corner_covariance.grid_steps; NaN where unknown: that corner is not read);
    groups (N,) int, the board of each corner; inside: (N, 2) bool, whether both squares of each of a
    corner's diagonal pairs lie inside the grid (inner_squares), when the grid is known. The squares are
    read at +-LIGHT_PROBE x (a +- b) from each corner; with ``inside``, the light is fitted to the readings
    inside the grid first and the others are kept where they agree with it (REJECT_MADS): the outer
    squares of a printed board may be cut short, and read as the board's edge or margin. Returns u (N, 2),
    the gradient of log light per px at each corner (0 where its board has too few readings), and b0 (N,),
    its board's black level (grey levels).
    """
    corners = np.asarray(corners, dtype=np.float64).reshape(-1, 2)
    steps = np.asarray(steps, dtype=np.float64).reshape(-1, 2, 2)
    n = len(corners)
    u = np.zeros((n, 2))
    b0 = np.zeros(n)
    img = np.asarray(smooth, dtype=np.float64)
    # Per corner and diagonal k: half the diagonal d between the two squares, their mean and half their
    # difference.
    d = np.stack([LIGHT_PROBE * (steps[:, 0] + steps[:, 1]), LIGHT_PROBE * (steps[:, 0] - steps[:, 1])], axis=1)
    plus, ok_p = _bilinear(img, (corners[:, None] + d).reshape(-1, 2))
    minus, ok_m = _bilinear(img, (corners[:, None] - d).reshape(-1, 2))
    level = (0.5 * (plus + minus)).reshape(n, 2)
    diff = (0.5 * (plus - minus)).reshape(n, 2)
    read = ((ok_p & ok_m & (plus < SATURATED) & (minus < SATURATED)).reshape(n, 2) & np.isfinite(d).all(axis=2))
    trusted = read if inside is None else read & np.asarray(inside, dtype=bool).reshape(n, 2)
    for g in np.unique(groups):
        members = np.nonzero(groups == g)[0]
        if trusted[members].sum() < MIN_READINGS_UNIFORM:
            continue
        xy = corners[members]
        centre = xy.mean(axis=0)
        radius = max(float(np.sqrt(np.mean(np.sum((xy - centre) ** 2, axis=1)))), 1.0)
        q = (xy - centre) / radius
        # u over the board: uniform, affine or quadratic in the corner's position, as the readings allow
        terms = np.stack([np.ones(len(q)), q[:, 0], q[:, 1], q[:, 0] ** 2, q[:, 0] * q[:, 1], q[:, 1] ** 2], axis=1)
        ci, ki = np.nonzero(read[members])
        dd, lv, rhs = d[members[ci], ki], level[members[ci], ki], diff[members[ci], ki]
        darkest = float(np.percentile(lv, 5))
        first = trusted[members][ci, ki]
        k = _order(int(first.sum()))
        fit = _fit_light(dd[first], lv[first], rhs[first], terms[ci[first], :k], darkest)
        if fit is None:
            continue
        if inside is not None and not first.all():
            coef, black = fit
            resid = rhs - (lv - black) * np.sum(dd * (terms[ci, :k] @ coef), axis=1)
            scale = 1.4826 * float(np.median(np.abs(resid[first]))) + REJECT_FLOOR
            keep = first | (np.abs(resid) < REJECT_MADS * scale)
            k = _order(int(keep.sum()))
            fit = _fit_light(dd[keep], lv[keep], rhs[keep], terms[ci[keep], :k], darkest) or fit
            k = fit[0].shape[0]
        coef, black = fit
        b0[members] = black
        u[members] = terms[:, :k] @ coef
    return u, b0


def inner_squares(ids: np.ndarray, groups: np.ndarray) -> np.ndarray:
    """(N, 2) bool: whether both squares of each diagonal pair around a corner (k = 0: towards (+col,
    +row) and (-col, -row); k = 1: towards (+col, -row) and (-col, +row)) lie inside its board's grid of
    found corners, ids (N, 2) (col, row), groups (N,) the board of each corner."""
    ids = np.asarray(ids, dtype=np.int64).reshape(-1, 2)
    out = np.zeros((len(ids), 2), dtype=bool)
    for g in np.unique(groups):
        members = np.nonzero(groups == g)[0]
        have = {tuple(i) for i in ids[members]}
        for m in members:
            c, r = ids[m]
            for k, (dc, dr) in enumerate(((1, 1), (1, -1))):
                out[m, k] = all((c + sc * x, r + sc * y) in have for sc in (1, -1)
                                for x, y in ((dc, 0), (0, dr), (dc, dr)))
    return out


def saddle_light_shift(smooth: np.ndarray, smoothing_sigma: float, corners: np.ndarray, spacing: np.ndarray,
                       steps: np.ndarray, groups: np.ndarray, ids: np.ndarray | None = None) -> np.ndarray:
    """How far (N, 2) px the light field moved the saddle fit's corners (the bias: the corners less it are
    closer to the truth); 0 where the fit is no saddle, the window leaves the image, the board has too
    few readings or the shift exceeds MAX_LIGHT_SHIFT_PX.

    smooth: (H, W) float32 the detector's smoothed image (smoothing_sigma px) the corners were refined on;
    corners (N, 2) px; spacing (N,) the square size each corner's fit window was made for; steps (N, 2, 2)
    and groups (N,) as board_light_field; ids (N, 2) the corners' (col, row) on their board, when known:
    the squares outside the grid then count only where they agree with those inside (inner_squares).
    """
    corners = np.asarray(corners, dtype=np.float64).reshape(-1, 2)
    n = len(corners)
    if n == 0:
        return np.zeros((0, 2))
    groups = np.asarray(groups, dtype=np.int64).reshape(n)
    u, b0 = board_light_field(smooth, corners, steps, groups, None if ids is None else inner_squares(ids, groups))
    win, inside, fit, blur = fit_windows(smooth, corners, np.asarray(spacing, dtype=np.float64).reshape(n))
    n_fit = win.shape[1]
    half = n_fit // 2
    oy, ox = np.mgrid[-half:half + 1, -half:half + 1].astype(np.float64)
    gy, gx = np.gradient(win, axis=(1, 2))
    s2 = (smoothing_sigma ** 2 + blur ** 2)[:, None, None]
    ux, uy = u[:, 0, None, None], u[:, 1, None, None]
    dwin = (ux * ox + uy * oy) * (win - b0[:, None, None]) + s2 * (ux * gx + uy * gy)
    c = win.reshape(n, -1) @ fit[:3].T
    m = dwin.reshape(n, -1) @ fit[3:5].T
    hxx, hxy, hyy = 2.0 * c[:, 0], c[:, 1], 2.0 * c[:, 2]
    det = hxx * hyy - hxy * hxy
    saddle = inside & (det < 0)
    safe = np.where(saddle, det, -1.0)
    # -H^-1 m
    shift = -np.stack([(hyy * m[:, 0] - hxy * m[:, 1]) / safe, (hxx * m[:, 1] - hxy * m[:, 0]) / safe], axis=1)
    keep = saddle & np.isfinite(shift).all(axis=1) & (np.hypot(shift[:, 0], shift[:, 1]) <= MAX_LIGHT_SHIFT_PX)
    shift[~keep] = 0.0
    return shift
