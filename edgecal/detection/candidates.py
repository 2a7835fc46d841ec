"""Step 1: image preparation and minimum-eigenvalue (Shi-Tomasi / "Lucas-Kanade") candidates."""

from __future__ import annotations

import math
from functools import lru_cache

import cv2
import numpy as np
from numba import njit


def smoothing_sigma(noise_sigma: float) -> float:
    """Gaussian sigma (px) for a given image noise: 0.8 px on clean images, up to 2 px on very noisy ones.

    More smoothing would merge the corners of the smallest (8 px) squares.
    """
    # (min/max: np.clip's value, NaN too, without its call overhead on a scalar)
    return float(min(max(0.8 + 0.06 * noise_sigma, 0.8), 2.0))


def smooth_image(grey: np.ndarray, sigma: float = 0.8) -> np.ndarray:
    """The float32 image the detector samples: a Gaussian keeps sensor noise out of the gradients, and
    blurring does not move a corner's saddle point. ``grey``: any depth (uint8 images, float noise)."""
    ksize = 2 * int(np.ceil(2.5 * sigma)) + 1
    # GaussianBlur's kernel and border, straight into float32: sepFilter2D reads a uint8 image as it is
    # (GaussianBlur needs a float copy first and filters it 3-4x slower); equal to GaussianBlur to 1e-4 grey
    # levels on uint8 (float rounding: the corners to ~1e-6 px), to the bit on float32
    kernel = cv2.getGaussianKernel(ksize, sigma, cv2.CV_32F)
    return cv2.sepFilter2D(grey, cv2.CV_32F, kernel, kernel, borderType=cv2.BORDER_DEFAULT)


def gradients(smooth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """x and y gradients of the smoothed image, grey levels per pixel (OpenCV Sobel / 8)."""
    gx = cv2.Sobel(smooth, cv2.CV_32F, 1, 0, ksize=3, scale=0.125)
    gy = cv2.Sobel(smooth, cv2.CV_32F, 0, 1, ksize=3, scale=0.125)
    return gx, gy


def gradients_near(smooth: np.ndarray, pts: np.ndarray, reach: np.ndarray,
                   out: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """gradients() only within ``reach`` (M,) px (and a pixel more) of each point (M, 2) x, y; zero elsewhere.
    ``out``: float32 x/y images of smooth's shape to write into (zeros, or an earlier call's: its discs stay).

    For a level whose gradient images are only sampled by probes round a few points (a window that refines
    a board: its corners' quality, completion's predictions beyond it; reach = probe.probe_reach): 2-3x
    cheaper than the whole images' Sobels (~0.8 ms at 1280x960) while the discs cover up to ~40 % of the
    level. Equal to gradients() to float32 rounding.
    """
    if out is None:
        gx = np.zeros(smooth.shape, np.float32)  # (numpy's zeros: pages untouched outside the discs stay unmapped)
        gy = np.zeros(smooth.shape, np.float32)
    else:
        gx, gy = out
    _sobel_boxes(np.ascontiguousarray(smooth, np.float32), np.ascontiguousarray(pts, np.float64),
                 np.ascontiguousarray(reach, np.float64), gx, gy)
    return gx, gy


@njit(cache=True, nogil=True, inline="always")
def _reflect_101(i: int, n: int) -> int:
    """Index i of a line of n pixels mirrored at its ends without repeating them (cv2.BORDER_REFLECT_101)."""
    if i < 0:
        return -i if n > 1 else 0
    if i >= n:
        return 2 * n - 2 - i if n > 1 else 0
    return i


@njit(cache=True, nogil=True, inline="always")
def _sobel_at(up: np.ndarray, mid: np.ndarray, down: np.ndarray, left: int, centre: int, right: int
              ) -> tuple[float, float]:
    """The 3x3 Sobel / 8 (x, y) at column ``centre`` of three rows, from its ``left`` and ``right`` columns."""
    two = np.float32(2.0)
    eighth = np.float32(0.125)
    gx = ((up[right] - up[left]) + two * (mid[right] - mid[left]) + (down[right] - down[left])) * eighth
    gy = ((down[left] + two * down[centre] + down[right]) - (up[left] + two * up[centre] + up[right])) * eighth
    return gx, gy


@njit(cache=True, nogil=True)
def _sobel_boxes(smooth: np.ndarray, pts: np.ndarray, reach: np.ndarray, gx: np.ndarray, gy: np.ndarray) -> None:
    """gradients_near's kernel: the 3x3 Sobel / 8 of ``smooth`` into gx, gy over each point's box (boxes that
    overlap are computed again: the same values). Pixels inside the image by a pixel take a loop the
    compiler vectorises; the image's outermost ones mirror it as cv2.BORDER_REFLECT_101 does."""
    h, w = smooth.shape
    one = np.uint64(1)
    for i in range(pts.shape[0]):
        r = reach[i] + 1.0
        x0 = max(0, int(math.floor(pts[i, 0] - r)))
        x1 = min(w - 1, int(math.floor(pts[i, 0] + r)) + 1)
        y0 = max(0, int(math.floor(pts[i, 1] - r)))
        y1 = min(h - 1, int(math.floor(pts[i, 1] + r)) + 1)
        a = max(x0, 1)
        b = min(x1, w - 2)
        for y in range(y0, y1 + 1):
            up = smooth[_reflect_101(y - 1, h)]
            mid = smooth[y]
            down = smooth[_reflect_101(y + 1, h)]
            # unsigned indices: no check for negative ones, so the loop is vectorised
            for j in range(np.uint64(a), np.uint64(b + 1)):
                gx[y, j], gy[y, j] = _sobel_at(up, mid, down, j - one, j, j + one)
            for x in (x0, x1):  # the image's first or last column (or a box that is only that)
                if x < a or x > b:
                    gx[y, x], gy[y, x] = _sobel_at(up, mid, down, _reflect_101(x - 1, w), x, _reflect_101(x + 1, w))


def prepare_image(grey: np.ndarray, sigma: float = 0.8) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Smoothed float32 image and its x/y gradients (see smooth_image and gradients)."""
    smooth = smooth_image(grey, sigma)
    return (smooth, *gradients(smooth))


def min_eigen_image(gx: np.ndarray, gy: np.ndarray, block_size: int) -> np.ndarray:
    """Minimum eigenvalue of the box-summed structure tensor at every pixel (Shi-Tomasi response).

    lambda_min = (a + c) / 2 - sqrt(((a - c) / 2)^2 + b^2) for the tensor [[a, b], [b, c]]. The 3x3 window
    (the detector's) is one numba pass over the rows (_min_eigen_3x3); other windows use OpenCV's image
    arithmetic.
    """
    if block_size == 3 and min(gx.shape) >= 3:
        return _min_eigen_3x3(np.ascontiguousarray(gx, np.float32), np.ascontiguousarray(gy, np.float32))
    k = (block_size, block_size)
    a = cv2.boxFilter(cv2.multiply(gx, gx), -1, k, normalize=False)
    c = cv2.boxFilter(cv2.multiply(gy, gy), -1, k, normalize=False)
    b = cv2.boxFilter(cv2.multiply(gx, gy), -1, k, normalize=False)
    root = cv2.magnitude(cv2.addWeighted(a, 0.5, c, -0.5, 0.0), b)
    return cv2.subtract(cv2.addWeighted(a, 0.5, c, 0.5, 0.0), root)


@njit(cache=True, nogil=True, inline="always")
def _box_rows_3(gx_row: np.ndarray, gy_row: np.ndarray, prod: np.ndarray, ha: np.ndarray, hc: np.ndarray,
                hb: np.ndarray) -> None:
    """The three products of one gradient row and their 3-wide horizontal sums (float64) into ha, hc, hb, in
    cv2.boxFilter's order: ((left + centre) + right), the border mirrored without repeating the edge pixel.
    prod: (3, w + 2) float32 scratch, the products with their mirrored ends (a loop without branches)."""
    w = gx_row.shape[0]
    for x in range(w):
        prod[0, x + 1] = gx_row[x] * gx_row[x]
        prod[1, x + 1] = gy_row[x] * gy_row[x]
        prod[2, x + 1] = gx_row[x] * gy_row[x]
    for q in range(3):
        prod[q, 0] = prod[q, 2]
        prod[q, w + 1] = prod[q, w - 1]
    pa = prod[0]
    pc = prod[1]
    pb = prod[2]
    for x in range(w):
        ha[x] = (np.float64(pa[x]) + np.float64(pa[x + 1])) + np.float64(pa[x + 2])
        hc[x] = (np.float64(pc[x]) + np.float64(pc[x + 1])) + np.float64(pc[x + 2])
        hb[x] = (np.float64(pb[x]) + np.float64(pb[x + 1])) + np.float64(pb[x + 2])


@njit(cache=True, nogil=True)
def _min_eigen_3x3(gx: np.ndarray, gy: np.ndarray) -> np.ndarray:
    """min_eigen_image for the 3x3 window, row by row (gx, gy float32, at least 3x3).

    The products, the box sums and the eigenvalue of one row are made while its rows are in cache, where
    OpenCV's eleven whole-image operations each read and write the image (~8 ms at 1280x800, this ~2 ms).
    The box sums repeat cv2.boxFilter's arithmetic exactly (float64 horizontal sums, a float64 running
    vertical sum, rounded to float32), and so do the (a +- c) / 2; the root is the correctly rounded
    sqrt(d^2 + b^2), where cv2.magnitude's (IPP's) is within 2 float32 ulp of it.
    """
    h, w = gx.shape
    lam = np.empty((h, w), np.float32)
    prod = np.empty((3, w + 2), np.float32)
    # horizontal sums of the last three rows (ring indexed by row + 1 modulo 3) and the running vertical sums
    ha = np.empty((3, w))
    hc = np.empty((3, w))
    hb = np.empty((3, w))
    sa = np.zeros(w)
    sc = np.zeros(w)
    sb = np.zeros(w)
    half = np.float32(0.5)
    for k in range(-1, h + 1):
        src = k if k >= 0 else -k  # mirrored rows -1 -> 1, h -> h - 2
        if src >= h:
            src = 2 * h - 2 - src
        slot = (k + 1) % 3
        _box_rows_3(gx[src], gy[src], prod, ha[slot], hc[slot], hb[slot])
        if k < 1:  # the running sum starts with the rows above the first output row
            for x in range(w):
                sa[x] += ha[slot, x]
                sc[x] += hc[slot, x]
                sb[x] += hb[slot, x]
            continue
        old = (k - 1) % 3  # row k - 2, leaving the window
        out = lam[k - 1]
        for x in range(w):
            a0 = sa[x] + ha[slot, x]
            c0 = sc[x] + hc[slot, x]
            b0 = sb[x] + hb[slot, x]
            sa[x] = a0 - ha[old, x]
            sc[x] = c0 - hc[old, x]
            sb[x] = b0 - hb[old, x]
            a = np.float32(a0)
            c = np.float32(c0)
            b = np.float32(b0)
            d = a * half - c * half
            root = np.float32(math.sqrt(np.float64(d) * np.float64(d) + np.float64(b) * np.float64(b)))
            out[x] = (a * half + c * half) - root
    return lam


def _local_maxima(lam: np.ndarray, thr: float, border: int) -> tuple[np.ndarray, np.ndarray]:
    """5x5 local maxima of ``lam`` above ``thr`` (float32 value), away from the border (at least 2 px): (points
    (M, 2) x, y; responses), in row-major order. A pixel is kept when nothing in its 5x5 neighbourhood is
    larger (cv2.dilate's maximum): a plateau gives several points a pixel apart; the detector's
    de-duplication keeps one."""
    return _maxima_5x5(np.ascontiguousarray(lam, np.float32), thr, border)


@njit(cache=True, nogil=True)
def _maxima_5x5(lam: np.ndarray, thr: float, border: int) -> tuple[np.ndarray, np.ndarray]:
    """_local_maxima of a C-contiguous float32 ``lam``, in one pass over its rows.

    The 5x5 maximum is separable: each row's 5-wide maxima go into a ring of the last five rows, whose
    column-wise maximum a row's pixels are compared with, in loops the compiler vectorises (no index may
    be negative: numba's wrap-around check keeps a loop scalar). The few pixels that pass are collected
    eight flags at a time. ~3x faster than OpenCV's dilation and a comparison pass, and than looking at
    the neighbourhood of each pixel above the threshold (any share of them: noisy images have half).
    """
    h, w = lam.shape
    b = max(border, 2)
    # room for every pixel (only the maxima's entries are written): no growing inside the loop, which
    # numba compiles into a loop several times slower
    xs = np.empty(h * w + 1, np.int64)
    ys = np.empty(h * w + 1, np.int64)
    n = 0
    if h - b <= b or w - b <= b:
        return _gathered(lam, xs, ys, n)
    ring = np.empty((5, w), np.float32)  # row y's 5-wide maxima in ring[y % 5] (entries 2 .. w - 3)
    column_max = np.empty(w, np.float32)
    flags = np.zeros(8 * ((w + 7) // 8), np.uint8)  # whole 8-byte words
    words = flags.view(np.uint64)
    thr32 = np.float32(thr)
    for y in range(b - 2, b + 2):
        _row_max_5(lam[y], ring[y % 5])
    for y in range(b, h - b):
        _row_max_5(lam[y + 2], ring[(y + 2) % 5])
        _column_max_5(ring, column_max)
        row = lam[y]
        for x in range(w):
            v = row[x]
            flags[x] = (v > thr32) & (v >= column_max[x])
        for k in range(words.shape[0]):
            if words[k] == 0:
                continue
            for x in range(max(8 * k, b), min(8 * k + 8, w - b)):
                if flags[x]:
                    xs[n] = x
                    ys[n] = y
                    n += 1
    return _gathered(lam, xs, ys, n)


@njit(cache=True, nogil=True, inline="always")
def _max_5(a: float, b: float, c: float, d: float, e: float) -> float:
    """The largest of five values, as selects the compiler vectorises."""
    a = a if a > b else b
    c = c if c > d else d
    a = a if a > c else c
    return a if a > e else e


@njit(cache=True, nogil=True)
def _row_max_5(row: np.ndarray, out: np.ndarray) -> None:
    """out[x] = the largest of row[x - 2 .. x + 2], for x in 2 .. len - 3."""
    for x in range(row.shape[0] - 4):
        out[x + 2] = _max_5(row[x], row[x + 1], row[x + 2], row[x + 3], row[x + 4])


@njit(cache=True, nogil=True)
def _column_max_5(ring: np.ndarray, out: np.ndarray) -> None:
    """out[x] = the largest of the five rows of ``ring`` at x."""
    for x in range(out.shape[0]):
        out[x] = _max_5(ring[0, x], ring[1, x], ring[2, x], ring[3, x], ring[4, x])


@njit(cache=True, nogil=True, inline="always")
def _gathered(lam: np.ndarray, xs: np.ndarray, ys: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """The first n (x, y) of xs, ys as (n, 2) float points and their responses in lam (float32)."""
    pts = np.empty((n, 2))
    resp = np.empty(n, np.float32)
    for k in range(n):
        pts[k, 0] = xs[k]
        pts[k, 1] = ys[k]
        resp[k] = lam[ys[k], xs[k]]
    return pts, resp


@lru_cache(maxsize=64)
def _unit_noise_response(sigma_centi: int, block_size: int, percentile: float) -> float:
    """The ``percentile`` of the minimum-eigenvalue response of unit white noise after the detector's own
    smoothing (sigma in hundredths of a pixel) and gradients: what noise alone gives, to scale by the
    image's noise variance. Measured on a fixed noise image rather than derived: the box sum of
    correlated (smoothed) gradients has no simple closed form."""
    rng = np.random.default_rng(0)
    noise = rng.standard_normal((160, 160)).astype(np.float32)
    smooth = smooth_image(noise, sigma_centi / 100.0)
    gx, gy = gradients(smooth)
    lam = min_eigen_image(gx, gy, block_size)[8:-8, 8:-8]
    return float(np.percentile(lam, percentile))


def noise_response_floor(noise_sigma: float, smooth_sigma: float, block_size: int, quantile: float) -> float:
    """The minimum-eigenvalue response that image noise of ``noise_sigma`` grey levels reaches at the
    ``quantile`` (e.g. 0.999): weaker candidates are as likely noise as corners (grey levels^2)."""
    return noise_sigma ** 2 * _unit_noise_response(int(round(100 * smooth_sigma)), block_size, 100.0 * quantile)


def min_eigen_candidates(gx: np.ndarray, gy: np.ndarray, block_size: int, quality: float,
                         max_candidates: int, floor: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Local maxima of the minimum eigenvalue of the structure tensor (Shi-Tomasi), strongest first.

    gx, gy: the image gradients (see gradients). Returns (points (M, 2) float64 x, y; responses (M,)
    float32). A point is kept when it is the largest in its 5x5 neighbourhood and above ``quality`` x the
    image's strongest response and above ``floor`` (see noise_response_floor); the outermost 2 pixels are
    skipped (the probe needs room).
    """
    lam = min_eigen_image(gx, gy, block_size)
    peak = float(lam.max()) if lam.size else 0.0
    if peak <= 0.0:
        return np.zeros((0, 2)), np.zeros(0, np.float32)
    # the threshold as float32, as lam's values are compared with it
    pts, resp = _local_maxima(lam, float(np.float32(max(quality * peak, floor))), 2)
    order = np.argsort(-resp, kind="stable")[:max_candidates]
    return pts[order], resp[order]


@njit(cache=True, nogil=True)
def _median_noise_response(grey: np.ndarray, stride: int) -> float:
    """Median |response| of the mask [[1,-2,1],[-2,4,-2],[1,-2,1]] over every ``stride``-th interior pixel
    (-1.0 when there is none).

    One pass without copies (nine strided slices, their conversions and np.median cost ~1 ms at 1280x800).
    The responses of a uint8 image are integers up to 16 x 255, so a histogram gives the exact median.
    """
    h, w = grey.shape
    ny = (h - 2 + stride - 1) // stride if h > 2 else 0
    nx = (w - 2 + stride - 1) // stride if w > 2 else 0
    n = ny * nx
    if n == 0:
        return -1.0
    # four histograms, one per column modulo 4: consecutive samples of a flat area no longer wait on one bin
    counts4 = np.zeros((4, 16 * 255 + 1), np.int32)
    for a in range(ny):
        y = a * stride
        r0 = grey[y]
        r1 = grey[y + 1]
        r2 = grey[y + 2]
        for b in range(nx):
            x = b * stride
            edge = np.int32(r0[x + 1]) + np.int32(r2[x + 1]) + np.int32(r1[x + 2]) + np.int32(r1[x])
            diag = np.int32(r0[x + 2]) + np.int32(r0[x]) + np.int32(r2[x + 2]) + np.int32(r2[x])
            counts4[b & 3, abs(4 * np.int32(r1[x + 1]) - 2 * edge + diag)] += 1
    counts = counts4.sum(axis=0)
    # the n // 2-th smallest (0-based), and for an even n the mean with the one before it
    hi_rank = n // 2
    lo_rank = hi_rank - 1 if n % 2 == 0 else hi_rank
    seen = 0
    lo = -1
    for v in range(counts.shape[0]):
        seen += counts[v]
        if lo < 0 and seen > lo_rank:
            lo = v
        if seen > hi_rank:
            return 0.5 * (lo + v)
    return 0.5 * (lo + counts.shape[0] - 1)


def estimate_noise_sigma(grey: np.ndarray, stride: int = 3) -> float:
    """Robust estimate of the image noise (grey levels), from the median response of a Laplacian-like mask.

    The 3x3 mask [[1,-2,1],[-2,4,-2],[1,-2,1]] cancels smooth shading and lines; its response to white noise
    has 6 sigma spread, and the median ignores the few edge pixels. The mask is evaluated on every
    ``stride``-th pixel in each direction only: plenty for a median, stride^2 times cheaper. grey: uint8.
    """
    if grey.dtype != np.uint8:
        raise TypeError(f"estimate_noise_sigma needs a uint8 image, got {grey.dtype}")
    median = _median_noise_response(np.ascontiguousarray(grey), int(stride))
    # in float32, as the estimate has always been computed (detections stay bit-identical)
    return float(np.float32(median) / np.float32(0.6745 * 6.0)) if median >= 0.0 else 0.0


# The half-resolution estimate's kernel: cv2.pyrDown's binomial (1, 4, 6, 4, 1) / 16, decimated by two, then
# the Laplacian-like mask's (1, -2, 1) on the half-resolution pixels, as one kernel on the full-resolution
# pixels: (1, 4, 4, -4, -10, -4, 4, 4, 1) / 16 per axis (_half_tap_sum). Its 2-D kernel c c^T / 256 passes
# sum(c^2) / 256 of white noise's sigma.
HALF_NOISE_GAIN = 198.0 / 256.0


@njit(cache=True, nogil=True, inline="always")
def _half_tap_sum(v0: int, v1: int, v2: int, v3: int, v4: int, v5: int, v6: int, v7: int, v8: int) -> int:
    """Nine values weighted by 16 x the half-resolution kernel (1, 4, 4, -4, -10, -4, 4, 4, 1), exactly."""
    return (v0 + v8) + 4 * (v1 + v2 + v6 + v7) - 4 * (v3 + v5) - 10 * v4


@njit(cache=True, nogil=True)
def _half_noise_responses(grey: np.ndarray, stride: int) -> np.ndarray:
    """|response| x 256 of the half-resolution mask at every ``stride``-th pixel whose 9x9 neighbourhood lies
    in the image (N,) float64: one strided pass over the full-resolution image, since the float pyrDown
    and the mask on it are only needed at these samples. Integer arithmetic: exact for a uint8 image."""
    h, w = grey.shape
    ny = (h - 9 + stride) // stride if h >= 9 else 0
    nx = (w - 9 + stride) // stride if w >= 9 else 0
    out = np.empty(ny * nx)
    col = np.empty(9, np.int32)
    n = 0
    for a in range(ny):
        y = a * stride
        for b in range(nx):
            x = b * stride
            for i in range(9):
                r = grey[y + i]
                col[i] = _half_tap_sum(np.int32(r[x]), np.int32(r[x + 1]), np.int32(r[x + 2]), np.int32(r[x + 3]),
                                       np.int32(r[x + 4]), np.int32(r[x + 5]), np.int32(r[x + 6]),
                                       np.int32(r[x + 7]), np.int32(r[x + 8]))
            out[n] = abs(_half_tap_sum(col[0], col[1], col[2], col[3], col[4], col[5], col[6], col[7], col[8]))
            n += 1
    return out


# Samples the half-resolution estimate takes (its stride follows the image's size): the median of 2000
# samples is good to ~3 %, and each costs a 9x9 neighbourhood (~0.04 ms per image, any size).
HALF_NOISE_SAMPLES = 2000


def half_resolution_noise_sigma(grey: np.ndarray, stride: int | None = None) -> float:
    """Image noise (grey levels of ``grey``, 1 sigma) seen at half resolution: estimate_noise_sigma's median of
    the Laplacian-like mask on the float image cv2.pyrDown makes of ``grey`` (its uint8 rounding moves the
    median in steps of ~1 grey level), divided by the gain of that whole pipeline on white noise.

    pyrDown passes 0.273 of white noise, but its half-resolution pixels are correlated and the mask sees
    less of them than of white noise: the pipeline passes HALF_NOISE_GAIN / 6 = 0.129 of what the mask
    passes at full resolution (so estimate_noise_sigma(pyrDown(grey)) / 0.273 says half the noise there
    is). JPEG compression and demosaicing remove pixel-to-pixel noise, which fools estimate_noise_sigma,
    while the noise at the scale of a corner stays: at half resolution it is seen (measured on ../shared's
    renders: 1.0-1.3 x the rendered noise, 1.05 under JPEG quality 70, where estimate_noise_sigma gives
    0.14). ``stride``: full-resolution pixels between samples (default: HALF_NOISE_SAMPLES samples).
    grey: uint8; 0.0 below 9x9 pixels.
    """
    if grey.dtype != np.uint8:
        raise TypeError(f"half_resolution_noise_sigma needs a uint8 image, got {grey.dtype}")
    if stride is None:
        stride = max(2, int(round(math.sqrt(grey.size / HALF_NOISE_SAMPLES))))
    resp = _half_noise_responses(np.ascontiguousarray(grey), int(stride))
    if resp.size == 0:
        return 0.0
    # the median of |N(0, s)| is 0.6745 s
    return float(_median(resp) / (256.0 * 0.6745 * HALF_NOISE_GAIN))


@njit(cache=True, nogil=True)
def _median(values: np.ndarray) -> float:
    """np.median of ``values`` (N > 0,) without NaN, in numba: the same value (the middle one, or the mean of
    the two middle ones as (a + b) / 2, as np.median's mean of two), at a quarter of np.median's call overhead
    (~15 us for 2000 samples, once per frame). The input is left as it was (numba sorts a copy)."""
    return np.median(values)


@njit(cache=True, nogil=True)
def snap_to_saddle(smooth: np.ndarray, pts: np.ndarray, reach: int) -> np.ndarray:
    """Move each point to the most saddle-like pixel within ``reach`` (most negative Hessian determinant).

    Min-eigenvalue maxima lie 1-3 px off an X-corner: the gradient vanishes at the saddle itself. The
    Hessian determinant is most negative exactly there, whatever the square size, so one cheap local search
    puts every candidate on its corner's nearest pixel before the probe looks at it.
    """
    h, w = smooth.shape
    out = pts.copy()
    for i in range(pts.shape[0]):
        cx = int(pts[i, 0] + 0.5)
        cy = int(pts[i, 1] + 0.5)
        best = 0.0
        bx = cx
        by = cy
        for y in range(max(2, cy - reach), min(h - 2, cy + reach + 1)):
            for x in range(max(2, cx - reach), min(w - 2, cx + reach + 1)):
                ixx = smooth[y, x + 1] - 2.0 * smooth[y, x] + smooth[y, x - 1]
                iyy = smooth[y + 1, x] - 2.0 * smooth[y, x] + smooth[y - 1, x]
                ixy = 0.25 * (smooth[y + 1, x + 1] - smooth[y + 1, x - 1] - smooth[y - 1, x + 1]
                              + smooth[y - 1, x - 1])
                d = ixx * iyy - ixy * ixy
                if d < best:
                    best = d
                    bx = x
                    by = y
        out[i, 0] = bx
        out[i, 1] = by
    return out


def chess_ring(radius: float) -> tuple[np.ndarray, np.ndarray]:
    """The 16 integer pixel offsets (dx, dy) of the ChESS ring of ``radius``, counter-clockwise from +x."""
    theta = np.arange(16) * (2.0 * np.pi / 16)
    return (np.round(radius * np.cos(theta)).astype(np.int64), np.round(radius * np.sin(theta)).astype(np.int64))


@njit(cache=True, nogil=True)
def chess_response(img: np.ndarray, dx: np.ndarray, dy: np.ndarray, out: np.ndarray) -> None:
    """ChESS response (Bennett & Lasenby 2014) of every pixel into ``out`` (same shape, float32; 0 at the border).

    On a ring of 16 samples: the sum response (opposite quarters alike, neighbouring quarters different)
    minus the difference response (opposite samples must match: an X-corner is point-symmetric, an edge is
    not) minus 16 x the ring mean's offset from the centre (a blob or a line end). Strongly positive only
    at X-corners, exactly at their saddle, and ~0 on edges and noise, which is why it thins the
    candidates far more than a corner measure like the minimum eigenvalue. One pass over the image with
    the ring as offsets into the flat pixel array.
    """
    h, w = img.shape
    r = 1
    for k in range(16):
        r = max(r, abs(dx[k]), abs(dy[k]))
    flat = img.ravel()
    res = out.ravel()
    res[:] = 0.0
    off = np.empty(16, np.int64)
    for k in range(16):
        off[k] = dy[k] * w + dx[k]
    for y in range(r, h - r):
        row = y * w
        for x in range(r, w - r):
            i = row + x
            s0 = flat[i + off[0]]
            s1 = flat[i + off[1]]
            s2 = flat[i + off[2]]
            s3 = flat[i + off[3]]
            s4 = flat[i + off[4]]
            s5 = flat[i + off[5]]
            s6 = flat[i + off[6]]
            s7 = flat[i + off[7]]
            s8 = flat[i + off[8]]
            s9 = flat[i + off[9]]
            s10 = flat[i + off[10]]
            s11 = flat[i + off[11]]
            s12 = flat[i + off[12]]
            s13 = flat[i + off[13]]
            s14 = flat[i + off[14]]
            s15 = flat[i + off[15]]
            sr = (abs(s0 + s8 - s4 - s12) + abs(s1 + s9 - s5 - s13) + abs(s2 + s10 - s6 - s14)
                  + abs(s3 + s11 - s7 - s15))
            dr = (abs(s0 - s8) + abs(s1 - s9) + abs(s2 - s10) + abs(s3 - s11) + abs(s4 - s12) + abs(s5 - s13)
                  + abs(s6 - s14) + abs(s7 - s15))
            tot = (s0 + s1 + s2 + s3 + s4 + s5 + s6 + s7 + s8 + s9 + s10 + s11 + s12 + s13 + s14 + s15)
            centre = np.float32(0.2) * (flat[i] + flat[i - 1] + flat[i + 1] + flat[i - w] + flat[i + w])
            res[i] = sr - dr - np.float32(16.0) * abs(tot * np.float32(1.0 / 16.0) - centre)


@njit(cache=True, nogil=True, inline="always")
def _chess_at(flat: np.ndarray, i: int, off: np.ndarray, w: int) -> float:
    """ChESS response at flat pixel index ``i`` for the ring offsets ``off`` (see chess_response)."""
    sr = 0.0
    for n in range(4):
        sr += abs(flat[i + off[n]] + flat[i + off[n + 8]] - flat[i + off[n + 4]] - flat[i + off[n + 12]])
    dr = 0.0
    tot = 0.0
    for n in range(8):
        a = flat[i + off[n]]
        b = flat[i + off[n + 8]]
        dr += abs(a - b)
        tot += a + b
    centre = 0.2 * (flat[i] + flat[i - 1] + flat[i + 1] + flat[i - w] + flat[i + w])
    return sr - dr - 16.0 * abs(tot / 16.0 - centre)


@njit(cache=True, nogil=True)
def chess_filter(img: np.ndarray, pts: np.ndarray, rings: np.ndarray, thresholds: np.ndarray) -> np.ndarray:
    """Which points have a ChESS response above ``thresholds[k]`` for some ring k within one pixel.

    img: smoothed float32 image; pts (M, 2) integer-valued x, y (snapped candidates); rings (K, 2, 16)
    integer dx, dy of each ring (chess_ring). Returns keep (M,) bool. Points too near the border for a
    ring are kept (the probe decides there).
    """
    h, w = img.shape
    flat = img.ravel()
    n_rings = rings.shape[0]
    offs = np.empty((n_rings, 16), np.int64)
    reach = np.zeros(n_rings, np.int64)
    for k in range(n_rings):
        for j in range(16):
            offs[k, j] = rings[k, 1, j] * w + rings[k, 0, j]
            reach[k] = max(reach[k], abs(rings[k, 0, j]), abs(rings[k, 1, j]))
    keep = np.zeros(pts.shape[0], np.bool_)
    for m in range(pts.shape[0]):
        cx = int(pts[m, 0] + 0.5)
        cy = int(pts[m, 1] + 0.5)
        for k in range(n_rings):
            r = reach[k] + 2
            if cx < r or cy < r or cx >= w - r or cy >= h - r:
                keep[m] = True
                break
            # some pixel of the 3x3 above the threshold (the first one found is enough)
            for yy in range(cy - 1, cy + 2):
                for xx in range(cx - 1, cx + 2):
                    if _chess_at(flat, yy * w + xx, offs[k], w) > thresholds[k]:
                        keep[m] = True
                        break
                if keep[m]:
                    break
            if keep[m]:
                break
    return keep


@njit(cache=True, nogil=True)
def dedupe_in_order(pts: np.ndarray, radius: float) -> np.ndarray:
    """Indices of the points (M, 2) with no earlier point within ``radius`` pixels, in order (greedy: a
    point is dropped only by a kept one). A hash grid keeps it linear in M: cells of at least ``radius``
    (every point within it lies in the 3x3 cells around), about 16 per point over the points' extent (cells
    of ``radius`` itself, 0.75 px, over a 1280x800 frame's candidates filled 1.8 M cells per call; one per
    point put dozens of a noisy frame's candidates, crowded along its edges, in a cell searched for each)."""
    m = pts.shape[0]
    keep = np.zeros(m, np.bool_)
    if m == 0:
        return np.zeros(0, np.int64)
    x0 = pts[:, 0].min()
    y0 = pts[:, 1].min()
    span_x = pts[:, 0].max() - x0
    span_y = pts[:, 1].max() - y0
    cell = max(radius, 1e-6, math.sqrt((span_x + 1.0) * (span_y + 1.0) / (16.0 * m)))
    nx = int(span_x / cell) + 1
    ny = int(span_y / cell) + 1
    head = np.full(nx * ny, -1, np.int64)  # kept points per cell as linked lists
    nxt = np.full(m, -1, np.int64)
    r2 = radius * radius
    for i in range(m):
        gx = int((pts[i, 0] - x0) / cell)
        gy = int((pts[i, 1] - y0) / cell)
        clash = False
        for yy in range(max(0, gy - 1), min(ny, gy + 2)):
            for xx in range(max(0, gx - 1), min(nx, gx + 2)):
                j = head[yy * nx + xx]
                while j >= 0 and not clash:
                    dxp = pts[i, 0] - pts[j, 0]
                    dyp = pts[i, 1] - pts[j, 1]
                    if dxp * dxp + dyp * dyp <= r2:
                        clash = True
                    j = nxt[j]
        if not clash:
            keep[i] = True
            c = gy * nx + gx
            nxt[i] = head[c]
            head[c] = i
    return np.nonzero(keep)[0]


@lru_cache(maxsize=64)
def _unit_noise_chess(sigma_centi: int, radius_deci: int, quantile: float) -> float:
    """The ``quantile`` of the ChESS response of unit white noise after the detector's smoothing (sigma in
    hundredths of a pixel) on the ring of ``radius_deci`` tenths of a pixel; measured like
    _unit_noise_response."""
    rng = np.random.default_rng(0)
    noise = rng.standard_normal((200, 200)).astype(np.float32)
    smooth = smooth_image(noise, sigma_centi / 100.0)
    dx, dy = chess_ring(radius_deci / 10.0)
    out = np.empty_like(smooth)
    chess_response(smooth, dx, dy, out)
    return float(np.quantile(out[10:-10, 10:-10], quantile))


def chess_thresholds(radii: tuple[float, ...], noise_sigma: float, smooth_sigma: float, quantile: float,
                     minimum: float) -> np.ndarray:
    """Per ChESS ring: what the image's noise reaches at ``quantile``, but at least ``minimum``."""
    return np.array([max(minimum, noise_sigma * _unit_noise_chess(int(round(100 * smooth_sigma)),
                                                                  int(round(10 * r)), quantile)) for r in radii])
