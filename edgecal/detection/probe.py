"""The circular probe of the paper (Eq. 1-5), as numba kernels over all candidates of a frame.

For each candidate the probe sums the edge signal along ``n_angles`` rays from ``r_in`` to the probe
radius (Eq. 1), smooths the circular profile, takes its four strongest local maxima as the board's border
directions, checks that opposite ones are 180 deg apart (Eq. 2-3) and that the four sectors between them
alternate black/white (Eq. 4-5).

Going past the paper: the edge signal is, by default, the gradient component *across* the ray
(|g . n| with n the ray's normal) instead of the plain magnitude |g|. Along a border line the gradient is
across the ray, so both agree there; but where a ray crosses other edges the gradient points along the ray
and the across-component is ~0, so the four border peaks stand out far more for small or blurred squares.
``edge_mode=0`` gives the paper's magnitude.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
from numba import njit

if TYPE_CHECKING:
    from edgecal.detection.params import DetectorParams

EDGE_MAGNITUDE = 0  # the paper's Eq. (1): |g|
EDGE_ACROSS_RAY = 1  # edgecal's default: |g . n|, n normal to the ray

# Columns of the per-candidate measurement array returned by probe_candidates.
M_ANGLE_ERR = 0     # mean |theta_diff| of Eq. (2), radians
M_CONTRAST = 1      # mean(white sectors) - mean(black sectors), grey levels
M_PEAK_RATIO = 2    # weakest border peak / weakest valley of the profile
M_SIGN_FRAC = 3     # smallest sector majority fraction of Eq. (4)
M_FIRST_SIGN = 4    # +1 if the sector after theta_1 is white, -1 if black
N_MEASURES = 5


@njit(cache=True, nogil=True, inline="always")
def _bilinear_cell(h: int, w: int, x: float, y: float) -> tuple[bool, int, int, float, float]:
    """The pixel cell of (x, y) in an h x w image and the fractions within it (OpenCV convention: integer =
    pixel centre); False outside the image."""
    if x < 0.0 or y < 0.0 or x > w - 1.0 or y > h - 1.0:
        return False, 0, 0, 0.0, 0.0
    x0 = min(int(x), w - 2)
    y0 = min(int(y), h - 2)
    return True, x0, y0, x - x0, y - y0


@njit(cache=True, nogil=True, inline="always")
def _interpolate(img: np.ndarray, x0: int, y0: int, fx: float, fy: float) -> float:
    top = img[y0, x0] * (1.0 - fx) + img[y0, x0 + 1] * fx
    bottom = img[y0 + 1, x0] * (1.0 - fx) + img[y0 + 1, x0 + 1] * fx
    return top * (1.0 - fy) + bottom * fy


@njit(cache=True, nogil=True)
def _bilinear(img: np.ndarray, x: float, y: float) -> float:
    """Bilinear sample at (x, y), OpenCV convention (integer = pixel centre); 0 outside the image."""
    inside, x0, y0, fx, fy = _bilinear_cell(img.shape[0], img.shape[1], x, y)
    return _interpolate(img, x0, y0, fx, fy) if inside else 0.0


@njit(cache=True, nogil=True)
def _bilinear_pair(ga: np.ndarray, gb: np.ndarray, x: float, y: float) -> tuple[float, float]:
    """_bilinear of two images of one shape at the same point: the cell and weights are found once (the probe
    samples both gradient images at every point of every ray)."""
    inside, x0, y0, fx, fy = _bilinear_cell(ga.shape[0], ga.shape[1], x, y)
    if not inside:
        return 0.0, 0.0
    return _interpolate(ga, x0, y0, fx, fy), _interpolate(gb, x0, y0, fx, fy)


@njit(cache=True, nogil=True)
def _fill_profile(gx: np.ndarray, gy: np.ndarray, x: float, y: float, radius: float, r_in: float,
                  edge_mode: int, cos_t: np.ndarray, sin_t: np.ndarray, out: np.ndarray) -> None:
    """Eq. (1): out[k] = mean edge signal along the ray at angle k from r_in to radius."""
    n = cos_t.shape[0]
    # One sample per pixel of radius, at most 10: a longer ray only averages more of the same line.
    n_steps = min(10, max(2, int(radius - r_in) + 1))
    step = (radius - r_in) / (n_steps - 1)
    h, w = gx.shape
    reach = max(abs(radius), abs(r_in)) + 1.0
    if x - reach >= 0.0 and y - reach >= 0.0 and x + reach <= w - 2.0 and y + reach <= h - 2.0:
        # Every sample lies a pixel inside the image: _bilinear_pair's cell without its bounds checks (the
        # same arithmetic, so the same profile; most candidates, ~13 % of the probe's time). The rays are the
        # inner loop, each ray's sum still taken from r_in outwards (the same sums): independent rays side
        # by side run ~1/4 faster than one ray's chain of dependent additions.
        for k in range(n):
            out[k] = 0.0
        for i in range(n_steps):
            r = r_in + i * step
            for k in range(n):
                c = cos_t[k]
                s = sin_t[k]
                sx = x + r * c
                sy = y + r * s
                x0 = int(sx)
                y0 = int(sy)
                ex = _interpolate(gx, x0, y0, sx - x0, sy - y0)
                ey = _interpolate(gy, x0, y0, sx - x0, sy - y0)
                if edge_mode == EDGE_MAGNITUDE:
                    out[k] += math.sqrt(ex * ex + ey * ey)
                else:
                    out[k] += abs(-ex * s + ey * c)
        for k in range(n):
            out[k] = out[k] / n_steps
        return
    for k in range(n):
        c = cos_t[k]
        s = sin_t[k]
        acc = 0.0
        for i in range(n_steps):
            r = r_in + i * step
            sx = x + r * c
            sy = y + r * s
            ex, ey = _bilinear_pair(gx, gy, sx, sy)
            if edge_mode == EDGE_MAGNITUDE:
                acc += math.sqrt(ex * ex + ey * ey)
            else:
                acc += abs(-ex * s + ey * c)
        out[k] = acc / n_steps


@njit(cache=True, nogil=True)
def probe_profiles(gx: np.ndarray, gy: np.ndarray, pts: np.ndarray, radii: np.ndarray, n_angles: int,
                   r_in: float, edge_mode: int) -> np.ndarray:
    """Eq. (1) for every point: an (M, n_angles) array of circular edge profiles (unsmoothed)."""
    m = pts.shape[0]
    out = np.zeros((m, n_angles))
    theta = np.arange(n_angles) * (2.0 * math.pi / n_angles)
    cos_t = np.cos(theta)
    sin_t = np.sin(theta)
    for i in range(m):
        _fill_profile(gx, gy, pts[i, 0], pts[i, 1], radii[i], r_in, edge_mode, cos_t, sin_t, out[i])
    return out


@njit(cache=True, nogil=True)
def _border_directions(profile: np.ndarray, smooth: np.ndarray, dirs: np.ndarray) -> float:
    """The four strongest local maxima of the smoothed circular profile, sorted, into ``dirs`` (radians).

    Returns the ratio weakest-peak / weakest-valley, or 0.0 when there are fewer than four maxima.
    """
    n = profile.shape[0]
    for k in range(n):
        smooth[k] = 0.25 * profile[(k - 1) % n] + 0.5 * profile[k] + 0.25 * profile[(k + 1) % n]
    # The four strongest strict local maxima (plateaus count once, at their first bin).
    best_val = np.full(4, -1.0)
    best_idx = np.full(4, -1)
    for k in range(n):
        a = smooth[(k - 1) % n]
        b = smooth[k]
        c = smooth[(k + 1) % n]
        if b > a and b >= c:
            # insert into the top-4 list
            j = 3
            if b <= best_val[3]:
                continue
            while j > 0 and best_val[j - 1] < b:
                best_val[j] = best_val[j - 1]
                best_idx[j] = best_idx[j - 1]
                j -= 1
            best_val[j] = b
            best_idx[j] = k
    if best_idx[3] < 0:
        return 0.0
    step = 2.0 * math.pi / n
    for j in range(4):
        k = best_idx[j]
        a = smooth[(k - 1) % n]
        b = smooth[k]
        c = smooth[(k + 1) % n]
        den = a - 2.0 * b + c
        off = 0.0
        if den < 0.0:
            off = 0.5 * (a - c) / den
            if off > 0.5:
                off = 0.5
            elif off < -0.5:
                off = -0.5
        ang = (k + off) * step
        if ang < 0.0:
            ang += 2.0 * math.pi
        elif ang >= 2.0 * math.pi:
            ang -= 2.0 * math.pi
        dirs[j] = ang
    dirs.sort()
    valley = smooth.min()
    weakest = best_val[3]
    if valley <= 1e-9:
        return 1e9
    return weakest / valley


@njit(cache=True, nogil=True)
def _sector_signs(grey: np.ndarray, x: float, y: float, radius: float, dirs: np.ndarray,
                  sign_fraction: float, out: np.ndarray) -> None:
    """Eq. (4)-(5): sample the four sectors, call each + (white) or - (black) against the local mean.

    Writes into out: [contrast, smallest majority fraction, first sign (+1/-1, 0 = no alternation)].
    """
    n_ang = 5
    n_rad = 3
    # Stay out of the corner's own blur (inner radius) and inside its four squares (outer radius).
    r0 = max(2.0, 0.35 * radius)
    r1 = max(r0 + 1.0, 0.7 * radius)
    vals = np.empty((4, n_ang * n_rad))
    total = 0.0
    for sct in range(4):
        a0 = dirs[sct]
        a1 = dirs[(sct + 1) % 4]
        if sct == 3:
            a1 += 2.0 * math.pi
        width = a1 - a0
        idx = 0
        for ia in range(n_ang):
            ang = a0 + width * (0.25 + 0.5 * ia / (n_ang - 1))
            c = math.cos(ang)
            s = math.sin(ang)
            for ir in range(n_rad):
                r = r0 + (r1 - r0) * ir / (n_rad - 1)
                v = _bilinear(grey, x + r * c, y + r * s)
                vals[sct, idx] = v
                total += v
                idx += 1
    m = total / (4 * n_ang * n_rad)
    signs = np.zeros(4)
    means = np.zeros(4)
    min_frac = 1.0
    for sct in range(4):
        above = 0
        below = 0
        acc = 0.0
        for i in range(n_ang * n_rad):
            v = vals[sct, i]
            acc += v
            if v > m:
                above += 1
            elif v < m:
                below += 1
        means[sct] = acc / (n_ang * n_rad)
        fa = above / (n_ang * n_rad)
        fb = below / (n_ang * n_rad)
        if fa >= sign_fraction:
            signs[sct] = 1.0
            min_frac = min(min_frac, fa)
        elif fb >= sign_fraction:
            signs[sct] = -1.0
            min_frac = min(min_frac, fb)
        else:
            min_frac = min(min_frac, max(fa, fb))
    alternates = (signs[0] != 0.0 and signs[0] == signs[2] and signs[1] == signs[3]
                  and signs[0] == -signs[1])
    out[0] = 0.5 * abs((means[0] + means[2]) - (means[1] + means[3]))
    out[1] = min_frac
    out[2] = signs[0] if alternates else 0.0


@njit(cache=True, nogil=True)
def _probe_point(gx: np.ndarray, gy: np.ndarray, grey: np.ndarray, x: float, y: float, radius: float, r_in: float,
                 edge_mode: int, angle_diff_max: float, sign_fraction: float, min_contrast: float,
                 min_peak_ratio: float, cos_t: np.ndarray, sin_t: np.ndarray, profile: np.ndarray,
                 smooth: np.ndarray, sign_out: np.ndarray, d: np.ndarray, dirs: np.ndarray,
                 measures: np.ndarray, row: int) -> bool:
    """The whole probe (Eq. 1-5) at one point, as probe_candidates runs it on each of its points: whether it
    accepts it; its border directions into ``dirs[row]`` (4,) and its measures into ``measures[row]``
    (N_MEASURES,) (the directions left as they are where no four borders are seen); profile, smooth,
    sign_out, d: work arrays. (probe_candidates keeps its own copy of these lines: through this function
    it ran ~4 % slower.)"""
    _fill_profile(gx, gy, x, y, radius, r_in, edge_mode, cos_t, sin_t, profile)
    ratio = _border_directions(profile, smooth, d)
    measures[row, M_PEAK_RATIO] = ratio
    if ratio <= 0.0:
        measures[row, M_ANGLE_ERR] = math.pi
        return False
    for j in range(4):
        dirs[row, j] = d[j]
    err = 0.5 * (abs((d[2] - d[0]) - math.pi) + abs((d[3] - d[1]) - math.pi))
    measures[row, M_ANGLE_ERR] = err
    _sector_signs(grey, x, y, radius, d, sign_fraction, sign_out)
    measures[row, M_CONTRAST] = sign_out[0]
    measures[row, M_SIGN_FRAC] = sign_out[1]
    measures[row, M_FIRST_SIGN] = sign_out[2]
    return (err < angle_diff_max and ratio >= min_peak_ratio and sign_out[2] != 0.0
            and sign_out[0] >= min_contrast)


@njit(cache=True, nogil=True)
def _probe_scratch(n_angles: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The probe's ray directions (cos, sin of n_angles angles) and its per-point scratch arrays (profile,
    smoothed profile, sector signs, border directions), made once per call of a probe kernel."""
    theta = np.arange(n_angles) * (2.0 * math.pi / n_angles)
    return (np.cos(theta), np.sin(theta), np.empty(n_angles), np.empty(n_angles), np.empty(3), np.empty(4))


@njit(cache=True, nogil=True)
def probe_candidates(gx: np.ndarray, gy: np.ndarray, grey: np.ndarray, pts: np.ndarray, radii: np.ndarray,
                     n_angles: int, r_in: float, edge_mode: int, angle_diff_max: float,
                     sign_fraction: float, min_contrast: float, min_peak_ratio: float):
    """Run the whole probe (Eq. 1-5) on every point; one call per frame.

    Returns (ok (M,) bool, dirs (M, 4) radians sorted ascending, measures (M, N_MEASURES)).
    """
    m = pts.shape[0]
    ok = np.zeros(m, dtype=np.bool_)
    dirs = np.zeros((m, 4))
    measures = np.zeros((m, N_MEASURES))
    cos_t, sin_t, profile, smooth, sign_out, d = _probe_scratch(n_angles)
    for i in range(m):
        x = pts[i, 0]
        y = pts[i, 1]
        _fill_profile(gx, gy, x, y, radii[i], r_in, edge_mode, cos_t, sin_t, profile)
        ratio = _border_directions(profile, smooth, d)
        measures[i, M_PEAK_RATIO] = ratio
        if ratio <= 0.0:
            measures[i, M_ANGLE_ERR] = math.pi
            continue
        for j in range(4):
            dirs[i, j] = d[j]
        err = 0.5 * (abs((d[2] - d[0]) - math.pi) + abs((d[3] - d[1]) - math.pi))
        measures[i, M_ANGLE_ERR] = err
        _sector_signs(grey, x, y, radii[i], d, sign_fraction, sign_out)
        measures[i, M_CONTRAST] = sign_out[0]
        measures[i, M_SIGN_FRAC] = sign_out[1]
        measures[i, M_FIRST_SIGN] = sign_out[2]
        ok[i] = (err < angle_diff_max and ratio >= min_peak_ratio and sign_out[2] != 0.0
                 and sign_out[0] >= min_contrast)
    return ok, dirs, measures


@njit(cache=True, nogil=True)
def probe_accepts(gx: np.ndarray, gy: np.ndarray, grey: np.ndarray, pts: np.ndarray, radii: np.ndarray,
                  n_angles: int, r_in: float, edge_mode: int, angle_diff_max: float,
                  sign_fraction: float, min_contrast: float, min_peak_ratio: float) -> np.ndarray:
    """(M,) bool: whether the probe (probe_candidates, the same thresholds) accepts each point at any of the
    ``radii`` (R,), tried in order until one does: the detector's first pass in one call (one call per
    radius on the points left cost more in calls than the few points after the first radius)."""
    m = pts.shape[0]
    ok = np.zeros(m, dtype=np.bool_)
    cos_t, sin_t, profile, smooth, sign_out, d = _probe_scratch(n_angles)
    dirs = np.zeros((1, 4))
    measures = np.zeros((1, N_MEASURES))
    for i in range(m):
        for radius in radii:
            if _probe_point(gx, gy, grey, pts[i, 0], pts[i, 1], radius, r_in, edge_mode, angle_diff_max,
                            sign_fraction, min_contrast, min_peak_ratio, cos_t, sin_t, profile, smooth,
                            sign_out, d, dirs, measures, 0):
                ok[i] = True
                break
    return ok


def probe_profile_reference(gx: np.ndarray, gy: np.ndarray, x: float, y: float, radius: float,
                            n_angles: int, r_in: float, edge_mode: int = EDGE_ACROSS_RAY) -> np.ndarray:
    """Plain-Python Eq. (1) for one point, the reference the kernel is tested against."""
    h, w = gx.shape

    def sample(img: np.ndarray, sx: float, sy: float) -> float:
        if sx < 0 or sy < 0 or sx > w - 1 or sy > h - 1:
            return 0.0
        x0 = min(int(math.floor(sx)), w - 2)
        y0 = min(int(math.floor(sy)), h - 2)
        fx, fy = sx - x0, sy - y0
        return float((img[y0, x0] * (1 - fx) + img[y0, x0 + 1] * fx) * (1 - fy)
                     + (img[y0 + 1, x0] * (1 - fx) + img[y0 + 1, x0 + 1] * fx) * fy)

    n_steps = min(10, max(2, int(radius - r_in) + 1))
    radii = [r_in + i * (radius - r_in) / (n_steps - 1) for i in range(n_steps)]
    out = np.zeros(n_angles)
    for k in range(n_angles):
        t = 2 * math.pi * k / n_angles
        c, s = math.cos(t), math.sin(t)
        vals = []
        for r in radii:
            ex, ey = sample(gx, x + r * c, y + r * s), sample(gy, x + r * c, y + r * s)
            vals.append(math.hypot(ex, ey) if edge_mode == EDGE_MAGNITUDE else abs(-ex * s + ey * c))
        out[k] = sum(vals) / n_steps
    return out


@njit(cache=True, nogil=True)
def ring_prefilter(grey: np.ndarray, pts: np.ndarray, radii: np.ndarray, min_contrast: float,
                   symmetric: bool = True) -> np.ndarray:
    """A cheap first look before the full probe: does a ring around the point cross dark/bright 4 times?

    Samples 24 points on a circle (at 0.5 and 1.0 x ``radii``), classifies each against the ring's mean with
    a hysteresis of a quarter of ``min_contrast``, and keeps points where either ring alternates exactly four
    times, spans at least ``min_contrast`` and (``symmetric``) is nearly point-symmetric (an X-corner looks
    the same turned by 180 degrees, locally even under perspective; edges, L- and T-junctions do not). Saves
    the full probe's cost on most non-corners. Without the symmetry test it also keeps a point a good part
    of the ring's radius off an X-corner (a prediction its refinement would still pull in), as long as the
    ring goes round the corner.
    """
    m = pts.shape[0]
    keep = np.zeros(m, dtype=np.bool_)
    vals = np.empty(_RING_SAMPLES)
    cos_t, sin_t = _ring_directions()
    for i in range(m):
        keep[i] = _ring_keeps(grey, pts[i, 0], pts[i, 1], radii[i], min_contrast, cos_t, sin_t, vals, symmetric)
    return keep


@njit(cache=True, nogil=True)
def ring_prefilter_radii(grey: np.ndarray, pts: np.ndarray, radii: np.ndarray, min_contrast: float) -> np.ndarray:
    """(M,) bool: whether ring_prefilter keeps each point at any of the ``radii`` (R,) (tried in order until
    one does): the first pass's pre-filter in one call."""
    m = pts.shape[0]
    keep = np.zeros(m, dtype=np.bool_)
    vals = np.empty(_RING_SAMPLES)
    cos_t, sin_t = _ring_directions()
    for i in range(m):
        for radius in radii:
            if _ring_keeps(grey, pts[i, 0], pts[i, 1], radius, min_contrast, cos_t, sin_t, vals, True):
                keep[i] = True
                break
    return keep


_RING_SAMPLES = 24


@njit(cache=True, nogil=True)
def _ring_directions() -> tuple[np.ndarray, np.ndarray]:
    """cos and sin of the ring's _RING_SAMPLES directions."""
    n = _RING_SAMPLES
    return np.cos(np.arange(n) * (2.0 * math.pi / n)), np.sin(np.arange(n) * (2.0 * math.pi / n))


@njit(cache=True, nogil=True)
def _ring_keeps(grey: np.ndarray, x: float, y: float, radius: float, min_contrast: float, cos_t: np.ndarray,
                sin_t: np.ndarray, vals: np.ndarray, symmetric: bool) -> bool:
    """ring_prefilter's test of one point at one radius (vals: a work array of _RING_SAMPLES)."""
    n = _RING_SAMPLES
    for scale in (0.5, 1.0):
        r = max(2.0, scale * radius)
        lo = 1e9
        hi = -1e9
        mean = 0.0
        for k in range(n):
            v = _bilinear(grey, x + r * cos_t[k], y + r * sin_t[k])
            vals[k] = v
            mean += v
            lo = min(lo, v)
            hi = max(hi, v)
        mean /= n
        if hi - lo < min_contrast:
            continue
        band = 0.25 * min_contrast
        # Walk the ring twice from a decided sample, counting state changes once around.
        state = 0
        start = -1
        for k in range(n):
            if abs(vals[k] - mean) > band:
                start = k
                state = 1 if vals[k] > mean else -1
                break
        if start < 0:
            continue
        spread = 0.0
        asym = 0.0
        for k in range(n):
            spread += abs(vals[k] - mean)
            asym += abs(vals[k] - vals[(k + n // 2) % n])
        if symmetric and asym > 0.6 * spread:
            continue
        changes = 0
        for j in range(1, n + 1):
            v = vals[(start + j) % n]
            if v > mean + band and state < 0:
                state = 1
                changes += 1
            elif v < mean - band and state > 0:
                state = -1
                changes += 1
        if changes == 4:
            return True
    return False


def probe_radii(spacing: np.ndarray, params: DetectorParams) -> np.ndarray:
    """Probe radius for each local square size: ``probe_radius_per_spacing`` x spacing, clamped to
    [probe_radius_min_px, probe_radius_max_px]."""
    # np.minimum/np.maximum: np.clip's values at a third of its call overhead
    return np.minimum(np.maximum(params.probe_radius_per_spacing * np.asarray(spacing, dtype=np.float64),
                                 params.probe_radius_min_px), params.probe_radius_max_px)


def probe_reach(radii: np.ndarray, params: DetectorParams) -> np.ndarray:
    """How far (px) from its centre a probe of each radius reads the gradient images: its rays' ends and the
    bilinear cells round them (see Level.gradients_near)."""
    return np.maximum(radii, params.probe_inner_radius_px) + 1.0


def probe_quality(measures: np.ndarray, params: DetectorParams) -> np.ndarray:
    """Per point in [0, 1]: how cleanly the probe saw a chessboard corner (angle error x contrast, each
    scaled to its threshold in ``params``); 1 is a clean, contrasty saddle."""
    angle = np.minimum(np.maximum(1.0 - measures[:, M_ANGLE_ERR] / math.radians(params.angle_diff_max_deg), 0.0), 1.0)
    contrast = np.minimum(np.maximum(measures[:, M_CONTRAST] / (4.0 * params.min_contrast), 0.0), 1.0)
    return angle * contrast
