"""Tsai's calibration from one view of non-coplanar points (Tsai 1987, the method of the paper's Table 2).

Tsai assumes the principal point (here: the image centre) and solves, in order:
1. the radial alignment constraint — the direction from the principal point to a pixel is parallel to
   the direction of the undistorted projection — a linear system in 7 unknowns giving r1, r2 (rows of
   R), tx, ty and the aspect ratio fx/fy, independent of the focal length, tz and radial distortion;
2. fy and tz linearly from the projection equations;
3. fy, tz and k1 by a small non-linear least-squares fit.
It needs no initial guess; its weakness is the assumed principal point.
"""

from __future__ import annotations

import cv2
import numpy as np
import scipy.optimize

from edgecal.calibration.checks import DegenerateInput, require_non_coplanar
from edgecal.calibration.dlt import LinearCamera


def _nearest_rotation(m: np.ndarray) -> np.ndarray:
    u, _, vt = np.linalg.svd(m)
    r = u @ vt
    if np.linalg.det(r) < 0:
        r = u @ np.diag([1.0, 1.0, -1.0]) @ vt
    return r


def calibrate_tsai(object_pts: np.ndarray, image_px: np.ndarray,
                   image_size: tuple[int, int]) -> LinearCamera:
    """Intrinsics (principal point at the image centre), k1 and pose from non-coplanar points.

    ``image_size`` is [width, height]; raises DegenerateInput for too few or coplanar points.
    """
    obj, img = require_non_coplanar(object_pts, image_px, min_points=7)
    cx, cy = (image_size[0] - 1) / 2.0, (image_size[1] - 1) / 2.0
    xd, yd = img[:, 0] - cx, img[:, 1] - cy
    # Stage 1, radial alignment: yd*(s r1.X + s tx) - xd*(r2.X + ty) = 0, divided by ty.
    a = np.c_[yd[:, None] * obj, yd, -xd[:, None] * obj]
    sol, *_ = np.linalg.lstsq(a, xd, rcond=None)
    norm_r2 = np.linalg.norm(sol[4:7])
    if norm_r2 < 1e-12:
        raise DegenerateInput("Tsai's method failed: the corners are too close to the image centre")
    ty_abs = 1.0 / norm_r2
    aspect = np.linalg.norm(sol[0:3]) * ty_abs  # s = fx / fy
    best: LinearCamera | None = None
    for ty in (ty_abs, -ty_abs):  # the sign of ty is the one that gives a positive focal length
        r1 = sol[0:3] * ty / aspect
        tx = sol[3] * ty / aspect
        r2 = sol[4:7] * ty
        rot = _nearest_rotation(np.vstack([r1, r2, np.cross(r1, r2)]))
        x = obj @ rot[0] + tx
        y = obj @ rot[1] + ty
        w = obj @ rot[2]
        # Stage 2: (v - cy)(w + tz) = fy y  and  (u - cx)(w + tz) = s fy x, linear in fy, tz.
        m = np.r_[np.c_[y, -yd], np.c_[aspect * x, -xd]]
        rhs = np.r_[yd * w, xd * w]
        (fy, tz), *_ = np.linalg.lstsq(m, rhs, rcond=None)
        if fy <= 0 or tz <= 0 or (w + tz).min() <= 0:
            continue
        rvec = cv2.Rodrigues(rot)[0]
        tvec = np.array([tx, ty, tz])

        # Stage 3: fy, tz, k1 non-linearly with the rest fixed (Tsai's final step). resid is solved within
        # this iteration, so its loop variables are the current ones.
        def resid(p: np.ndarray) -> np.ndarray:
            k = np.array([[aspect * p[0], 0, cx], [0, p[0], cy], [0, 0, 1.0]])
            proj, _ = cv2.projectPoints(obj, rvec, np.array([tx, ty, p[1]]), k,  # noqa: B023
                                        np.array([p[2], 0, 0, 0, 0.0]))
            return (proj.reshape(-1, 2) - img).ravel()

        fit = scipy.optimize.least_squares(resid, [fy, tz, 0.0], x_scale=[fy, tz, 0.1], method="lm")
        fy, tz, k1 = fit.x
        if fy <= 0 or tz <= 0:
            continue
        k = np.array([[aspect * fy, 0, cx], [0, fy, cy], [0, 0, 1.0]])
        tvec = np.array([tx, ty, tz])
        dist = np.array([k1, 0, 0, 0, 0.0])
        rms = float(np.sqrt(np.mean(np.sum(fit.fun.reshape(-1, 2) ** 2, axis=1))))
        cam = LinearCamera(k, rot, tvec, dist, rms, "tsai")
        if best is None or cam.rms_px < best.rms_px:
            best = cam
    if best is None:
        raise DegenerateInput("Tsai's method found no camera in front of the target: the matches are inconsistent")
    return best
