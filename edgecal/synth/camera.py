"""The renderer's view of edgecal.camera.CameraModel: cameras by field of view, per-pixel ray grids, truth JSON.

Projection is edgecal.camera.project (tested against OpenCV for every lens model). The inverse, pixel ->
ray, is edgecal.camera.unproject, except for the radtan lens, whose pixel-corner grid keeps its numba
Newton kernel below (same answer to ~1e-14, and renders bit-identical to the published sets). The
renderer's ground truth is only as good as this inverse.

Poses follow docs/conventions.md: ``X_cam = R_cam_world @ X_world + t_cam_world_mm`` (mm).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from edgecal.camera import LENS_PARAMS, CameraModel, project, unproject

# The truth files' "model" name of each lens model.
JSON_MODEL = {"radtan": "opencv-pinhole-k1k2p1p2k3", "rational": "opencv-rational-k1k2p1p2k3k4k5k6",
              "fisheye": "kannala-brandt-k1k2k3k4"}


def camera_from_fov(size: tuple[int, int], hfov_deg: float, dist: tuple[float, ...] = (0.0,) * 5,
                    principal_offset_px: tuple[float, float] = (0.0, 0.0), aspect: float = 1.0,
                    lens: str = "radtan") -> CameraModel:
    """A camera of horizontal field of view ``hfov_deg`` with the principal point near the image centre.

    Pinhole lenses (radtan, rational): f = w / 2 / tan(hfov / 2); fisheye: the equidistant f = w / 2 / (hfov / 2),
    so a fisheye may see 180 degrees and more.
    """
    w, h = size
    half = 0.5 * np.radians(hfov_deg)
    fx = 0.5 * w / (half if lens == "fisheye" else np.tan(half))
    return CameraModel(fx, fx * aspect, (w - 1) / 2.0 + principal_offset_px[0], (h - 1) / 2.0 + principal_offset_px[1],
                       lens, np.asarray(dist, dtype=np.float64)[:len(LENS_PARAMS[lens])], (w, h))


def project_world(camera: CameraModel, points_world: np.ndarray, R_cam_world: np.ndarray,
                  t_cam_world_mm: np.ndarray) -> np.ndarray:
    """Pixels (N, 2) of world points (N, 3) seen by ``camera`` at pose (R_cam_world, t_cam_world_mm)."""
    p = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
    return project(p @ np.asarray(R_cam_world).T + np.asarray(t_cam_world_mm).reshape(1, 3), camera)


def pixel_rays(camera: CameraModel, pixels: np.ndarray) -> np.ndarray:
    """Rays (N, 3) through pixels (N, 2), scaled to z = 1; NaN where the lens has no inverse or the ray is
    not in front of the camera (z <= 0, a fisheye beyond 90 degrees)."""
    px = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    if camera.lens == "radtan":
        xd = (px[:, 0] - camera.cx) / camera.fx
        yd = (px[:, 1] - camera.cy) / camera.fy
        x, y = undistort_normalized(xd, yd, camera.params)
        return np.stack([x, y, np.ones_like(x)], axis=1)
    v = unproject(px, camera)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.where(v[:, 2] > 1e-12, v[:, 2], np.nan)
    return v / z[:, None]


def corner_ray_grid(camera: CameraModel) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rays through every pixel *corner*: arrays (h+1, w+1) of x, y and z (z = 1 for pinhole lenses,
    unit rays for fisheye ones, which may point behind the camera plane).

    Grid point (i, j) is the pixel-coordinate point (j - 0.5, i - 0.5): the corners shared by the
    pixels around it (pixel centres are integers, see docs/conventions.md).
    """
    return _ray_grid_cached(camera)


def camera_json(camera: CameraModel, name: str, R_cam_world: np.ndarray, t_cam_world_mm: np.ndarray) -> dict:
    """The ``camera`` section of an "edgecal-synth-gt/1" file (``dist``: the lens model's parameters)."""
    R = np.asarray(R_cam_world, dtype=np.float64)
    t = np.asarray(t_cam_world_mm, dtype=np.float64).ravel()
    return {
        "name": name,
        "model": JSON_MODEL[camera.lens],
        "lens": camera.lens,
        "K": camera.camera_matrix.tolist(),
        "dist": camera.dist_coeffs.tolist(),
        "image_size": list(camera.image_size),
        "R_cam_world": R.tolist(),
        "t_cam_world_mm": t.tolist(),
        "center_world_mm": (-R.T @ t).tolist(),
    }


def camera_from_json(cam: dict) -> tuple[CameraModel, np.ndarray, np.ndarray]:
    """(camera, R_cam_world, t_cam_world_mm) of a truth file's ``camera`` section (radtan when it names no lens)."""
    model = CameraModel.from_opencv(np.array(cam["K"], dtype=np.float64), np.array(cam["dist"], dtype=np.float64),
                                    tuple(cam["image_size"]), str(cam.get("lens", "radtan")))
    return model, np.array(cam["R_cam_world"], dtype=np.float64), np.array(cam["t_cam_world_mm"], dtype=np.float64)


_RAY_CACHE: dict[tuple, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}


def _ray_grid_cached(cam: CameraModel) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    # A camera's ray grid never changes, and sequences render thousands of frames with one camera.
    key = cam.key()
    hit = _RAY_CACHE.get(key)
    if hit is None:
        w, h = cam.image_size
        if cam.lens == "radtan":
            d = cam.params
            out_x = np.empty((h + 1, w + 1))
            out_y = np.empty((h + 1, w + 1))
            _undistort_grid(cam.fx, 0.0, cam.cx, cam.fy, cam.cy, float(d[0]), float(d[1]), float(d[2]), float(d[3]),
                            float(d[4]), monotonic_radius2(d), out_x, out_y)
            hit = (out_x, out_y, np.ones_like(out_x))
        else:
            jj, ii = np.meshgrid(np.arange(w + 1) - 0.5, np.arange(h + 1) - 0.5)
            v = unproject(np.stack([jj, ii], axis=-1), cam)
            if cam.lens != "fisheye":
                v = v / v[..., 2:3]   # pinhole rays at z = 1, as the radtan grid
            hit = (np.ascontiguousarray(v[..., 0]), np.ascontiguousarray(v[..., 1]), np.ascontiguousarray(v[..., 2]))
        if len(_RAY_CACHE) > 8:
            _RAY_CACHE.clear()
        _RAY_CACHE[key] = hit
    return hit


def monotonic_radius2(dist: np.ndarray) -> float:
    """A squared radius (normalised) inside which the distortion is surely one-to-one (inf if everywhere).

    From the radial terms: the first zero of d(r R(r))/dr = 1 + 3 k1 r^2 + 5 k2 r^4 + 7 k3 r^6, with a
    margin for the tangential terms; beyond it the renderer checks each solution explicitly.
    """
    k1, k2, p1, p2, k3 = (float(v) for v in np.asarray(dist, dtype=np.float64).ravel()[:5])
    coeffs = [7.0 * k3, 5.0 * k2, 3.0 * k1, 1.0]
    while coeffs and coeffs[0] == 0.0:
        coeffs.pop(0)
    if len(coeffs) < 2:
        return float("inf")
    roots = np.roots(coeffs)
    real = [float(r.real) for r in roots if abs(r.imag) < 1e-12 and r.real > 0]
    return 0.5 * min(real) if real else float("inf")


def distort_normalized(xy: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """OpenCV's distortion of normalised coordinates (N, 2) with (k1, k2, p1, p2, k3)."""
    k1, k2, p1, p2, k3 = (float(v) for v in np.asarray(dist, dtype=np.float64).ravel()[:5])
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return np.stack([xd, yd], axis=1)


@njit(cache=True, nogil=True)
def _jacobian_det(x: float, y: float, k1: float, k2: float, p1: float, p2: float, k3: float) -> float:
    """Determinant of the Jacobian of the distortion at (x, y)."""
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    dr = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
    a = radial + 2.0 * x * x * dr + 2.0 * p1 * y + 6.0 * p2 * x
    b = 2.0 * x * y * dr + 2.0 * p1 * x + 2.0 * p2 * y
    d = radial + 2.0 * y * y * dr + 6.0 * p1 * y + 2.0 * p2 * x
    return a * d - b * b


@njit(cache=True, nogil=True)
def _on_principal_branch(x: float, y: float, k1: float, k2: float, p1: float, p2: float, k3: float,
                         r2_safe: float) -> bool:
    """True when the segment from the optical axis to (x, y) never crosses a fold of the distortion."""
    if x * x + y * y <= r2_safe:
        return True
    for k in range(1, 17):
        s = k / 16.0
        if _jacobian_det(s * x, s * y, k1, k2, p1, p2, k3) <= 1e-9:
            return False
    return True


@njit(cache=True, nogil=True)
def _newton_undistort(xd: float, yd: float, x: float, y: float, k1: float, k2: float, p1: float, p2: float,
                      k3: float, r2_safe: float = np.inf) -> tuple[float, float, bool]:
    """Solve distort(x, y) = (xd, yd) by Newton's method from the guess (x, y).

    Only the principal solution counts (reached from the optical axis without crossing a fold, where
    the model is one-to-one); beyond a fold the same pixel has other, unphysical preimages.
    """
    for _ in range(40):
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        fx = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x) - xd
        fy = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y - yd
        if abs(fx) + abs(fy) < 1e-14:
            return x, y, _on_principal_branch(x, y, k1, k2, p1, p2, k3, r2_safe)
        dr = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)  # d(radial)/d(r2)
        a = radial + 2.0 * x * x * dr + 2.0 * p1 * y + 6.0 * p2 * x
        b = 2.0 * x * y * dr + 2.0 * p1 * x + 2.0 * p2 * y  # the Jacobian is symmetric
        d = radial + 2.0 * y * y * dr + 6.0 * p1 * y + 2.0 * p2 * x
        det = a * d - b * b
        if det <= 1e-9:
            # The distortion folds over here: no unique inverse.
            return x, y, False
        x -= (d * fx - b * fy) / det
        y -= (a * fy - b * fx) / det
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    fx = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x) - xd
    fy = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y - yd
    return x, y, abs(fx) + abs(fy) < 1e-12 and _on_principal_branch(x, y, k1, k2, p1, p2, k3, r2_safe)


@njit(cache=True, nogil=True)
def _undistort_kernel(xd: np.ndarray, yd: np.ndarray, k1: float, k2: float, p1: float, p2: float,
                      k3: float, r2_safe: float, out_x: np.ndarray, out_y: np.ndarray) -> None:
    """Undistort a list of points; each starts from the previous solution when there is one."""
    px = np.nan
    py = np.nan
    pxd = 0.0
    pyd = 0.0
    for i in range(xd.shape[0]):
        if px == px:
            x0 = px + (xd[i] - pxd)
            y0 = py + (yd[i] - pyd)
        else:
            x0 = xd[i]
            y0 = yd[i]
        x, y, ok = _newton_undistort(xd[i], yd[i], x0, y0, k1, k2, p1, p2, k3, r2_safe)
        if not ok and px == px:
            # A far-away previous point can be a poor start: try from the distorted point itself.
            x, y, ok = _newton_undistort(xd[i], yd[i], xd[i], yd[i], k1, k2, p1, p2, k3, r2_safe)
        if ok:
            out_x[i] = x
            out_y[i] = y
            px = x
            py = y
            pxd = xd[i]
            pyd = yd[i]
        else:
            out_x[i] = np.nan
            out_y[i] = np.nan
            px = np.nan


@njit(cache=True, nogil=True)
def _undistort_grid(fx: float, skew: float, cx: float, fy: float, cy: float, k1: float, k2: float, p1: float,
                    p2: float, k3: float, r2_safe: float, out_x: np.ndarray, out_y: np.ndarray) -> None:
    """Rays through the pixel-corner grid: out[i, j] for pixel point (j - 0.5, i - 0.5)."""
    gh, gw = out_x.shape
    for i in range(gh):
        yd = (i - 0.5 - cy) / fy
        x = np.nan
        y = np.nan
        for j in range(gw):
            xd = (j - 0.5 - cx - skew * yd) / fx
            # Warm start from the left neighbour (or the row above): two Newton steps usually suffice.
            if x != x:
                if i > 0 and out_x[i - 1, j] == out_x[i - 1, j]:
                    x = out_x[i - 1, j]
                    y = out_y[i - 1, j]
                else:
                    x = xd
                    y = yd
            x, y, ok = _newton_undistort(xd, yd, x, y, k1, k2, p1, p2, k3, r2_safe)
            if not ok:
                x, y, ok = _newton_undistort(xd, yd, xd, yd, k1, k2, p1, p2, k3, r2_safe)
            if ok:
                out_x[i, j] = x
                out_y[i, j] = y
            else:
                out_x[i, j] = np.nan
                out_y[i, j] = np.nan
                x = np.nan
                y = np.nan


def undistort_normalized(xd: np.ndarray, yd: np.ndarray, dist: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Invert OpenCV's distortion: undistorted (x, y) of distorted normalised coordinates (1-D arrays).

    Newton's method to 1e-14; points where the model folds over (no unique inverse) come back NaN.
    """
    xd = np.ascontiguousarray(xd, dtype=np.float64).ravel()
    yd = np.ascontiguousarray(yd, dtype=np.float64).ravel()
    d = np.asarray(dist, dtype=np.float64).ravel()
    out_x = np.empty_like(xd)
    out_y = np.empty_like(yd)
    _undistort_kernel(xd, yd, float(d[0]), float(d[1]), float(d[2]), float(d[3]), float(d[4]), monotonic_radius2(d),
                      out_x, out_y)
    return out_x, out_y


def stereo_right_pose(R_left_world: np.ndarray, t_left_world_mm: np.ndarray, R_right_left: np.ndarray,
                      T_right_left_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pose of the right camera from the left one and the rig extrinsics (X_right = R X_left + T)."""
    R = np.asarray(R_right_left) @ np.asarray(R_left_world)
    t = np.asarray(R_right_left) @ np.asarray(t_left_world_mm).ravel() + np.asarray(T_right_left_mm).ravel()
    return R, t
