"""Step 1: image preparation and minimum-eigenvalue (Shi-Tomasi / "Lucas-Kanade") candidates."""

from __future__ import annotations

import cv2
import numpy as np
from numba import njit


def smoothing_sigma(noise_sigma: float) -> float:
    """Gaussian sigma (px) for a given image noise: 0.8 px on clean images, up to 2 px on very noisy ones.

    More smoothing would merge the corners of the smallest (8 px) squares.
    """
    return float(np.clip(0.8 + 0.06 * noise_sigma, 0.8, 2.0))


def smooth_image(grey: np.ndarray, sigma: float = 0.8) -> np.ndarray:
    """The float32 image the detector samples: a Gaussian keeps sensor noise out of the gradients, and
    blurring does not move a corner's saddle point."""
    ksize = 2 * int(np.ceil(2.5 * sigma)) + 1
    return cv2.GaussianBlur(grey.astype(np.float32), (ksize, ksize), sigma)


def gradients(smooth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """x and y gradients of the smoothed image, grey levels per pixel (OpenCV Sobel / 8)."""
    gx = cv2.Sobel(smooth, cv2.CV_32F, 1, 0, ksize=3, scale=0.125)
    gy = cv2.Sobel(smooth, cv2.CV_32F, 0, 1, ksize=3, scale=0.125)
    return gx, gy


def prepare_image(grey: np.ndarray, sigma: float = 0.8) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Smoothed float32 image and its x/y gradients (see smooth_image and gradients)."""
    smooth = smooth_image(grey, sigma)
    return (smooth, *gradients(smooth))


def min_eigen_image(gx: np.ndarray, gy: np.ndarray, block_size: int) -> np.ndarray:
    """Minimum eigenvalue of the box-summed structure tensor at every pixel (Shi-Tomasi response).

    lambda_min = (a + c) / 2 - sqrt(((a - c) / 2)^2 + b^2) for the tensor [[a, b], [b, c]], all in OpenCV's
    vectorised image arithmetic (several times faster here than a per-pixel loop).
    """
    k = (block_size, block_size)
    a = cv2.boxFilter(cv2.multiply(gx, gx), -1, k, normalize=False)
    c = cv2.boxFilter(cv2.multiply(gy, gy), -1, k, normalize=False)
    b = cv2.boxFilter(cv2.multiply(gx, gy), -1, k, normalize=False)
    root = cv2.magnitude(cv2.addWeighted(a, 0.5, c, -0.5, 0.0), b)
    return cv2.subtract(cv2.addWeighted(a, 0.5, c, 0.5, 0.0), root)


@njit(cache=True, nogil=True)
def _local_maxima(lam: np.ndarray, thr: float, border: int) -> tuple[np.ndarray, np.ndarray]:
    """Strict 5x5 local maxima of ``lam`` above ``thr``, away from the border."""
    h, w = lam.shape
    xs = []
    ys = []
    rs = []
    for y in range(max(border, 2), h - max(border, 2)):
        for x in range(max(border, 2), w - max(border, 2)):
            v = lam[y, x]
            if v <= thr:
                continue
            is_max = True
            for dy in range(-2, 3):
                for dx in range(-2, 3):
                    if dy == 0 and dx == 0:
                        continue
                    u = lam[y + dy, x + dx]
                    # ties go to the first pixel in raster order, so a plateau gives one candidate
                    if u > v or (u == v and (dy < 0 or (dy == 0 and dx < 0))):
                        is_max = False
                        break
                if not is_max:
                    break
            if is_max:
                xs.append(x)
                ys.append(y)
                rs.append(v)
    pts = np.empty((len(xs), 2))
    resp = np.empty(len(xs), dtype=np.float32)
    for i in range(len(xs)):
        pts[i, 0] = xs[i]
        pts[i, 1] = ys[i]
        resp[i] = rs[i]
    return pts, resp


def min_eigen_candidates(gx: np.ndarray, gy: np.ndarray, block_size: int, quality: float,
                         max_candidates: int) -> tuple[np.ndarray, np.ndarray]:
    """Local maxima of the minimum eigenvalue of the structure tensor (Shi-Tomasi), strongest first.

    gx, gy: the image gradients (see gradients). Returns (points (M, 2) float64 x, y; responses (M,)
    float32). A point is kept when it is the largest in its 5x5 neighbourhood and above ``quality`` x the
    image's strongest response; the outermost 2 pixels are skipped (the probe needs room).
    """
    lam = min_eigen_image(gx, gy, block_size)
    peak = float(lam.max()) if lam.size else 0.0
    if peak <= 0.0:
        return np.zeros((0, 2)), np.zeros(0, np.float32)
    pts, resp = _local_maxima(lam, quality * peak, 2)
    order = np.argsort(-resp, kind="stable")[:max_candidates]
    return pts[order], resp[order]


def estimate_noise_sigma(grey: np.ndarray, stride: int = 3) -> float:
    """Robust estimate of the image noise (grey levels), from the median response of a Laplacian-like mask.

    The 3x3 mask [[1,-2,1],[-2,4,-2],[1,-2,1]] cancels smooth shading and lines; its response to white noise
    has 6 sigma spread, and the median ignores the few edge pixels.
    """
    # The mask evaluated on every ``stride``-th pixel in each direction only: plenty for a median, stride^2
    # times cheaper (the slices are taken before any conversion, so the full image is never copied).
    def part(dy: int, dx: int) -> np.ndarray:
        return grey[dy:grey.shape[0] - 2 + dy:stride, dx:grey.shape[1] - 2 + dx:stride].astype(np.float32)

    c, n, s_, e, wv = part(1, 1), part(0, 1), part(2, 1), part(1, 2), part(1, 0)
    ne, nw, se, sw = part(0, 2), part(0, 0), part(2, 2), part(2, 0)
    resp = 4.0 * c - 2.0 * (n + s_ + e + wv) + (ne + nw + se + sw)
    return float(np.median(np.abs(resp)) / (0.6745 * 6.0)) if resp.size else 0.0


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
