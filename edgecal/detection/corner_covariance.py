"""How well each refined corner is known: a 2x2 covariance per corner, from the image around it.

The refinement (cv2.cornerSubPix, edgecal.detection.subpixel) solves the gradient-orthogonality equations
sum_i w_i g_i g_i^T (q - p_i) = 0 over its window (w_i = exp(-|p_i - q|^2 / hw^2), cornerSubPix's weights).
Perturbing the gradients by image noise and linearising gives the sandwich

    Sigma_noise = A^-1 B A^-1 * sigma_g^2,   A = sum w g g^T,   B = sum w^2 g g^T |p - q|^2,

with sigma_g the noise of one gradient sample of the smoothed image (from the image noise and the
smoothing). It follows contrast (g scales with it), blur (flatter gradients, a wider A^-1) and
foreshortening (two edges close to parallel: A nearly singular along their bisector) by itself.

What noise does not explain is the bias of a corner that is not an ideal X-junction: an uneven light
field adds a gradient that does not point at the corner, perspective and lens curvature break its point
symmetry, pixels and quantisation limit a clean image. Those are widened in by a model-error term,
isotropic in the shape of A^-1 (so it grows along the weak direction of a foreshortened corner), whose
size comes from what the window itself shows: the share of the gradient energy that does not point at the
corner (the misfit of the gradient-orthogonality model), the mean gradient over the window relative to the
contrast (a light field: an ideal X-junction's gradients cancel over a symmetric window), and a floor.
The constants were fitted on edgecal.synth renders with exact truth (bench/corner_noise.py measures the
normalised error e^T Sigma^-1 e, 2 on average for a consistent 2-D covariance).

A covariance that is not positive definite or not finite (a flat or saturated window, a corner at the
image border, a line instead of a corner) marks that corner unusable, with the reason.

Pure functions: the smoothed image and the corners in, covariances out; one numba call per frame over all
corners.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from edgecal.detection.subpixel import nearest_spacing, subpixel_window

# Columns of the per-corner window statistics returned by window_statistics.
W_AXX, W_AXY, W_AYY = 0, 1, 2          # A = sum w g g^T (grey levels^2 per pixel^2)
W_BXX, W_BXY, W_BYY = 3, 4, 5          # B = sum w^2 g g^T |p - q|^2
W_MX, W_MY = 6, 7                      # weighted mean gradient over the window
W_CONTRAST = 8                         # weighted mean above the window mean minus below it (grey levels)
W_MISFIT = 9                           # sum w (g . r)^2 / sum w |g|^2 |r|^2 (0 for an ideal X-junction)
W_INSIDE = 10                          # 1 when the window lies inside the image
N_STATS = 11

# Reasons a corner is unusable (Detection.unusable); the text is part of detect's JSON.
REASON_BORDER = "refinement window leaves the image"
REASON_FLAT = "no gradient in the refinement window (flat or saturated)"
REASON_DEGENERATE = "covariance not positive definite (a line or an edge, not a corner)"


# Model error (px, 1 sigma per axis, in the shape of A^-1): a floor every corner has (pixel sampling,
# quantisation, the renderer's and the lens' small departures from an ideal X-junction) and the gain on the
# window's asymmetry |mean gradient| / contrast x half-width (an uneven light field, perspective across the
# window, neighbouring structure: a light gradient eps per pixel biases the saddle by about
# eps x (mean level / contrast) x edge width x half-width). Fitted by maximum likelihood on 400 edgecal.synth
# renders of clean, normal, hard, uneven-light and strongly foreshortened planar views (then the gain
# lowered from 1.35 so that the uneven-light set, whose error is a bias along one direction, is not
# over-covered), with the noise term taken as it is: its Monte-Carlo check (noise-only repeats of one
# render) needs no factor, normalised error 1.9-2.2 (2.8 at 2 px blur).
MODEL_FLOOR_PX = 0.01
ASYMMETRY_GAIN = 1.2
# pyrDown's 5x5 binomial passes 0.273 of white noise (as in the detector).
_PYRDOWN_NOISE_GAIN = 0.273
# Largest condition number of a usable covariance: beyond it the corner is a line, not a point.
MAX_CONDITION = 1e6


def covariance_noise_sigma(grey: np.ndarray, half_noise: float | None = None) -> float:
    """The image noise (grey levels, 1 sigma) that moves the corners.

    The detector's estimate (candidates.estimate_noise_sigma) looks at pixel-to-pixel differences, which
    JPEG compression and demosaicing remove while the noise at the scale of a corner window stays; the
    same estimate at half resolution sees that, so the larger of the two is taken. Quantisation (1/12
    grey level^2) is added: a noise-free 8-bit image still has it. ``half_noise``: that half-resolution
    estimate (estimate_noise_sigma of cv2.pyrDown(grey)) when the caller already has it (the detector's
    pyramid does): a second pyrDown of a 1280x800 image would cost more than the covariances themselves.
    """
    import cv2

    from edgecal.detection.candidates import estimate_noise_sigma

    # Every 6th pixel at full resolution: tens of thousands of samples, a few times cheaper.
    sigma = estimate_noise_sigma(grey, stride=6)
    if half_noise is None and min(grey.shape) >= 16:
        half_noise = estimate_noise_sigma(cv2.pyrDown(grey))
    if half_noise is not None:
        sigma = max(sigma, half_noise / _PYRDOWN_NOISE_GAIN)
    return float(np.sqrt(sigma * sigma + 1.0 / 12.0))


@njit(cache=True, nogil=True)
def _smooth_energy(v0: np.ndarray, v1: np.ndarray, p: int, g: np.ndarray, tmp0: np.ndarray, tmp1: np.ndarray,
                   u0: np.ndarray, u1: np.ndarray) -> tuple[float, float, float]:
    """Sum of u u^T over the plane for u = (g (x) g) scattered over v[:p, :p] (full correlation; tmp, u:
    work arrays of at least (p, p + 2r) and (p + 2r, p + 2r))."""
    k = g.shape[0]
    q = p + k - 1
    for a in range(p):
        for b in range(q):
            tmp0[a, b] = 0.0
            tmp1[a, b] = 0.0
        for b in range(p):
            x0 = v0[a, b]
            x1 = v1[a, b]
            for t in range(k):
                tmp0[a, b + t] += x0 * g[t]
                tmp1[a, b + t] += x1 * g[t]
    for a in range(q):
        for b in range(q):
            u0[a, b] = 0.0
            u1[a, b] = 0.0
    for a in range(p):
        for t in range(k):
            gt = g[t]
            for b in range(q):
                u0[a + t, b] += tmp0[a, b] * gt
                u1[a + t, b] += tmp1[a, b] * gt
    sxx = sxy = syy = 0.0
    for a in range(q):
        for b in range(q):
            sxx += u0[a, b] * u0[a, b]
            sxy += u0[a, b] * u1[a, b]
            syy += u1[a, b] * u1[a, b]
    return sxx, sxy, syy


@njit(cache=True, nogil=True)
def window_statistics(smooth: np.ndarray, corners: np.ndarray, half: np.ndarray, gauss: np.ndarray) -> np.ndarray:
    """Statistics of each corner's refinement window (N, N_STATS), columns W_*.

    smooth: (H, W) float32, the image the refinement ran on; corners: (N, 2) float64 pixels; half: (N,)
    int64 window half-widths (subpixel_window); gauss: the detector's 1-D smoothing kernel
    (noise_kernel), through which raw pixel noise reaches the window's gradients. The window
    is resampled at the corner's sub-pixel position (as cornerSubPix does); gradients are central
    differences in grey levels per pixel.

    B is the covariance of sum_i M_i dg_i (M_i = w_i (g_i r_i^T + (g_i . r_i) I), r_i = p_i - q, dg_i
    the gradient noise) for unit white noise in the raw image, carried exactly through the smoothing and
    the differences: the smoothing correlates neighbouring gradients, which a per-sample variance misses.
    Both gradient kernels are the Gaussian times a central difference, so sum_i M_i dg_i is the Gaussian
    scattered over v = (central differences scattered over M's columns): one smoothing per component.
    """
    h, w = smooth.shape
    n = corners.shape[0]
    out = np.zeros((n, N_STATS))
    hmax = 1
    for i in range(n):
        hmax = max(hmax, half[i])
    k = gauss.shape[0]
    pm = 2 * hmax + 1
    patch = np.empty((pm + 2, pm + 2))
    wts = np.empty((pm, pm))
    ex = np.empty(pm)
    v0 = np.empty((pm + 2, pm + 2))
    v1 = np.empty((pm + 2, pm + 2))
    tmp0 = np.empty((pm + 2, pm + 1 + k))
    tmp1 = np.empty((pm + 2, pm + 1 + k))
    u0 = np.empty((pm + 1 + k, pm + 1 + k))
    u1 = np.empty((pm + 1 + k, pm + 1 + k))
    for i in range(n):
        qx = corners[i, 0]
        qy = corners[i, 1]
        hw = half[i]
        if not (math.isfinite(qx) and math.isfinite(qy)) or hw < 1:
            continue
        if qx - hw - 1 < 0 or qy - hw - 1 < 0 or qx + hw + 2 > w - 1 or qy + hw + 2 > h - 1:
            continue
        out[i, W_INSIDE] = 1.0
        m = 2 * hw + 3
        p = 2 * hw + 1
        # One bilinear resampling at the sub-pixel position: the same fractions for every pixel.
        x0 = int(math.floor(qx))
        y0 = int(math.floor(qy))
        fx = qx - x0
        fy = qy - y0
        for a in range(m):
            yy = y0 + a - hw - 1
            for b in range(m):
                xx = x0 + b - hw - 1
                patch[a, b] = ((smooth[yy, xx] * (1.0 - fx) + smooth[yy, xx + 1] * fx) * (1.0 - fy)
                               + (smooth[yy + 1, xx] * (1.0 - fx) + smooth[yy + 1, xx + 1] * fx) * fy)
        axx = axy = ayy = mx = my = sw = 0.0
        mean = 0.0
        fit_num = fit_den = 0.0
        inv = 1.0 / (hw * hw)
        for a in range(p):
            ex[a] = math.exp(-float((a - hw) * (a - hw)) * inv)     # cornerSubPix's weights are separable
        for a in range(p + 2):
            for b in range(p + 2):
                v0[a, b] = 0.0
                v1[a, b] = 0.0
        for a in range(p):
            dy = a - hw
            for b in range(p):
                dx = b - hw
                r2 = float(dx * dx + dy * dy)
                wt = ex[a] * ex[b]
                gx = 0.5 * (patch[a + 1, b + 2] - patch[a + 1, b])
                gy = 0.5 * (patch[a + 2, b + 1] - patch[a, b + 1])
                wts[a, b] = wt
                axx += wt * gx * gx
                axy += wt * gx * gy
                ayy += wt * gy * gy
                gr = gx * dx + gy * dy
                # q solves sum w g g^T (q - p) = 0; the sign of r drops out of B. M's columns go through
                # the central differences (the same kernel (-1/2, 0, 1/2) along x and along y) into v.
                m00 = wt * (gx * dx + gr)
                m01 = wt * gx * dy
                m10 = wt * gy * dx
                m11 = wt * (gy * dy + gr)
                v0[a + 1, b] -= 0.5 * m00
                v0[a + 1, b + 2] += 0.5 * m00
                v0[a, b + 1] -= 0.5 * m01
                v0[a + 2, b + 1] += 0.5 * m01
                v1[a + 1, b] -= 0.5 * m10
                v1[a + 1, b + 2] += 0.5 * m10
                v1[a, b + 1] -= 0.5 * m11
                v1[a + 2, b + 1] += 0.5 * m11
                mx += wt * gx
                my += wt * gy
                sw += wt
                mean += wt * patch[a + 1, b + 1]
                fit_num += wt * gr * gr
                fit_den += wt * (gx * gx + gy * gy) * r2
        mean /= sw
        hi = lo = whi = wlo = 0.0
        for a in range(p):
            for b in range(p):
                v = patch[a + 1, b + 1]
                if v >= mean:
                    hi += wts[a, b] * v
                    whi += wts[a, b]
                else:
                    lo += wts[a, b] * v
                    wlo += wts[a, b]
        bxx, bxy, byy = _smooth_energy(v0, v1, p + 2, gauss, tmp0, tmp1, u0, u1)
        out[i, W_AXX] = axx
        out[i, W_AXY] = axy
        out[i, W_AYY] = ayy
        out[i, W_BXX] = bxx
        out[i, W_BXY] = bxy
        out[i, W_BYY] = byy
        out[i, W_MX] = mx / sw
        out[i, W_MY] = my / sw
        out[i, W_CONTRAST] = (hi / whi if whi > 0 else mean) - (lo / wlo if wlo > 0 else mean)
        out[i, W_MISFIT] = fit_num / fit_den if fit_den > 0 else 1.0
    return out


def noise_kernel(smoothing_sigma: float) -> np.ndarray:
    """The detector's 1-D Gaussian (candidates.smooth_image), float64: how one raw pixel's noise reaches the
    smoothed image."""
    import cv2

    ksize = 2 * int(np.ceil(2.5 * smoothing_sigma)) + 1
    return cv2.getGaussianKernel(ksize, smoothing_sigma, cv2.CV_64F).ravel()


def corner_covariance(grey: np.ndarray, smooth: np.ndarray, smoothing_sigma: float, corners: np.ndarray,
                      spacing: np.ndarray | None = None, noise_sigma: float | None = None
                      ) -> tuple[np.ndarray, list[str]]:
    """2x2 covariance (px^2, OpenCV pixel axes) of each refined corner, and why a corner is unusable.

    grey: (H, W) uint8, the image; smooth: the detector's smoothed float32 image of it (candidates.smooth_image
    with ``smoothing_sigma``) on which the corners were refined; corners: (N, 2) pixels; spacing: (N,)
    the local square size the refinement window came from (default: nearest_spacing of the corners).
    noise_sigma: covariance_noise_sigma of the whole image, when grey is a window of it or the caller has it
    (default: measured on grey). Returns (N, 2, 2) covariances, NaN for an unusable corner, and
    (N,) reasons ("" for a usable one).
    """
    corners = np.ascontiguousarray(np.asarray(corners, dtype=np.float64).reshape(-1, 2))
    n = len(corners)
    if n == 0:
        return np.zeros((0, 2, 2)), []
    if spacing is None:
        spacing = nearest_spacing(corners)
    half = subpixel_window(spacing)
    st = window_statistics(np.ascontiguousarray(smooth, dtype=np.float32), corners, half,
                           noise_kernel(smoothing_sigma))
    noise2 = (covariance_noise_sigma(grey) if noise_sigma is None else noise_sigma) ** 2
    a = st[:, W_AXX] * st[:, W_AYY] - st[:, W_AXY] ** 2
    tr = st[:, W_AXX] + st[:, W_AYY]
    ok = (st[:, W_INSIDE] > 0) & (tr > 0) & (a > tr * tr / MAX_CONDITION)
    det = np.where(ok, a, 1.0)
    # A^-1 for every corner at once.
    ai = (np.stack([st[:, W_AYY], -st[:, W_AXY], -st[:, W_AXY], st[:, W_AXX]], axis=1).reshape(-1, 2, 2)
          / det[:, None, None])
    b = np.stack([st[:, W_BXX], st[:, W_BXY], st[:, W_BXY], st[:, W_BYY]], axis=1).reshape(-1, 2, 2)
    cov_noise = noise2 * ai @ b @ ai
    contrast = np.maximum(st[:, W_CONTRAST], 1e-6)
    asymmetry = np.hypot(st[:, W_MX], st[:, W_MY]) / contrast * half
    model2 = MODEL_FLOOR_PX ** 2 + (ASYMMETRY_GAIN * asymmetry) ** 2
    # The model error takes A^-1's shape, scaled so that an isotropic corner gets model2 per axis.
    cov = cov_noise + (model2 * 0.5 * tr)[:, None, None] * ai
    cov = 0.5 * (cov + np.transpose(cov, (0, 2, 1)))
    ev_min = 0.5 * (cov[:, 0, 0] + cov[:, 1, 1]) - np.hypot(0.5 * (cov[:, 0, 0] - cov[:, 1, 1]), cov[:, 0, 1])
    finite = np.isfinite(cov).all(axis=(1, 2))
    inside = st[:, W_INSIDE] > 0
    reasons = np.select([~inside, tr <= 0, ~(ok & finite & (ev_min > 0))],
                        [REASON_BORDER, REASON_FLAT, REASON_DEGENERATE], default="")
    cov[reasons != ""] = np.nan
    return cov, reasons.tolist()
