"""The images one detection pass works on: the grey image (or a window of it), smoothed, and its gradients."""

from __future__ import annotations

import math

import numpy as np

from edgecal.detection.candidates import estimate_noise_sigma, gradients, gradients_near, smooth_image, smoothing_sigma

# The window's left edge on a multiple of this many pixels: OpenCV's vectorised filters then round every
# pixel as they do on the whole image (a start off the vector grid moves pixels between vector and scalar code).
_WINDOW_ALIGN_PX = 32


# Share of a level's pixels (the discs' summed areas, over all calls) up to which Level.gradients_near
# computes the gradients round the points only: 2-3x cheaper than the whole images' Sobels at a share of
# 0.1-0.4, as cheap at ~0.7 (54 discs on 640x480), where the whole images are made and kept for later use.
_NEAR_SHARE = 0.5


class Level:
    """The images one pyramid level works on; the gradients are computed on first use only (a level that
    only refines corners found on a coarser one never needs them).

    A level can be a window of its image: ``grey`` is then the window, ``origin`` (x, y) its top-left pixel
    in the image and ``image`` the whole image (the covariances' noise is measured on all of it).
    ``noise_sigma`` sets the thresholds that are noise quantiles (candidates, ChESS), ``smoothing_noise``
    (default noise_sigma) the smoothing (candidates.smoothing_sigma).
    """

    def __init__(self, grey: np.ndarray, noise_sigma: float | None = None, origin: tuple[int, int] = (0, 0),
                 image: np.ndarray | None = None, smoothing_noise: float | None = None) -> None:
        self.noise_sigma = estimate_noise_sigma(grey) if noise_sigma is None else noise_sigma
        self.grey = grey
        self.origin = np.array(origin, dtype=np.float64)
        self.image = grey if image is None else image
        self.smoothing_sigma = smoothing_sigma(self.noise_sigma if smoothing_noise is None else smoothing_noise)
        self.smooth = smooth_image(grey, self.smoothing_sigma)
        self._gradients: tuple[np.ndarray, np.ndarray] | None = None
        # gradients_near's images and the discs' summed area so far: one pair per level, not per call (a
        # window round several boards is asked once per board and check, and each fresh pair cost more
        # than its discs)
        self._near: tuple[np.ndarray, np.ndarray] | None = None
        self._near_area = 0.0

    @property
    def gx(self) -> np.ndarray:
        """x gradient of the smoothed image (computed on first use)."""
        return self._grads()[0]

    @property
    def gy(self) -> np.ndarray:
        """y gradient of the smoothed image (computed on first use)."""
        return self._grads()[1]

    def gradients_near(self, pts: np.ndarray, reach: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The x/y gradients wherever they are read within ``reach`` (M,) px of points (M, 2): the level's
        whole gradient images once they are made, else only those discs (candidates.gradients_near), which
        is cheaper when they cover little of the level (a window that only refines a board's corners). The
        discs of every call go into one pair of images, until together they cover _NEAR_SHARE of the level."""
        if self._gradients is None:
            area = self._near_area + np.pi * float(np.sum((reach + 2.0) ** 2))
            if area <= _NEAR_SHARE * self.smooth.size:
                self._near_area = area
                self._near = gradients_near(self.smooth, pts, reach, self._near)
                return self._near
        return self._grads()

    def _grads(self) -> tuple[np.ndarray, np.ndarray]:
        if self._gradients is None:
            self._gradients = gradients(self.smooth)
            self._near = None  # (the discs' images are not used again)
        return self._gradients


def window_level(grey: np.ndarray, noise_sigma: float, box: tuple[float, float, float, float]) -> Level:
    """A level on the window of ``grey`` holding ``box`` (x0, y0, x1, y1 pixels), whose smoothed image and
    gradients equal the whole image's within the box: the window reaches past it by the smoothing kernel
    and the gradient stencil (clipped at the image's border, where both mirror the same way)."""
    h, w = grey.shape
    pad = int(np.ceil(2.5 * smoothing_sigma(noise_sigma))) + 2
    x0 = max(0, int(math.floor(box[0])) - pad)
    x0 -= x0 % _WINDOW_ALIGN_PX
    y0 = max(0, int(math.floor(box[1])) - pad)
    x1 = min(w, int(math.ceil(box[2])) + pad + 1)
    y1 = min(h, int(math.ceil(box[3])) + pad + 1)
    return Level(grey[y0:y1, x0:x1], noise_sigma, (x0, y0), grey)
