"""How well each refined corner is known: a 2x2 covariance per corner, from the image around it.

Two refiners place the final corners (subpixel.REFINERS); each gets the covariance of its own estimator,
image noise carried through it exactly plus a model error for what noise does not explain.

The saddle fit (the detector's default, subpixel.saddle_refine) fits a quadratic to the smoothed image
around the corner and takes its saddle: H s = -(d, e), H the quadratic's Hessian, (d, e) its linear terms.
Noise moves the linear terms only to first order, so Sigma_noise = H^-1 N H^-1 sigma^2, N the covariance of
(d, e) for unit white noise in the raw image, carried exactly through the detector's smoothing, the bilinear
resampling, the fit's own smoothing and its weights. H holds contrast (it scales with it), blur (a flatter
saddle) and foreshortening (edges close to parallel: one small eigenvalue) by itself.

cornerSubPix (the "cornersubpix" refiner, and tracking's first pass) solves the gradient-orthogonality
equations sum_i w_i g_i g_i^T (q - p_i) = 0 over its window (w_i = exp(-|p_i - q|^2 / hw^2)). Perturbing
the gradients by image noise and linearising gives the sandwich

    Sigma_noise = A^-1 B A^-1 * sigma_g^2,   A = sum w g g^T,   B = sum w^2 g g^T |p - q|^2.

What noise does not explain is the bias of a corner that is not an ideal X-junction: an uneven light
field adds a gradient that does not point at the corner, perspective and lens curvature break its point
symmetry, pixels and quantisation limit a clean image (an edge along a pixel axis most: pixel locking).
For the saddle fit it is isotropic (measured: its errors beyond noise have no preferred direction, also on
foreshortened corners; cornerSubPix's model error in A^-1's shape made its covariances 1.7-2.2x elongated
where the errors were not): a floor that grows for an edge within ~10 deg of a pixel axis
(pixel locking), the saddle's shift by the light field (a light field L(x) times the pattern adds
m = grad L x the saddle's level to the fit's linear terms: H^-1 m, no fitted factor; grad L is read off
the squares next to the corner, diagonally opposite ones having the same colour, not off the window's
mean gradient, which neighbouring edges and perspective move too) and the Newton step the fit still sees
at the corner. For cornerSubPix, in A^-1's shape (a light gradient biases it along its weak direction): a
floor and a gain on the window's asymmetry |mean gradient| / contrast.
bench/corner_noise.py measures the normalised error e^T Sigma^-1 e on renders with exact truth (2 on
average for a consistent 2-D covariance).

A covariance that is not positive definite or not finite (a flat or saturated window, a corner at the
image border, a line instead of a corner) marks that corner unusable, with the reason; so does a saddle
fit that would put the corner more than a pixel from where cornerSubPix put it (not one clean corner), and,
for the saddle and X-junction refiners, a corner neither fit sees (cornerSubPix's position alone is often
on an edge there).

Pure functions: the smoothed image and the corners in, covariances out; one numba call per frame over all
corners.
"""

from __future__ import annotations

import math
from functools import lru_cache
from typing import NamedTuple

import numpy as np
from numba import njit

from edgecal.detection.subpixel import (
    REFINERS,
    fit_coefficients,
    id_grid,
    nearest_spacing,
    saddle_fit_setup,
    subpixel_window,
    xjunction_disc_radius,
)
from edgecal.detection.types import Detection

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
REASON_DISAGREE = "saddle fit and cornerSubPix disagree by more than 1 px (not one clean corner)"
REASON_NO_FIT = "neither the saddle fit nor the X-junction fit sees a corner there (an edge or a blur)"


# The saddle fit's model error (px, 1 sigma per axis), measured on noise-free edgecal.synth renders (72
# planar views, optics blur 0.3 / 0.7 / 1.2 px, squares 15-45 px, tilts to 60 deg; the 11x11 fit; errors
# binned by the smallest angle between an edge and a pixel axis): corners whose edges are 12 deg or more
# off the pixel axes are good to 0.002-0.004 px per axis, what the noise term (quantisation alone) says:
# the floor is what is left, at most 0.002 px. Edges within 6 deg of a pixel axis give 0.010-0.014 px at
# every blur, 6-9 deg 0.009, 9-12 deg 0.004 (with the faint noise of bench/corner_noise.py's clean renders,
# 0-1 grey levels, which dithers it: 0.008 px up to 9 deg; 0.007 is taken, the value that makes those
# clean renders consistent, normalised error 1.75, with the noise estimate as it is): pixel locking, a bias
# that follows the edge's sub-pixel
# phase, which an edge slanted across the pixel grid averages out along its length. A Gaussian average
# over L along the edge damps it by exp(-2 pi^2 (L tan a)^2); L = PIXEL_LOCK_LENGTH_PX is read off that
# fall-off (the fit window's own RMS width, 2.5 px, would damp it by 9 deg already, which the errors do
# not show). A real lens and sensor add more; calibration's noise floor (calibration/refine.py) measures it.
SADDLE_FLOOR_PX = 0.002
PIXEL_LOCK_PX = 0.007
PROBE_NOISE_SHARE = 0.0  # see _saddle_covariance
PIXEL_LOCK_LENGTH_PX = 1.3
# The X-junction fit (the default refiner) against the saddle fit it starts from, measured by its author
# (subpixel.xjunction_fit, commit 62d9d3d): noise-only repeats of one render give its corners 0.42 of the
# saddle noise term's variance; noise-free renders binned by the edges' angle to the pixel axes 0.0061 /
# 0.0033 px at 0-4 / 4-9 deg against the saddle fit's 0.0125 / 0.0108 (pixel locking about half).
# The X-junction fit's noise term is its own: the position block of its (J^T W J)^-1 times the image's noise
# variance (subpixel.xjunction_fit, Detection.xjunction_noise), which counts the blur, contrast and disc it
# fitted; no gain. It replaced XJUNCTION_NOISE_SHARE x the saddle fit's term (which stays for corners given
# without it), whose one share could not fit both blurs: the robot sequences' corners, normalised error
# normal + 8 ms motion blur 1.51 (x 0.84, y 0.66 per axis) and the pose's sigma 1.2-1.6x too large there
# (bench/live.py, 298 frames: y 0.62, rx 0.66), while bench/corner_noise.py's hard renders were at 3.0. With
# the fit's own term (24 views per condition): corner_noise 1.93-2.67 (was 1.98-3.07), robot normal corners
# 1.76 (x 0.87, y 0.85), its pose's ratios 0.81-0.90.
XJUNCTION_NOISE_SHARE = 0.50
XJUNCTION_LOCK_SHARE = 0.5
# The X-junction fit's own floor: its corners' errors beyond noise and pixel locking. Fitted first (with the
# saddle fit's noise term scaled) over bench/corner_noise.py's clean and foreshortened renders, 0.000 and
# 0.0025-0.0028 px per axis: 0.001. With the fit's own noise term (smaller on clean renders, which have only
# quantisation noise) the robot sequence's clean corners had a normalised error of 3.27 and its pose z
# ratio 1.42; 0.0015 px: 2.95, pose ratios 0.82-1.32, corner_noise clean 1.95 (0.002: 2.64, 0.75-1.21, 1.58).
XJUNCTION_FLOOR_PX = 0.0015
# The lens-bend correction (line_bend) is a first-order model read off the board's own noisy corners: its
# error grows with the shift it takes off. On bench/calibrate.py's rendered fisheye hand-held sessions (24
# seeds, ~7,400 X-junction corners, clean and normal photometry) the normalised error was 52 and 9.0 (180
# and 25 on the quarter of the corners with the largest shifts, 0.05-0.25 px); with BEND_ERROR_SHARE x the
# shift's length added per axis, 0.2: 3.3 and 2.9, 0.3: 2.1 and 2.1 (that quarter 1.9 and 1.9).
BEND_ERROR_SHARE = 0.3
# That error is wholly shared by a board's corners (CornerCovariances.shared_px2): each line's curvature is
# read off the line's own corners, and the lens's curvature field is smooth over a board, so the error of the
# shift taken off is alike along a line and across neighbouring lines - on a wide lens a scale error of the
# board, which the pose sees as depth. bench/live.py --lens fisheye, 298 frames, searched pose: with it
# independent per corner the z error was 1.86 sigma (rational lens 1.96; NEES 11.3, 11.8); counted in the
# board's shared part 1.33 (NEES 6.8), and the clean radtan sequence's z 1.32 -> 1.14.
# A light field L moves the X-junction fit's corner by about XJUNCTION_LIGHT_PX x r |grad log L| per axis
# (r its disc's radius: the light's change across the disc, which its model of constant levels cannot
# follow). The shift follows the corner's polarity: all corners of a board move by one vector b, times +1 or
# -1 in the board's checkerboard pattern of corners (on the other-rig robot scene this alternating part,
# the board's mean of (-1)^(col+row) e, was 0.0114 px RMS per axis against 0.0015 that the corners' other
# errors leave in it; on the other sequences 0.0009-0.023, what their noise leaves). A pose or a
# calibration barely sees it (it cancels over neighbouring corners), so it is reported apart
# (CornerCovariances.alternating_px2) and the pose models it as that pattern (pose.estimate.shared_error).
# The saddle fit's light term H^-1 m does not apply to the X-junction fit: on bench/live.py's
# robot sequences its errors did not grow with that term (err^2 flat at 1.4-2.3e-4 px^2 over H^-1 m
# quantiles where the term ran from 4e-5 to 1.7e-3), which made their covariances' spread too wide
# (normalised error 3.8 for the most confident quarter of the corners, 0.3 for the least). Measured on
# renders of the other-rig robot scene (bench/live.py --scene other: light gradient 60 % / 35 %,
# vignetting 0.3, noise 2, blur 0.7; 3 stereo frames, 468 corners): RMS error per axis 0.0118 px, 0.0072
# without the gradient (the rest unchanged), 0.0108 without noise: 0.0093 px from the light at a median
# board |grad log L| of 0.0011 /px and discs of 7-12 px: its alternating part 1.28 r |grad log L| per axis (median
# over boards); on planar renders under the same light 0.74 (tests/test_corner_covariance.py). Fitted with the
# noise share over bench/corner_noise.py's conditions: 1.1 (normalised error under uneven light 2.1, 3.5 with
# 0.8), all of it alternating.
XJUNCTION_LIGHT_PX = 1.1
# The shift a light field puts on all of a board's corners alike, per unit gradient of log light (px^2; the
# shift is about LIGHT_SHIFT_PX2 x grad log L, towards the light). The light term above, H^-1 m, alternates
# in sign from corner to corner (the saddle's Hessian does) and so misses it: blur after the light moves
# every edge towards it whatever its polarity. Measured on bench/corner_noise.py's planar renders (the mean
# error of each board's corners against its light gradient): for the X-junction fit (the default refiner,
# on the raw image) 1.0 px^2 (normal), 1.6 (uneven light, correlation 0.84), 1.0 (foreshortened); for the
# saddle fit alone (on the detector's smoothed image, whose smoothing comes after the light) 6.7, 10.2
# (correlation 0.96) and 9.9. 2 is taken, for the default: with the saddle refiner chosen instead, corners
# under a strong light gradient are over-confident (uneven light: normalised error 4.1, not 2.9 with 14).
# Each corner's covariance holds it (isotropic); the pose models it as one offset of all corners along the
# gradient (edgecal.pose.estimate.shared_error).
LIGHT_SHIFT_PX2 = 2.0
#
# The share of a corner's error (sigma) that all corners of its board have in common, per refiner: the light
# field, blur and perspective over a board bias its corners alike, which does not average out over them as
# independent errors do, and a fit's residual cannot see a bias the pose absorbs. Measured on bench/live.py's
# rendered robot sequences (the mean error of each board's corners in each image against the truth): the
# saddle fit's boards 0.03 px against corners of 0.13 px on the hard sequence, cornerSubPix's 0.11 against
# 0.23 px from the same images (its window's weights make it the more sensitive to an asymmetric
# neighbourhood); fitted on the pose's NEES and per-axis error over the four sequences.
SHARED_FRACTION = {"saddle": 0.1, "cornersubpix": 0.2}
#
# cornerSubPix's model error: a floor (pixel sampling and locking, quantisation, the renderer's and a lens'
# small departures from an ideal X-junction) and the gain on the window's asymmetry
# |mean gradient| / contrast x half-width (an uneven light field, perspective across the window,
# neighbouring structure: a light gradient eps per pixel biases cornerSubPix by about
# eps x (mean level / contrast) x edge width x half-width). Fitted by maximum likelihood on 400 edgecal.synth
# renders of clean, normal, hard, uneven-light and strongly foreshortened planar views (then the gain
# lowered from 1.35 so that the uneven-light set, whose error is a bias along one direction, is not
# over-covered), with the noise term taken as it is: its Monte-Carlo check (noise-only repeats of one
# render) needs no factor, normalised error 1.9-2.2 (2.8 at 2 px blur). The floor refitted (0.010 ->
# 0.012) with the noise estimate of covariance_noise_sigma: clean tracked renders 3.05 -> 2.3.
CORNERSUBPIX_FLOOR_PX = 0.012
ASYMMETRY_GAIN = 1.2
# The half-resolution noise estimate over the full-resolution one on white noise, at most (edgecal.synth
# renders without JPEG, 271 views of five conditions: median 1.19, p90 1.39; beyond it only views of
# under 0.3 grey levels, where quantisation dominates; JPEG quality 60-95: 1.2-7).
WHITE_NOISE_HALF_RATIO = 1.4
# Largest condition number of a usable covariance: beyond it the corner is a line, not a point.
MAX_CONDITION = 1e6
# Where the light field is read: at +-SQUARE_PROBE x (a +- b) from the corner (a, b its steps to the next
# column and row), half way to the four squares' centres: inside them, 0.25 squares from their edges, also
# where a real board's outer squares are cut short at its rim.
SQUARE_PROBE = 0.25
# A saddle fit that would move the corner further than this (px) from where it is reported (the detector
# keeps cornerSubPix's position when the fit would move it more than saddle_refine's 1 px): the two
# refinements do not agree on one corner there, so it is unusable (rim corners misplaced by 1-10 px on
# real photos, corners on the wrong structure on renders, 1.1-1.2 px off).
MAX_SADDLE_STEP_PX = 1.0


def covariance_noise_sigma(grey: np.ndarray) -> float:
    """The image noise (grey levels, 1 sigma) that moves the corners.

    The detector's estimate (candidates.estimate_noise_sigma) looks at pixel-to-pixel differences, which
    JPEG compression and demosaicing remove while the noise at the scale of a corner window stays; the
    half-resolution estimate (candidates.half_resolution_noise_sigma) sees that noise, but image structure
    (edges in its 9x9 footprint) also inflates it, by up to WHITE_NOISE_HALF_RATIO on white noise. So what
    it sees beyond that ratio is added: sigma^2 = full^2 + max(0, half^2 - (ratio x full)^2): white noise
    keeps the full-resolution value, compressed noise gets about the half-resolution one. Both are measured
    on the 8-bit image, so they hold its quantisation; quantisation alone (1/12 grey level^2) is the floor, as
    a noise-free 8-bit image still has it (added on top, it made clean renders' covariances 1.2x too wide
    in sigma).
    """
    from edgecal.detection.candidates import estimate_noise_sigma, half_resolution_noise_sigma

    # Every 6th pixel at full resolution: tens of thousands of samples, a few times cheaper.
    full = estimate_noise_sigma(grey, stride=6)
    half = half_resolution_noise_sigma(grey)
    excess = max(0.0, half * half - (WHITE_NOISE_HALF_RATIO * full) ** 2)
    return float(np.sqrt(max(full * full + excess, 1.0 / 12.0)))


@njit(cache=True, nogil=True)
def _smooth_energy(v0: np.ndarray, v1: np.ndarray, p: int, g: np.ndarray, tmp0: np.ndarray, tmp1: np.ndarray,
                   u0: np.ndarray, u1: np.ndarray) -> tuple[float, float, float]:
    """Sum of u u^T over the plane for u = (g (x) g) scattered over v[:p, :p] (full correlation; tmp, u:
    work arrays of at least (p, p + 2r) and (p + 2r, p + 2r)).

    Both passes run along the first axis, so that the innermost loop runs over contiguous, independent
    outputs (a pass along the second axis scattered each input over k neighbours one at a time, ~2x
    slower); between them the first pass's result is transposed into tmp. The sums equal the earlier
    row-then-column order to rounding (~1e-15 relative)."""
    k = g.shape[0]
    q = p + k - 1
    for a in range(q):
        for b in range(p):
            u0[a, b] = 0.0
            u1[a, b] = 0.0
    for a in range(p):
        for t in range(k):
            gt = g[t]
            for b in range(p):
                u0[a + t, b] += v0[a, b] * gt
                u1[a + t, b] += v1[a, b] * gt
    for a in range(q):
        for b in range(p):
            tmp0[b, a] = u0[a, b]
            tmp1[b, a] = u1[a, b]
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
def window_statistics(smooth: np.ndarray, corners: np.ndarray, half: np.ndarray, gauss: np.ndarray,
                      noise: np.ndarray) -> np.ndarray:
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
    noise: (N,) bool, the corners that need B (the others, whose covariance the saddle fit gives, get 0:
    B is most of this kernel's cost).
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
        want_b = noise[i]
        if want_b:
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
                if want_b:
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
        bxx = bxy = byy = 0.0
        if want_b:
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



# Columns of the per-corner saddle-fit statistics returned by saddle_statistics.
S_HXX, S_HXY, S_HYY = 0, 1, 2          # Hessian of the fitted quadratic (grey levels per pixel^2)
S_NXX, S_NXY, S_NYY = 3, 4, 5          # covariance of its linear terms (d, e) for unit white noise in the raw image
S_STEPX, S_STEPY = 6, 7                # the Newton step left at the corner (px): ~0 where the saddle fit converged
S_LEVEL = 8                            # the fitted value at the saddle (grey levels)
S_OK = 9                               # 1 when the window lies inside the image and the fit is a saddle
S_LIGHTX, S_LIGHTY = 10, 11            # the light field's gradient at the saddle's level (grey levels per px)
S_AXIS_ANGLE = 12                      # the smallest angle between an edge and a pixel axis (radians)
S_LNXX, S_LNXY, S_LNYY = 13, 14, 15    # covariance of that light gradient for unit white noise in the raw image
N_SADDLE = 16


def saddle_statistics(smooth: np.ndarray, corners: np.ndarray, blur: np.ndarray, gauss: np.ndarray,
                      fit: np.ndarray, half: int, blur_half: int, spacing: np.ndarray,
                      steps: np.ndarray) -> np.ndarray:
    """The saddle fit (subpixel.saddle_refine) at each corner, and how raw image noise reaches it (N, N_SADDLE);
    see _saddle_statistics (one numba pass over all corners)."""
    return _saddle_statistics(smooth, corners, blur, gauss, fit, half, blur_half, spacing, steps,
                              _fit_correlations(np.ascontiguousarray(fit, dtype=np.float64), 2 * half + 1))


def _fit_correlations(fit: np.ndarray, n_fit: int) -> np.ndarray:
    """Cross-correlations (3, 2 n_fit - 1, 2 n_fit - 1) of the saddle fit's linear-term rows fit[3] (d) and
    fit[4] (e) on their n_fit x n_fit window: [0] d with d, [1] d with e, [2] e with e, at lags (dy, dx) from
    -(n_fit - 1); computed once per fit matrix."""
    key = (fit.shape, fit.tobytes())
    got = _FIT_CORRELATIONS.get(key)
    if got is None:
        rows = fit[3:5].reshape(2, n_fit, n_fit)
        lag = n_fit - 1
        got = np.zeros((3, 2 * lag + 1, 2 * lag + 1))
        for k, (j, m) in enumerate(((0, 0), (0, 1), (1, 1))):
            padded = np.zeros((n_fit + 2 * lag, n_fit + 2 * lag))
            padded[lag:lag + n_fit, lag:lag + n_fit] = rows[m]
            for dy in range(-lag, lag + 1):
                for dx in range(-lag, lag + 1):
                    shifted = padded[lag + dy:lag + dy + n_fit, lag + dx:lag + dx + n_fit]
                    got[k, dy + lag, dx + lag] = float((rows[j] * shifted).sum())
        _FIT_CORRELATIONS[key] = got
    return got


_FIT_CORRELATIONS: dict[tuple, np.ndarray] = {}


@njit(cache=True, nogil=True)
def _saddle_statistics(smooth: np.ndarray, corners: np.ndarray, blur: np.ndarray, gauss: np.ndarray,
                       fit: np.ndarray, half: int, blur_half: int, spacing: np.ndarray,
                       steps: np.ndarray, fit_corr: np.ndarray) -> np.ndarray:
    """The saddle fit (subpixel.saddle_refine) at each corner, and how raw image noise reaches it (N, N_SADDLE);
    fit_corr: _fit_correlations of ``fit``.

    smooth: (H, W) float32 the detector's smoothed image; corners: (N, 2) px; blur: (N,) the fit's extra
    smoothing sigma per corner; gauss: the detector's 1-D smoothing kernel (noise_kernel); fit: (5, (2 half +
    1)^2) the fit's weighted pseudo-inverse rows (a, b, c, d, e). The fit is repeated exactly as the refiner
    does it (patch resampled at the corner, smoothed, fitted). Raw pixel noise reaches the fit's linear terms
    through the detector's Gaussian, the bilinear resampling and the extra smoothing: one separable kernel,
    through which each fit row is carried exactly (correlated samples included).

    steps: (N, 2, 2) the board's local steps (px) to the next column and row at each corner (grid_steps;
    NaN where unknown: then along the fit's asymptotes, ``spacing`` (N,) long). They give the edges'
    angles to the pixel axes and the squares' centres, where the light field is read: diagonally
    opposite squares have the same colour, so their difference is the light field's, whatever the
    perspective (gradient of log light from the two pairs, times the saddle's level; a zero black level
    is assumed).
    """
    h, w = smooth.shape
    m = corners.shape[0]
    out = np.zeros((m, N_SADDLE))
    side = 2 * (half + blur_half) + 1
    n_fit = 2 * half + 1
    nk = 2 * blur_half + 1
    kg = gauss.shape[0]
    nc = nk + kg                    # length of the combined 1-D kernel (extra blur * Gaussian * bilinear)
    patch = np.empty((side, side))
    rows = np.empty((side, n_fit))
    win = np.empty(n_fit * n_fit)
    kern = np.empty(nk)
    kb = np.empty(nk + kg - 1)
    cx = np.empty(nc)
    cy = np.empty(nc)
    lag = n_fit - 1  # the fit rows' correlations vanish beyond it
    n_lag = 2 * lag + 1
    rcx = np.empty(n_lag)
    rcy = np.empty(n_lag)
    r0 = half + blur_half
    gauss2 = 0.0
    for t in range(kg):
        gauss2 += gauss[t] * gauss[t]
    gauss2 = gauss2 * gauss2
    for i in range(m):
        x = corners[i, 0]
        y = corners[i, 1]
        if not (math.isfinite(x) and math.isfinite(y)):
            continue
        if x < r0 + 1 or y < r0 + 1 or x > w - r0 - 2 or y > h - r0 - 2:
            continue
        total = 0.0
        for k in range(nk):
            kern[k] = math.exp(-((k - blur_half) ** 2) / (2.0 * blur[i] * blur[i]))
            total += kern[k]
        for k in range(nk):
            kern[k] /= total
        x0 = int(math.floor(x))
        y0 = int(math.floor(y))
        fx = x - x0
        fy = y - y0
        for a in range(side):
            yy = y0 + a - r0
            for b in range(side):
                xx = x0 + b - r0
                patch[a, b] = ((smooth[yy, xx] * (1.0 - fx) + smooth[yy, xx + 1] * fx) * (1.0 - fy)
                               + (smooth[yy + 1, xx] * (1.0 - fx) + smooth[yy + 1, xx + 1] * fx) * fy)
        # each output's taps summed in order (as the refiner does), a row of outputs at a time
        for a in range(side):
            for b in range(n_fit):
                rows[a, b] = 0.0
            for k in range(nk):
                kk = kern[k]
                for b in range(n_fit):
                    rows[a, b] += patch[a, b + k] * kk
        for a in range(n_fit):
            for b in range(n_fit):
                win[a * n_fit + b] = 0.0
            for k in range(nk):
                kk = kern[k]
                for b in range(n_fit):
                    win[a * n_fit + b] += rows[a + k, b] * kk
        c = fit_coefficients(fit, win, 6)
        hxx = 2.0 * c[0]
        hxy = c[1]
        hyy = 2.0 * c[2]
        det = hxx * hyy - hxy * hxy
        out[i, S_HXX] = hxx
        out[i, S_HXY] = hxy
        out[i, S_HYY] = hyy
        out[i, S_LEVEL] = c[5]
        if not det < 0.0:
            continue
        out[i, S_STEPX] = -(hyy * c[3] - hxy * c[4]) / det
        out[i, S_STEPY] = -(hxx * c[4] - hxy * c[3]) / det
        out[i, S_OK] = 1.0
        # The board's steps to the next column (a) and row (b) at this corner: from the grid when the
        # caller has it, else along the fitted quadratic's asymptotes (at +-psi from H's eigenvector e1),
        # a square long (the asymptotes are the edges only where the four sectors are alike).
        ax_ = steps[i, 0, 0]
        ay_ = steps[i, 0, 1]
        bx_ = steps[i, 1, 0]
        by_ = steps[i, 1, 1]
        if not (math.isfinite(ax_) and math.isfinite(ay_) and math.isfinite(bx_) and math.isfinite(by_)):
            l1 = 0.5 * (hxx + hyy) + math.hypot(0.5 * (hxx - hyy), hxy)
            l2 = 0.5 * (hxx + hyy) - math.hypot(0.5 * (hxx - hyy), hxy)
            phi = 0.5 * math.atan2(2.0 * hxy, hxx - hyy)
            psi = math.atan(math.sqrt(l1 / -l2)) if l2 < 0.0 else 0.25 * math.pi
            ax_ = spacing[i] * math.cos(phi + psi)
            ay_ = spacing[i] * math.sin(phi + psi)
            bx_ = spacing[i] * math.cos(phi - psi)
            by_ = spacing[i] * math.sin(phi - psi)
        axis = 0.5 * math.pi
        for ex, ey in ((ax_, ay_), (bx_, by_)):
            tilt = math.atan2(abs(ey), abs(ex))
            axis = min(axis, tilt, 0.5 * math.pi - tilt)
        out[i, S_AXIS_ANGLE] = axis
        # The four squares lie along +-(a + b) and +-(a - b); opposite squares have the same colour, so
        # (I(q + v) - I(q - v)) / (I(q + v) + I(q - v)) = grad log L . v for both v.
        vx = (SQUARE_PROBE * (ax_ + bx_), SQUARE_PROBE * (ax_ - bx_))
        vy = (SQUARE_PROBE * (ay_ + by_), SQUARE_PROBE * (ay_ - by_))
        g = np.zeros(2)
        gvar = np.zeros(2)
        inside = True
        for k in range(2):
            vals = np.zeros(2)
            for sgn in range(2):
                px = x + (vx[k] if sgn == 0 else -vx[k])
                py = y + (vy[k] if sgn == 0 else -vy[k])
                if not (0.0 <= px < w - 1 and 0.0 <= py < h - 1):
                    inside = False
                    break
                ix = int(px)
                iy = int(py)
                fx_ = px - ix
                fy_ = py - iy
                vals[sgn] = ((smooth[iy, ix] * (1.0 - fx_) + smooth[iy, ix + 1] * fx_) * (1.0 - fy_)
                             + (smooth[iy + 1, ix] * (1.0 - fx_) + smooth[iy + 1, ix + 1] * fx_) * fy_)
            if not inside or vals[0] + vals[1] <= 2.0:
                inside = False
                break
            g[k] = (vals[0] - vals[1]) / (vals[0] + vals[1])
            # its noise: two samples of the smoothed image, each with gauss2 (sum of the 2-D kernel squared)
            gvar[k] = 2.0 * gauss2 / ((vals[0] + vals[1]) ** 2)
        dv = vx[0] * vy[1] - vx[1] * vy[0]
        if inside and abs(dv) > 1e-9:
            # [v0; v1] grad log L = g, times the saddle's level; and how noise in g reaches it
            i00 = vy[1] / dv
            i01 = -vy[0] / dv
            i10 = -vx[1] / dv
            i11 = vx[0] / dv
            out[i, S_LIGHTX] = c[5] * (i00 * g[0] + i01 * g[1])
            out[i, S_LIGHTY] = c[5] * (i10 * g[0] + i11 * g[1])
            c2 = c[5] * c[5]
            out[i, S_LNXX] = c2 * (i00 * i00 * gvar[0] + i01 * i01 * gvar[1])
            out[i, S_LNXY] = c2 * (i00 * i10 * gvar[0] + i01 * i11 * gvar[1])
            out[i, S_LNYY] = c2 * (i10 * i10 * gvar[0] + i11 * i11 * gvar[1])
        # The combined kernel from a raw pixel to a window sample, per axis: extra blur * Gaussian, then
        # the bilinear pair (1 - f, f).
        for t in range(nk + kg - 1):
            kb[t] = 0.0
        for k in range(nk):
            for t in range(kg):
                kb[k + t] += kern[k] * gauss[t]
        for t in range(nc):
            cx[t] = 0.0
            cy[t] = 0.0
        for t in range(nk + kg - 1):
            cx[t] += kb[t] * (1.0 - fx)
            cx[t + 1] += kb[t] * fx
            cy[t] += kb[t] * (1.0 - fy)
            cy[t + 1] += kb[t] * fy
        # The linear terms' noise: sum over the raw pixels of the products of their weights (each fit row
        # spread by the separable kernel cy x cx), as the fit rows' cross-correlations (fixed, per lag)
        # times the kernel's autocorrelation per axis: ~1/4 of the work of spreading the rows.
        for t in range(n_lag):
            s = t - lag
            ax = 0.0
            ay = 0.0
            for u in range(max(0, -s), min(nc, nc - s)):
                ax += cx[u] * cx[u + s]
                ay += cy[u] * cy[u + s]
            rcx[t] = ax
            rcy[t] = ay
        sdd = sde = see = 0.0
        for ty in range(n_lag):
            pdd = pde = pee = 0.0
            for tx in range(n_lag):
                pdd += fit_corr[0, ty, tx] * rcx[tx]
                pde += fit_corr[1, ty, tx] * rcx[tx]
                pee += fit_corr[2, ty, tx] * rcx[tx]
            sdd += pdd * rcy[ty]
            sde += pde * rcy[ty]
            see += pee * rcy[ty]
        out[i, S_NXX] = sdd
        out[i, S_NXY] = sde
        out[i, S_NYY] = see
    return out


def noise_kernel(smoothing_sigma: float) -> np.ndarray:
    """The detector's 1-D Gaussian (candidates.smooth_image), float64: how one raw pixel's noise reaches the
    smoothed image (read-only: one array per sigma, made once)."""
    return _noise_kernel(float(smoothing_sigma))


@lru_cache(maxsize=64)
def _noise_kernel(smoothing_sigma: float) -> np.ndarray:
    import cv2

    ksize = 2 * int(np.ceil(2.5 * smoothing_sigma)) + 1
    kernel = cv2.getGaussianKernel(ksize, smoothing_sigma, cv2.CV_64F).ravel()
    kernel.setflags(write=False)
    return kernel


class CornerCovariances(NamedTuple):
    """What corner_covariance says of N corners.

    covariance: (N, 2, 2) px^2, OpenCV pixel axes, NaN for an unusable corner. shared_px2: (N,) the part of
    it (px^2 per axis) that the corners of its board share (SHARED_FRACTION, and the lens-bend correction's
    error, BEND_ERROR_SHARE), NaN for an unusable corner.
    unusable: (N,) reasons, "" for a usable corner. light_gradient: (N, 2)
    the gradient of log light (1/px, image axes) at each corner, its board's mean reading (saddle fit with
    ``boards``; the corner's own reading without), zeros where none was read (cornerSubPix).
    alternating_px2: (N,) the part of the covariance (px^2 per axis) that is the board's light shift in its
    checkerboard pattern (XJUNCTION_LIGHT_PX; zero for the other refiners), NaN for an unusable corner.
    """

    covariance: np.ndarray
    shared_px2: np.ndarray
    unusable: list[str]
    light_gradient: np.ndarray
    alternating_px2: np.ndarray


def corner_covariance(grey: np.ndarray, smooth: np.ndarray, smoothing_sigma: float, corners: np.ndarray,
                      spacing: np.ndarray | None = None, noise_sigma: float | None = None, *, refiner: str,
                      steps: np.ndarray | None = None, boards: np.ndarray | None = None,
                      xjunction_fitted: np.ndarray | None = None, bend_px: np.ndarray | None = None,
                      xjunction_noise: np.ndarray | None = None) -> CornerCovariances:
    """2x2 covariance (px^2, OpenCV pixel axes) of each refined corner, the part its board's corners share,
    and why a corner is unusable (CornerCovariances).

    grey: (H, W) uint8, the image; smooth: the detector's smoothed float32 image of it (candidates.smooth_image
    with ``smoothing_sigma``) on which the corners were refined; corners: (N, 2) pixels; spacing: (N,)
    the local square size the refinement window came from (default: nearest_spacing of the corners).
    noise_sigma: covariance_noise_sigma of the whole image, when grey is a window of it or the caller has it
    (default: measured on grey). refiner: the refinement that placed the corners, "cornersubpix" or
    "saddle" (subpixel.REFINERS); a corner the saddle fit does not see as a saddle kept cornerSubPix's
    position and gets its covariance. steps: (N, 2, 2) the board's local steps to the next column and row
    (grid_steps), for the saddle fit's model error (default: read off the fit); boards: (N,) int, which
    board each corner is on: the light field, smooth over a board, is averaged over its corners (default:
    each corner alone). xjunction_fitted: (N,) bool, refiner "xjunction": the corners its fit placed
    (Detection.xjunction_fitted; default all); the others get the saddle fit's covariance. bend_px: (N,)
    the lens-bend correction's length on each (Detection.bend_px; default none), BEND_ERROR_SHARE of it
    added per axis. xjunction_noise: (N, 2, 2) the X-junction fit's covariance per unit noise variance
    (Detection.xjunction_noise), its corners' noise term (default, or NaN: the saddle fit's, scaled).
    """
    if refiner not in REFINERS:
        raise ValueError(f"unknown refiner {refiner!r} ({', '.join(REFINERS)})")
    corners = np.ascontiguousarray(np.asarray(corners, dtype=np.float64).reshape(-1, 2))
    n = len(corners)
    if n == 0:
        return CornerCovariances(np.zeros((0, 2, 2)), np.zeros(0), [], np.zeros((0, 2)), np.zeros(0))
    if spacing is None:
        spacing = nearest_spacing(corners)
    st, sd, half = corner_statistics(smooth, smoothing_sigma, corners, spacing, refiner, steps)
    noise2 = (covariance_noise_sigma(grey) if noise_sigma is None else noise_sigma) ** 2
    xj = np.ones(n, dtype=np.bool_) if xjunction_fitted is None else \
        np.ascontiguousarray(np.asarray(xjunction_fitted, dtype=np.bool_).reshape(n))
    bend = np.zeros(n) if bend_px is None else np.ascontiguousarray(np.asarray(bend_px, dtype=np.float64).reshape(n))
    board = np.zeros(n, dtype=np.int64) if boards is None else \
        np.ascontiguousarray(np.asarray(boards, dtype=np.int64).reshape(n))
    disc = xjunction_disc_radius(spacing) if refiner == "xjunction" else np.zeros(n)
    fit_noise = np.full((n, 2, 2), np.nan) if xjunction_noise is None else \
        np.ascontiguousarray(np.asarray(xjunction_noise, dtype=np.float64).reshape(n, 2, 2))
    cov, shared, light, alternating, code = _covariances(
        st, sd, half, np.ascontiguousarray(disc, dtype=np.float64), float(noise2),
        REFINERS.index(refiner), boards is not None, board, xjunction_fitted is not None, xj, bend, fit_noise)
    return CornerCovariances(cov, shared, [_REASONS[c] for c in code.tolist()], light, alternating)


def corner_statistics(smooth: np.ndarray, smoothing_sigma: float, corners: np.ndarray, spacing: np.ndarray,
                      refiner: str, steps: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """What corner_covariance computes its covariances from (its arguments of the same names; ``corners``
    (N, 2) float64 contiguous): (window_statistics (N, N_STATS), saddle_statistics (N, N_SADDLE), zeros for
    refiner "cornersubpix", the cornerSubPix windows' half-widths (N,))."""
    n = len(corners)
    half = subpixel_window(spacing)
    smooth = np.ascontiguousarray(smooth, dtype=np.float32)
    gauss = noise_kernel(smoothing_sigma)
    if refiner in ("saddle", "xjunction"):
        fit, fit_half, blur_half, blur = saddle_fit_setup(spacing)
        if steps is None:
            steps = np.full((n, 2, 2), np.nan)
        sd = saddle_statistics(smooth, corners, blur, gauss, np.ascontiguousarray(fit), fit_half, blur_half,
                               np.ascontiguousarray(spacing, dtype=np.float64),
                               np.ascontiguousarray(steps, dtype=np.float64).reshape(n, 2, 2))
        # cornerSubPix's noise term only where the saddle fit gives no covariance
        st = window_statistics(smooth, corners, half, gauss, ~(sd[:, S_OK] > 0))
    else:
        sd = np.zeros((n, N_SADDLE))
        st = window_statistics(smooth, corners, half, gauss, np.ones(n, dtype=np.bool_))
    return st, sd, half


# Unusable reasons by the code _covariances returns (0: usable).
_REASONS = ("", REASON_BORDER, REASON_FLAT, REASON_DEGENERATE, REASON_DISAGREE, REASON_NO_FIT)
# SHARED_FRACTION for the kernel (numba reads no dicts)
_SHARED_CORNERSUBPIX = SHARED_FRACTION["cornersubpix"]
_SHARED_SADDLE = SHARED_FRACTION["saddle"]


def covariances_reference(st: np.ndarray, sd: np.ndarray, half: np.ndarray, spacing: np.ndarray, noise2: float,
                          refiner: str, boards: np.ndarray | None = None, xjunction_fitted: np.ndarray | None = None,
                          bend_px: np.ndarray | None = None, xjunction_noise: np.ndarray | None = None
                          ) -> CornerCovariances:
    """corner_covariance from the window and saddle statistics (``st`` (N, N_STATS), ``sd`` (N, N_SADDLE)),
    in numpy: the reference the one-pass kernel (_covariances) is tested against."""
    n = len(st)
    a = st[:, W_AXX] * st[:, W_AYY] - st[:, W_AXY] ** 2
    tr = st[:, W_AXX] + st[:, W_AYY]
    inside_window = st[:, W_INSIDE] > 0
    ok = inside_window & (tr > 0) & (a > tr * tr / MAX_CONDITION)
    cov = _cornersubpix_covariance(st, half, noise2, np.where(ok, a, 1.0))
    shared_fraction = np.full(n, SHARED_FRACTION["cornersubpix"])
    alternating = np.zeros(n)
    bend_shared = np.zeros(n)  # the lens-bend correction's error, all shared (BEND_ERROR_SHARE)
    if refiner in ("saddle", "xjunction"):
        fitted = (sd[:, S_OK] > 0) & inside_window
        xj = np.ones(n, dtype=bool) if xjunction_fitted is None else np.asarray(xjunction_fitted, bool).reshape(n)
        if boards is not None:
            sd = _board_light(sd, np.asarray(boards, dtype=np.int64).reshape(n))
        read = fitted & (np.abs(sd[:, S_LEVEL]) > 1.0)
        light = np.zeros((n, 2))
        light[read] = sd[read][:, [S_LIGHTX, S_LIGHTY]] / sd[read, S_LEVEL, None]
        if refiner == "xjunction":
            g2 = np.zeros(n)
            g2[read] = np.maximum(np.sum(light[read] ** 2, axis=1)
                                  - noise2 * (sd[read, S_LNXX] + sd[read, S_LNYY]) / sd[read, S_LEVEL] ** 2, 0.0)
            light_px = XJUNCTION_LIGHT_PX * xjunction_disc_radius(spacing) * np.sqrt(g2)
            placed = fitted & xj
            alternating[placed] = light_px[placed] ** 2
            bend = np.zeros(n) if bend_px is None else np.asarray(bend_px, dtype=np.float64).reshape(n)
            fit_noise = (np.full((n, 2, 2), np.nan) if xjunction_noise is None
                         else np.asarray(xjunction_noise, dtype=np.float64).reshape(n, 2, 2))
            cov[placed] = _xjunction_covariance(sd[placed], noise2, light_px[placed], bend[placed], fit_noise[placed])
            bend_shared[placed] = (BEND_ERROR_SHARE * bend[placed]) ** 2
            held = fitted & ~placed            # where the X-junction fit did not run: the saddle fit's corner
            cov[held] = _saddle_covariance(sd[held], noise2)
        else:
            cov[fitted] = _saddle_covariance(sd[fitted], noise2)
        shared_fraction[fitted] = SHARED_FRACTION["saddle"]
        shift2 = LIGHT_SHIFT_PX2 ** 2 * np.sum(light[read] ** 2, axis=1)
        cov[read] += 0.5 * shift2[:, None, None] * np.eye(2)
        ok |= fitted
        disagree = fitted & (np.hypot(sd[:, S_STEPX], sd[:, S_STEPY]) > MAX_SADDLE_STEP_PX)
        unfitted = inside_window & ~fitted
        if refiner == "xjunction" and xjunction_fitted is not None:
            unfitted &= ~xj
    else:
        disagree = np.zeros(n, dtype=bool)
        unfitted = np.zeros(n, dtype=bool)
        light = np.zeros((n, 2))
    cov = 0.5 * (cov + np.transpose(cov, (0, 2, 1)))
    ev_min = 0.5 * (cov[:, 0, 0] + cov[:, 1, 1]) - np.hypot(0.5 * (cov[:, 0, 0] - cov[:, 1, 1]), cov[:, 0, 1])
    finite = np.isfinite(cov).all(axis=(1, 2))
    reasons = np.select([~inside_window, tr <= 0, ~(ok & finite & (ev_min > 0)), disagree, unfitted],
                        [REASON_BORDER, REASON_FLAT, REASON_DEGENERATE, REASON_DISAGREE, REASON_NO_FIT],
                        default="")
    cov[reasons != ""] = np.nan
    shared = shared_fraction ** 2 * (0.5 * (cov[:, 0, 0] + cov[:, 1, 1]) - alternating) + bend_shared
    light[reasons != ""] = 0.0
    alternating[reasons != ""] = np.nan
    return CornerCovariances(cov, shared, reasons.tolist(), light, alternating)


@njit(cache=True, nogil=True, inline="always")
def _inverse_2x2(a: float, b: float, c: float, d: float) -> tuple[float, float, float, float]:
    """The inverse of [[a, b], [c, d]] (row-major)."""
    det = a * d - b * c
    return d / det, -b / det, -c / det, a / det


@njit(cache=True, nogil=True, inline="always")
def _sandwich(s: float, m00: float, m01: float, m10: float, m11: float, n00: float, n01: float, n11: float
              ) -> tuple[float, float, float, float]:
    """(s M) N M for a 2x2 M (row-major) and a symmetric N (its upper half), in numpy's order of
    ``s * m @ n @ m``."""
    l00 = s * m00
    l01 = s * m01
    l10 = s * m10
    l11 = s * m11
    t00 = l00 * n00 + l01 * n01
    t01 = l00 * n01 + l01 * n11
    t10 = l10 * n00 + l11 * n01
    t11 = l10 * n01 + l11 * n11
    return t00 * m00 + t01 * m10, t00 * m01 + t01 * m11, t10 * m00 + t11 * m10, t10 * m01 + t11 * m11


@njit(cache=True, nogil=True)
def _covariances(st: np.ndarray, sd: np.ndarray, half: np.ndarray, disc: np.ndarray, noise2: float,
                 refiner: int, by_board: bool, boards: np.ndarray, xj_given: bool, xj: np.ndarray,
                 bend: np.ndarray, fit_noise: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """corner_covariance's covariances from the window and saddle statistics in one pass over the corners:
    (covariance (N, 2, 2), shared_px2 (N,), light_gradient (N, 2), alternating_px2 (N,), reason codes (N,)
    int64, _REASONS). ``disc`` (N,): xjunction_disc_radius; ``refiner``: index in REFINERS (0 cornerSubPix:
    ``sd`` unused); ``by_board``: average
    the light field over each board of ``boards`` (N,) (_board_light); ``xj_given``: ``xj`` (N,) says which
    corners the X-junction fit placed (else all); ``bend`` (N,) px; ``fit_noise`` (N, 2, 2) the X-junction
    fit's covariance per unit noise variance (NaN: the saddle fit's term scaled). The same formulas, in the same order,
    as covariances_reference (whose dozens of small array operations cost ~10x this)."""
    n = st.shape[0]
    cov = np.empty((n, 2, 2))
    shared = np.empty(n)
    light = np.zeros((n, 2))
    alternating = np.zeros(n)
    code = np.zeros(n, dtype=np.int64)
    fits = refiner != 0
    # the light field per board (_board_light): the boards' mean gradient of log light and its noise
    lx_col = np.empty(n)
    ly_col = np.empty(n)
    ln_col = np.empty((n, 3))
    for i in range(n):
        if fits:
            lx_col[i] = sd[i, S_LIGHTX]
            ly_col[i] = sd[i, S_LIGHTY]
            ln_col[i, 0] = sd[i, S_LNXX]
            ln_col[i, 1] = sd[i, S_LNXY]
            ln_col[i, 2] = sd[i, S_LNYY]
    if fits and by_board:
        k = 0
        for i in range(n):
            k = max(k, boards[i] + 1)
        count = np.zeros(k, dtype=np.int64)
        sums = np.zeros((k, 2))
        vsum = np.zeros((k, 3))
        any_read = False
        for i in range(n):
            level = sd[i, S_LEVEL]
            if sd[i, S_OK] > 0 and abs(level) > 1.0 and (sd[i, S_LIGHTX] != 0 or sd[i, S_LIGHTY] != 0):
                any_read = True
                b = boards[i]
                count[b] += 1
                sums[b, 0] += sd[i, S_LIGHTX] / level
                sums[b, 1] += sd[i, S_LIGHTY] / level
                vsum[b, 0] += sd[i, S_LNXX] / level ** 2
                vsum[b, 1] += sd[i, S_LNXY] / level ** 2
                vsum[b, 2] += sd[i, S_LNYY] / level ** 2
        if any_read:
            for i in range(n):
                b = boards[i]
                level = sd[i, S_LEVEL]
                c = max(count[b], 1)
                lx_col[i] = level * (sums[b, 0] / c)
                ly_col[i] = level * (sums[b, 1] / c)
                for j in range(3):
                    ln_col[i, j] = level ** 2 * vsum[b, j] / c ** 2
    for i in range(n):
        axx = st[i, W_AXX]
        axy = st[i, W_AXY]
        ayy = st[i, W_AYY]
        a = axx * ayy - axy ** 2
        tr = axx + ayy
        inside = st[i, W_INSIDE] > 0
        ok = inside and tr > 0 and a > tr * tr / MAX_CONDITION
        # cornerSubPix's covariance (_cornersubpix_covariance)
        det = a if ok else 1.0
        ai00 = st[i, W_AYY] / det
        ai01 = -st[i, W_AXY] / det
        ai11 = st[i, W_AXX] / det
        c00, c01, c10, c11 = _sandwich(noise2, ai00, ai01, ai01, ai11, st[i, W_BXX], st[i, W_BXY], st[i, W_BYY])
        contrast = max(st[i, W_CONTRAST], 1e-6)
        asymmetry = math.hypot(st[i, W_MX], st[i, W_MY]) / contrast * half[i]
        model2 = CORNERSUBPIX_FLOOR_PX ** 2 + (ASYMMETRY_GAIN * asymmetry) ** 2
        g = model2 * 0.5 * tr
        c00 += g * ai00
        c01 += g * ai01
        c10 += g * ai01
        c11 += g * ai11
        sf = _SHARED_CORNERSUBPIX
        alt = 0.0
        bend2 = 0.0
        disagree = False
        unfitted = False
        lx = 0.0
        ly = 0.0
        if fits:
            fitted = sd[i, S_OK] > 0 and inside
            level = sd[i, S_LEVEL]
            read = fitted and abs(level) > 1.0
            if read:
                lx = lx_col[i] / level
                ly = ly_col[i] / level
            if fitted:
                hi00, hi01, hi10, hi11 = _inverse_2x2(sd[i, S_HXX], sd[i, S_HXY], sd[i, S_HXY], sd[i, S_HYY])
                # saddle_noise_term: H^-1 N H^-1 noise2
                q00, q01, q10, q11 = _sandwich(noise2, hi00, hi01, hi10, hi11, sd[i, S_NXX], sd[i, S_NXY],
                                               sd[i, S_NYY])
                tan = math.tan(sd[i, S_AXIS_ANGLE])
                locking = math.exp(-2.0 * math.pi ** 2 * (PIXEL_LOCK_LENGTH_PX * tan) ** 2)
                if refiner == 2 and xj[i]:
                    g2 = 0.0
                    if read:
                        g2 = max(lx ** 2 + ly ** 2 - noise2 * (ln_col[i, 0] + ln_col[i, 2]) / level ** 2, 0.0)
                    light_px = XJUNCTION_LIGHT_PX * disc[i] * math.sqrt(g2)
                    alt = light_px ** 2
                    bend2 = (BEND_ERROR_SHARE * bend[i]) ** 2
                    m2 = (XJUNCTION_FLOOR_PX ** 2 + (XJUNCTION_LOCK_SHARE * PIXEL_LOCK_PX) ** 2 * locking
                          + light_px ** 2 + bend2)
                    f = fit_noise[i]
                    if np.isfinite(f[0, 0]) and np.isfinite(f[0, 1]) and np.isfinite(f[1, 1]):
                        c00 = noise2 * f[0, 0] + m2
                        c01 = noise2 * f[0, 1]
                        c10 = noise2 * f[1, 0]
                        c11 = noise2 * f[1, 1] + m2
                    else:
                        c00 = XJUNCTION_NOISE_SHARE * q00 + m2
                        c01 = XJUNCTION_NOISE_SHARE * q01
                        c10 = XJUNCTION_NOISE_SHARE * q10
                        c11 = XJUNCTION_NOISE_SHARE * q11 + m2
                else:
                    # _saddle_covariance: the light's bias H^-1 m and the probe's own noise on it
                    b0 = hi00 * lx_col[i] + hi01 * ly_col[i]
                    b1 = hi10 * lx_col[i] + hi11 * ly_col[i]
                    p00, _p01, _p10, p11 = _sandwich(1.0, hi00, hi01, hi10, hi11, ln_col[i, 0], ln_col[i, 1],
                                                     ln_col[i, 2])
                    probe_noise = noise2 * (p00 + p11)
                    bias2 = max(b0 ** 2 + b1 ** 2 - PROBE_NOISE_SHARE * probe_noise, 0.0)
                    m2 = (SADDLE_FLOOR_PX ** 2 + PIXEL_LOCK_PX ** 2 * locking + 0.5 * bias2
                          + 0.5 * (sd[i, S_STEPX] ** 2 + sd[i, S_STEPY] ** 2))
                    c00 = q00 + m2
                    c01 = q01
                    c10 = q10
                    c11 = q11 + m2
                sf = _SHARED_SADDLE
            if read:
                shift2 = LIGHT_SHIFT_PX2 ** 2 * (lx ** 2 + ly ** 2)
                c00 += 0.5 * shift2
                c11 += 0.5 * shift2
            ok = ok or fitted
            disagree = fitted and math.hypot(sd[i, S_STEPX], sd[i, S_STEPY]) > MAX_SADDLE_STEP_PX
            unfitted = inside and not fitted
            if refiner == 2 and xj_given:
                unfitted = unfitted and not xj[i]
        off = 0.5 * (c01 + c10)
        ev_min = 0.5 * (c00 + c11) - math.hypot(0.5 * (c00 - c11), off)
        finite = math.isfinite(c00) and math.isfinite(off) and math.isfinite(c11)
        if not inside:
            code[i] = 1
        elif tr <= 0:
            code[i] = 2
        elif not (ok and finite and ev_min > 0):
            code[i] = 3
        elif disagree:
            code[i] = 4
        elif unfitted:
            code[i] = 5
        if code[i]:
            cov[i, 0, 0] = cov[i, 0, 1] = cov[i, 1, 0] = cov[i, 1, 1] = np.nan
            shared[i] = np.nan
            alternating[i] = np.nan
            continue
        cov[i, 0, 0] = c00
        cov[i, 0, 1] = off
        cov[i, 1, 0] = off
        cov[i, 1, 1] = c11
        shared[i] = sf ** 2 * (0.5 * (c00 + c11) - alt) + bend2
        light[i, 0] = lx
        light[i, 1] = ly
        alternating[i] = alt
    return cov, shared, light, alternating, code


def without_light_shift(covariance: np.ndarray, light_gradient: np.ndarray | None,
                        alternating_px2: np.ndarray | None = None) -> np.ndarray:
    """Corner covariances (N, 2, 2) less the light field's shift that all corners of their board share
    (LIGHT_SHIFT_PX2 x |light_gradient| (N, 2), as corner_covariance adds it) and less its alternating
    part (``alternating_px2`` (N,), CornerCovariances): what calibration weighs by, since each view's pose
    absorbs a shift common to its corners (weighted by the whole covariance, the planar renders' focal error
    was 7 % larger) and the alternating shift cancels over neighbouring corners. Unchanged without them."""
    out = covariance
    if light_gradient is not None:
        shift2 = LIGHT_SHIFT_PX2 ** 2 * np.sum(np.asarray(light_gradient, dtype=np.float64) ** 2, axis=1)
        out = out - 0.5 * shift2[:, None, None] * np.eye(2)
    if alternating_px2 is not None:
        out = out - np.asarray(alternating_px2, dtype=np.float64)[:, None, None] * np.eye(2)
    return out


def _cornersubpix_covariance(st: np.ndarray, half: np.ndarray, noise2: float, det: np.ndarray) -> np.ndarray:
    """cornerSubPix's corners (N, 2, 2): the noise sandwich A^-1 B A^-1 plus the model error in A^-1's shape
    (window statistics st (N, N_STATS), half-widths, noise variance, det A with 1 where A is singular)."""
    ai = (np.stack([st[:, W_AYY], -st[:, W_AXY], -st[:, W_AXY], st[:, W_AXX]], axis=1).reshape(-1, 2, 2)
          / det[:, None, None])
    b = np.stack([st[:, W_BXX], st[:, W_BXY], st[:, W_BXY], st[:, W_BYY]], axis=1).reshape(-1, 2, 2)
    cov_noise = noise2 * ai @ b @ ai
    contrast = np.maximum(st[:, W_CONTRAST], 1e-6)
    asymmetry = np.hypot(st[:, W_MX], st[:, W_MY]) / contrast * half
    model2 = CORNERSUBPIX_FLOOR_PX ** 2 + (ASYMMETRY_GAIN * asymmetry) ** 2
    tr = st[:, W_AXX] + st[:, W_AYY]
    # In A^-1's shape, scaled so that an isotropic corner gets model2 per axis: a light gradient biases
    # cornerSubPix along its weak direction (measured on the pose: isotropic instead, the tracked pose's
    # NEES under a strong light gradient went from 8.7 to 13.4, position RMS 0.026 to 0.028 mm).
    return cov_noise + (model2 * 0.5 * tr)[:, None, None] * ai


def _saddle_covariance(sd: np.ndarray, noise2: float) -> np.ndarray:
    """The saddle fit's corners (N, 2, 2) from its statistics sd (N, N_SADDLE) and the noise variance.

    Noise: the fit's saddle s solves H s = -(d, e), so dq = -H^-1 (dd, de) and Sigma = H^-1 N H^-1 x
    noise2 (N: the covariance of the linear terms per unit raw noise). Model error, isotropic: the floor
    with the pixel-locking of an edge along a pixel axis, the bias a light field puts on the fit (its
    gradient m at the saddle's level adds m to the linear terms, moving the saddle by H^-1 m), and the
    Newton step the fit still sees (not converged, or refused).
    """
    hi = np.linalg.inv(np.stack([sd[:, S_HXX], sd[:, S_HXY], sd[:, S_HXY], sd[:, S_HYY]],
                                axis=1).reshape(-1, 2, 2))
    bias = (hi @ sd[:, [S_LIGHTX, S_LIGHTY], None])[:, :, 0]
    # The light probe's own noise inflates |bias|^2 by the trace of its covariance (S_LN*). Taking it off
    # (PROBE_NOISE_SHARE 1) predicted 2.6x the probe scatter seen on clean renders and left the uneven-light
    # set 3x over-confident, so it is not taken off (0): on noisy images the light term double-counts noise.
    ln = np.stack([sd[:, S_LNXX], sd[:, S_LNXY], sd[:, S_LNXY], sd[:, S_LNYY]], axis=1).reshape(-1, 2, 2)
    probe_noise = noise2 * np.trace(hi @ ln @ hi, axis1=1, axis2=2)
    bias2 = np.maximum((bias ** 2).sum(axis=1) - PROBE_NOISE_SHARE * probe_noise, 0.0)
    model2 = (SADDLE_FLOOR_PX ** 2 + PIXEL_LOCK_PX ** 2 * _locking(sd) + 0.5 * bias2
              + 0.5 * (sd[:, S_STEPX] ** 2 + sd[:, S_STEPY] ** 2))
    return saddle_noise_term(sd, noise2) + model2[:, None, None] * np.eye(2)


def _xjunction_covariance(sd: np.ndarray, noise2: float, light_px: np.ndarray, bend_px: np.ndarray,
                          fit_noise: np.ndarray) -> np.ndarray:
    """Corners the X-junction fit polished (subpixel.xjunction_fit; N, 2, 2): its own noise term, ``noise2``
    times ``fit_noise`` (N, 2, 2; Detection.xjunction_noise) - where that is NaN the saddle fit's term from
    its statistics sd (N, N_SADDLE) times XJUNCTION_NOISE_SHARE -, the saddle fit's pixel locking scaled by
    what the X-junction fit measured against it (XJUNCTION_LOCK_SHARE), its floor (XJUNCTION_FLOOR_PX), and the light
    field's shift ``light_px`` (N,) px per axis (XJUNCTION_LIGHT_PX) and BEND_ERROR_SHARE of the lens-bend
    correction ``bend_px`` (N,) px. Not the saddle fit's light term H^-1 m nor its remaining step (the
    distance the polish moved the corner, not an error). Pixel locking stays isotropic: put across the
    locked edge instead, the strongly foreshortened renders' covariances were 1.4x too
    elongated (tests/test_corner_covariance.py), though the robot sequences' clean corners had 0.79 of their
    sigma along the image's y axis with it isotropic and 0.94 across the edges."""
    model2 = (XJUNCTION_FLOOR_PX ** 2 + (XJUNCTION_LOCK_SHARE * PIXEL_LOCK_PX) ** 2 * _locking(sd)
              + np.asarray(light_px, dtype=np.float64) ** 2
              + (BEND_ERROR_SHARE * np.asarray(bend_px, np.float64)) ** 2)
    noise = XJUNCTION_NOISE_SHARE * saddle_noise_term(sd, noise2)
    own = np.isfinite(fit_noise).all(axis=(1, 2))
    noise[own] = noise2 * fit_noise[own]
    return noise + model2[:, None, None] * np.eye(2)


def _locking(sd: np.ndarray) -> np.ndarray:
    """(N,) 0..1: how much pixel locking an edge's angle to the nearest pixel axis (S_AXIS_ANGLE) leaves
    (PIXEL_LOCK_LENGTH_PX)."""
    return np.exp(-2.0 * np.pi ** 2 * (PIXEL_LOCK_LENGTH_PX * np.tan(sd[:, S_AXIS_ANGLE])) ** 2)


def _board_light(sd: np.ndarray, boards: np.ndarray) -> np.ndarray:
    """sd with each corner's light gradient replaced by its board's mean gradient of log light times the
    corner's level (sd (N, N_SADDLE), boards (N,)). A light field is smooth over a board, while each corner's
    own reading carries the image noise of four samples: on renders with no light gradient but noise up to
    4 grey levels those readings alone gave biases as large as a real 25 % gradient, and weighting by them
    cost the pose 40 % of its accuracy."""
    out = sd.copy()
    level = sd[:, S_LEVEL]
    read = (sd[:, S_OK] > 0) & (np.abs(level) > 1.0) & ((sd[:, S_LIGHTX] != 0) | (sd[:, S_LIGHTY] != 0))
    if not read.any():
        return out
    k = int(boards.max()) + 1
    count = np.bincount(boards[read], minlength=k)
    gl = np.zeros((len(sd), 2))
    gl[read] = sd[read][:, [S_LIGHTX, S_LIGHTY]] / level[read, None]
    sums = np.stack([np.bincount(boards[read], weights=gl[read, j], minlength=k) for j in range(2)], axis=1)
    mean = sums.astype(np.float64) / np.maximum(count, 1)[:, None]
    out[:, S_LIGHTX] = level * mean[boards, 0]
    out[:, S_LIGHTY] = level * mean[boards, 1]
    # the mean's own noise: the corners' probe noise over their number
    for col in (S_LNXX, S_LNXY, S_LNYY):
        v = np.zeros(len(sd))
        v[read] = sd[read, col] / level[read] ** 2
        out[:, col] = level ** 2 * np.bincount(boards[read], weights=v[read], minlength=k)[boards] / np.maximum(
            count[boards], 1) ** 2
    return out


def saddle_noise_term(sd: np.ndarray, noise2: float) -> np.ndarray:
    """The saddle fit's noise term (N, 2, 2) px^2, H^-1 N H^-1 x noise2, from saddle_statistics' sd
    (N, N_SADDLE) and the raw image's noise variance (grey levels^2)."""
    h = np.stack([sd[:, S_HXX], sd[:, S_HXY], sd[:, S_HXY], sd[:, S_HYY]], axis=1).reshape(-1, 2, 2)
    nn = np.stack([sd[:, S_NXX], sd[:, S_NXY], sd[:, S_NXY], sd[:, S_NYY]], axis=1).reshape(-1, 2, 2)
    hi = np.linalg.inv(h)
    return noise2 * hi @ nn @ hi


def grid_steps(ids: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """The board's local steps (N, 2, 2) px at each corner: [0] to the next column, [1] to the next row.

    ids: (N, 2) (col, row) of one board's corners; corners: (N, 2) px. Central differences of the
    neighbours where both are there, one-sided where one is, NaN where neither is.
    """
    ids = np.asarray(ids, dtype=np.int64).reshape(-1, 2)
    corners = np.asarray(corners, dtype=np.float64).reshape(-1, 2)
    out = np.full((len(ids), 2, 2), np.nan)
    if len(ids) == 0:
        return out
    lo = ids.min(axis=0)
    shape = ids.max(axis=0) - lo + 3
    grid = np.full((shape[1], shape[0], 2), np.nan)
    c, r = (ids - lo + 1).T
    grid[r, c] = corners
    for k, (dc, dr) in enumerate(((1, 0), (0, 1))):
        ahead = grid[r + dr, c + dc] - corners
        behind = corners - grid[r - dr, c - dc]
        both = 0.5 * (ahead + behind)
        out[:, k] = np.where(np.isfinite(both), both, np.where(np.isfinite(ahead), ahead, behind))
    return out


@njit(cache=True, nogil=True)
def _grid_steps_of_boards(ids: np.ndarray, corners: np.ndarray, bounds: np.ndarray) -> np.ndarray:
    """grid_steps of several boards in one pass: corners bounds[b]:bounds[b + 1] of ``ids`` (N, 2) int64 and
    ``corners`` (N, 2) are board b's. The same differences, per coordinate, as grid_steps."""
    n = ids.shape[0]
    out = np.full((n, 2, 2), np.nan)
    for b in range(bounds.shape[0] - 1):
        s, e = bounds[b], bounds[b + 1]
        if e <= s:
            continue
        grid, lo_c, lo_r = id_grid(corners, ids, s, e, 1)
        for i in range(s, e):
            c = ids[i, 0] - lo_c + 1
            r = ids[i, 1] - lo_r + 1
            for k in range(2):
                dc = 1 - k
                dr = k
                for j in range(2):
                    ahead = grid[r + dr, c + dc, j] - corners[i, j]
                    behind = corners[i, j] - grid[r - dr, c - dc, j]
                    both = 0.5 * (ahead + behind)
                    out[i, k, j] = both if math.isfinite(both) else (ahead if math.isfinite(ahead) else behind)
    return out


def add_board_covariances(detections: list[Detection], grey: np.ndarray, smooth: np.ndarray, smoothing_sigma: float,
                          noise_sigma: float, refiner: str, origin: np.ndarray | None = None,
                          spacing: list[np.ndarray] | None = None) -> None:
    """Fill in each detection's covariance, shared_px2, alternating_px2, light_gradient and unusable (one
    corner_covariance call for all): ``detections`` with corners in image pixels, refined by ``refiner`` on
    ``grey`` (a window of the image whose top-left pixel is ``origin``, default (0, 0)) and its ``smooth``
    image; ``noise_sigma`` covariance_noise_sigma of the whole image; ``spacing`` per detection the square
    size the refinement window came from (default: nearest_spacing of its corners)."""
    if not detections:
        return
    origin = np.zeros(2) if origin is None else np.asarray(origin, dtype=np.float64)
    corners = np.concatenate([d.corners for d in detections]).astype(np.float64)
    xy = corners - origin
    windows = np.concatenate(spacing if spacing is not None else [nearest_spacing(d.corners) for d in detections])
    counts = [len(d.corners) for d in detections]
    steps = _grid_steps_of_boards(np.concatenate([d.ids for d in detections]).astype(np.int64), corners,
                                  np.cumsum([0, *counts]).astype(np.int64))
    boards = np.repeat(np.arange(len(detections)), counts)
    placed = [np.ones(len(d.corners), bool) if d.xjunction_fitted is None else d.xjunction_fitted for d in detections]
    bend = [np.zeros(len(d.corners)) if d.bend_px is None else d.bend_px for d in detections]
    fit_noise = [np.full((len(d.corners), 2, 2), np.nan) if d.xjunction_noise is None else d.xjunction_noise
                 for d in detections]
    cc = corner_covariance(grey, smooth, smoothing_sigma, xy, windows, noise_sigma, refiner=refiner, steps=steps,
                           boards=boards, xjunction_fitted=np.concatenate(placed), bend_px=np.concatenate(bend),
                           xjunction_noise=np.concatenate(fit_noise))
    start = 0
    for d in detections:
        end = start + len(d.corners)
        d.covariance, d.shared_px2, d.unusable = cc.covariance[start:end], cc.shared_px2[start:end], \
            cc.unusable[start:end]
        d.light_gradient, d.alternating_px2 = cc.light_gradient[start:end], cc.alternating_px2[start:end]
        start = end
