"""Step 1: image preparation and minimum-eigenvalue (Shi-Tomasi / "Lucas-Kanade") candidates."""

from __future__ import annotations

import cv2
import numpy as np


def smoothing_sigma(noise_sigma: float) -> float:
    """Gaussian sigma (px) for a given image noise: 0.8 px on clean images, up to 2 px on very noisy ones.

    More smoothing would merge the corners of the smallest (8 px) squares.
    """
    return float(np.clip(0.8 + 0.06 * noise_sigma, 0.8, 2.0))


def prepare_image(grey: np.ndarray, sigma: float = 0.8) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Smoothed float32 image and its x/y gradients (grey levels per pixel, OpenCV Sobel / 8).

    The Gaussian keeps sensor noise out of the gradients; blurring does not move a corner's saddle point.
    """
    ksize = 2 * int(np.ceil(2.5 * sigma)) + 1
    smooth = cv2.GaussianBlur(grey.astype(np.float32), (ksize, ksize), sigma)
    gx = cv2.Sobel(smooth, cv2.CV_32F, 1, 0, ksize=3, scale=0.125)
    gy = cv2.Sobel(smooth, cv2.CV_32F, 0, 1, ksize=3, scale=0.125)
    return smooth, gx, gy


def min_eigen_candidates(smooth: np.ndarray, block_size: int, quality: float,
                         max_candidates: int) -> tuple[np.ndarray, np.ndarray]:
    """Local maxima of the minimum eigenvalue of the structure tensor, strongest first.

    Returns (points (M, 2) float64 x, y; responses (M,) float32). A point is kept when it is the largest
    in its 5x5 neighbourhood and above ``quality`` x the image's strongest response.
    """
    resp = cv2.cornerMinEigenVal(smooth, block_size, ksize=3)
    peak = float(resp.max()) if resp.size else 0.0
    if peak <= 0.0:
        return np.zeros((0, 2)), np.zeros(0, np.float32)
    local_max = cv2.dilate(resp, np.ones((5, 5), np.uint8))
    mask = (resp >= local_max) & (resp > quality * peak)
    # Probe rays need room: skip the outermost 2 pixels.
    mask[:2, :] = False
    mask[-2:, :] = False
    mask[:, :2] = False
    mask[:, -2:] = False
    ys, xs = np.nonzero(mask)
    r = resp[ys, xs]
    order = np.argsort(-r, kind="stable")[:max_candidates]
    pts = np.stack([xs[order], ys[order]], axis=1).astype(np.float64)
    return pts, r[order]


def estimate_noise_sigma(grey: np.ndarray) -> float:
    """Robust estimate of the image noise (grey levels), from the median response of a Laplacian-like mask.

    The 3x3 mask [[1,-2,1],[-2,4,-2],[1,-2,1]] cancels smooth shading and lines; its response to white noise
    has 6 sigma spread, and the median ignores the few edge pixels.
    """
    mask = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)
    resp = cv2.filter2D(grey.astype(np.float32), cv2.CV_32F, mask)
    return float(np.median(np.abs(resp[1:-1, 1:-1])) / (0.6745 * 6.0))
