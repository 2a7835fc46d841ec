"""The camera model: intrinsics, a lens model by name with its parameter vector, the image size.

One type (`CameraModel`) and pure array functions on it: `project` (camera-frame points -> pixels, with
the Jacobians the solvers need), `unproject` (pixels -> unit rays) and `undistort_points` (pixels ->
ideal normalised coordinates). A stereo pair is a `StereoRig`. Nothing here keeps state or reads files.

Lens models (the names are the ones rig.yaml writes; docs/conventions.md):
- ``radtan``   OpenCV's pinhole model (k1, k2, p1, p2, k3); ROS ``plumb_bob``. Calibration can free any
               subset (``none``, ``k1``, ``k1k2``, ... see `DISTORTION_MODELS`); the rest stay 0.
- ``rational`` OpenCV's CALIB_RATIONAL_MODEL (k1, k2, p1, p2, k3, k4, k5, k6); ROS ``rational_polynomial``.
- ``fisheye``  Kannala-Brandt on the angle theta from the axis (k1, k2, k3, k4): r = theta (1 + k1 theta^2
               + ... + k4 theta^8); OpenCV cv2.fisheye, ROS ``equidistant``, Kalibr ``pinhole-equi``. Defined
               for rays behind the camera plane too (theta up to pi), so a 190 degree lens is one model.

Projection follows OpenCV exactly (tests compare against cv2.projectPoints and cv2.fisheye.projectPoints).
The inverses are solved by Newton's method to ~1e-14 (normalised), far below a thousandth of a pixel,
because the renderer's ground truth and the pose's triangulation are only as good as this inverse. OpenCV's
own cv2.undistortPoints stops after 5 iterations by default, which leaves ~0.01 px on strong lenses.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numba import njit

# Parameter names of each lens model, in the order of its parameter vector (OpenCV's order).
LENS_PARAMS: dict[str, tuple[str, ...]] = {
    "radtan": ("k1", "k2", "p1", "p2", "k3"),
    "rational": ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
    "fisheye": ("k1", "k2", "k3", "k4"),
}
# ROS sensor_msgs/CameraInfo distortion_model of each lens model.
ROS_DISTORTION_MODEL = {"radtan": "plumb_bob", "rational": "rational_polynomial", "fisheye": "equidistant"}
# What a calibration may fit: (lens model, free parameters). "none" is the ideal pinhole.
DISTORTION_MODELS: dict[str, tuple[str, tuple[str, ...]]] = {
    "none": ("radtan", ()),
    "k1": ("radtan", ("k1",)),
    "k1k2": ("radtan", ("k1", "k2")),
    "k1k2k3": ("radtan", ("k1", "k2", "k3")),
    "k1k2p1p2": ("radtan", ("k1", "k2", "p1", "p2")),
    "k1k2p1p2k3": ("radtan", ("k1", "k2", "p1", "p2", "k3")),
    "rational": ("rational", LENS_PARAMS["rational"]),
    "fisheye": ("fisheye", LENS_PARAMS["fisheye"]),
}
INTRINSIC_NAMES = ("fx", "fy", "cx", "cy")

_NEWTON_ITERATIONS = 40   # Newton converges quadratically; 40 is a bound, not a typical count
_NEWTON_TOL = 1e-14       # normalised units: ~1e-11 px at f = 1000
_FOLD_SAMPLES = 16        # points checked between the axis and a solution for a fold of the lens model


@dataclass(frozen=True)
class CameraModel:
    """One camera: focal lengths and principal point (px), lens model by name, its parameters, image size.

    ``params`` is in the order of ``LENS_PARAMS[lens]``; ``image_size`` is (width, height) in pixels.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    lens: str = "radtan"
    params: np.ndarray = field(default_factory=lambda: np.zeros(5))
    image_size: tuple[int, int] = (0, 0)

    def __post_init__(self) -> None:
        if self.lens not in LENS_PARAMS:
            raise ValueError(f"lens model {self.lens!r} unknown (one of {', '.join(LENS_PARAMS)})")
        n = len(LENS_PARAMS[self.lens])
        given = np.asarray(self.params, dtype=np.float64).ravel()
        if len(given) > n and np.any(given[n:] != 0):
            raise ValueError(f"lens model {self.lens} has {n} parameters, {len(given)} given")
        p = np.zeros(n)
        p[:min(n, len(given))] = given[:n]
        p.setflags(write=False)
        for name in ("fx", "fy", "cx", "cy"):
            object.__setattr__(self, name, float(getattr(self, name)))
        object.__setattr__(self, "params", p)
        object.__setattr__(self, "image_size", (int(self.image_size[0]), int(self.image_size[1])))

    @staticmethod
    def from_opencv(camera_matrix: np.ndarray, dist_coeffs: np.ndarray, image_size: tuple[int, int] = (0, 0),
                    lens: str | None = None) -> CameraModel:
        """From OpenCV's camera matrix and distortion vector.

        Without ``lens``, 8 or more coefficients with any of k4..k6 set mean ``rational``, else ``radtan``
        (a 4-vector is radtan's k1 k2 p1 p2, as for cv2.projectPoints: fisheye must be named).
        """
        k = np.asarray(camera_matrix, dtype=np.float64).reshape(3, 3)
        d = np.asarray(dist_coeffs, dtype=np.float64).ravel()
        if lens is None:
            lens = "rational" if len(d) >= 8 and np.any(d[5:8] != 0) else "radtan"
        if len(d) > 8 and np.any(d[8:] != 0):
            raise ValueError("thin-prism and tilt distortion terms (beyond k6) are not supported")
        return CameraModel(k[0, 0], k[1, 1], k[0, 2], k[1, 2], lens, d[:len(LENS_PARAMS[lens])], image_size)

    @property
    def camera_matrix(self) -> np.ndarray:
        """OpenCV's 3x3 K."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def dist_coeffs(self) -> np.ndarray:
        """The distortion vector as OpenCV's functions for this lens take it (5, 8 or 4 numbers)."""
        return np.array(self.params, dtype=np.float64)

    @property
    def param_names(self) -> tuple[str, ...]:
        """Names of ``params``."""
        return LENS_PARAMS[self.lens]

    @property
    def intrinsics(self) -> np.ndarray:
        """(fx, fy, cx, cy, *params): the vector `project`'s intrinsics Jacobian refers to."""
        return np.r_[self.fx, self.fy, self.cx, self.cy, self.params]

    @property
    def intrinsic_names(self) -> tuple[str, ...]:
        """Names of ``intrinsics``."""
        return INTRINSIC_NAMES + self.param_names

    @property
    def ros_distortion_model(self) -> str:
        """The ROS camera_info distortion_model name."""
        return ROS_DISTORTION_MODEL[self.lens]

    def with_intrinsics(self, intrinsics: np.ndarray) -> CameraModel:
        """The same lens model and size with new (fx, fy, cx, cy, *params)."""
        v = np.asarray(intrinsics, dtype=np.float64).ravel()
        return CameraModel(v[0], v[1], v[2], v[3], self.lens, v[4:], self.image_size)

    def with_lens(self, lens: str, params: np.ndarray | None = None) -> CameraModel:
        """The same focal lengths, principal point and size with another lens model (parameters 0 if not given)."""
        return CameraModel(self.fx, self.fy, self.cx, self.cy, lens,
                           np.zeros(len(LENS_PARAMS[lens])) if params is None else params, self.image_size)

    def project(self, p_cam: np.ndarray) -> np.ndarray:
        """Pixels (..., 2) of camera-frame points (..., 3); see `project`."""
        return project(p_cam, self)

    def unproject(self, q: np.ndarray) -> np.ndarray:
        """Unit rays (..., 3) through pixels (..., 2); see `unproject`."""
        return unproject(q, self)

    def undistort_points(self, q: np.ndarray) -> np.ndarray:
        """Normalised ideal coordinates (..., 2) of pixels (..., 2); see `undistort_points`."""
        return undistort_points(q, self)

    def key(self) -> tuple:
        """A hashable identity (for caches of per-pixel rays)."""
        return (self.lens, tuple(np.round(self.intrinsics, 12)), self.image_size)


@dataclass(frozen=True)
class StereoRig:
    """Two cameras and ``T_right_left``: X_right = R_right_left X_left + t_right_left_m (metres)."""

    left: CameraModel
    right: CameraModel
    R_right_left: np.ndarray
    t_right_left_m: np.ndarray

    def __post_init__(self) -> None:
        r = np.asarray(self.R_right_left, dtype=np.float64).reshape(3, 3).copy()
        t = np.asarray(self.t_right_left_m, dtype=np.float64).reshape(3).copy()
        r.setflags(write=False)
        t.setflags(write=False)
        object.__setattr__(self, "R_right_left", r)
        object.__setattr__(self, "t_right_left_m", t)

    @property
    def cameras(self) -> tuple[CameraModel, CameraModel]:
        """(left, right)."""
        return self.left, self.right

    @property
    def baseline_m(self) -> float:
        """Distance between the two optical centres."""
        return float(np.linalg.norm(self.t_right_left_m))

    @property
    def image_size(self) -> tuple[int, int]:
        """The left camera's (width, height)."""
        return self.left.image_size


# ---------------------------------------------------------------------------------------------- projection

def _radtan_distort(x: np.ndarray, y: np.ndarray, d: np.ndarray, want_jac: bool) -> tuple:
    """OpenCV's distortion of normalised (x, y) (arrays of one shape); d = (k1 k2 p1 p2 k3 [k4 k5 k6]).

    Returns xd, yd and, if asked, d(xd, yd)/d(x, y) as (a, b, c, e) = [[a, b], [c, e]] (the derivatives by
    the parameters are _radtan_param_jacobian's: Newton's inverse needs only these).
    """
    xs = np.ascontiguousarray(x, dtype=np.float64)
    ys = np.ascontiguousarray(y, dtype=np.float64)
    k = np.zeros(8)
    k[:len(d)] = d
    xd, yd, a, b, e = _radtan_distort_kernel(xs.ravel(), ys.ravel(), k, want_jac)
    shape = xs.shape
    if not want_jac:
        return xd.reshape(shape), yd.reshape(shape)
    b = b.reshape(shape)
    return xd.reshape(shape), yd.reshape(shape), (a.reshape(shape), b, b, e.reshape(shape))


@njit(cache=True, nogil=True)
def _radtan_distort_kernel(x: np.ndarray, y: np.ndarray, d: np.ndarray, want_jac: bool) -> tuple:
    """_radtan_distort on flat arrays, d padded to 8 (k4..k6 = 0 for radtan): xd, yd, a, b, e (a, b, e empty
    unless ``want_jac``). One pass per point instead of ~25 array operations (Newton's inverse calls it
    ~20 times per frame); the same float64 operations in the same order, so the same numbers."""
    k1, k2, p1, p2, k3, k4, k5, k6 = d[0], d[1], d[2], d[3], d[4], d[5], d[6], d[7]
    n = x.shape[0]
    xd = np.empty(n)
    yd = np.empty(n)
    m = n if want_jac else 0
    a = np.empty(m)
    b = np.empty(m)
    e = np.empty(m)
    for i in range(n):
        xi = x[i]
        yi = y[i]
        r2 = xi * xi + yi * yi
        num = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        den = 1.0 + r2 * (k4 + r2 * (k5 + r2 * k6))
        c = num / den
        xy2 = 2.0 * xi * yi
        xd[i] = xi * c + p1 * xy2 + p2 * (r2 + 2.0 * xi * xi)
        yd[i] = yi * c + p1 * (r2 + 2.0 * yi * yi) + p2 * xy2
        if want_jac:
            dnum = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
            dden = k4 + r2 * (2.0 * k5 + 3.0 * k6 * r2)
            dc = (dnum * den - num * dden) / (den * den)   # dc / d(r2)
            a[i] = c + 2.0 * xi * xi * dc + 2.0 * p1 * yi + 6.0 * p2 * xi
            b[i] = 2.0 * xi * yi * dc + 2.0 * p1 * xi + 2.0 * p2 * yi
            e[i] = c + 2.0 * yi * yi * dc + 6.0 * p1 * yi + 2.0 * p2 * xi
    return xd, yd, a, b, e


def _radtan_param_jacobian(x: np.ndarray, y: np.ndarray, d: np.ndarray) -> np.ndarray:
    """d(xd, yd)/d(params) (..., 2, len(d)) of _radtan_distort at normalised (x, y)."""
    k1, k2, k3 = d[0], d[1], d[4]
    k4, k5, k6 = (d[5], d[6], d[7]) if len(d) == 8 else (0.0, 0.0, 0.0)
    r2 = x * x + y * y
    num = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    den = 1.0 + r2 * (k4 + r2 * (k5 + r2 * k6))
    c = num / den
    xy2 = 2.0 * x * y
    r4, r6 = r2 * r2, r2 * r2 * r2
    jp = np.zeros(x.shape + (2, len(d)))
    for i, rk in ((0, r2), (1, r4), (4, r6)):
        jp[..., 0, i] = x * rk / den
        jp[..., 1, i] = y * rk / den
    jp[..., 0, 2], jp[..., 1, 2] = xy2, r2 + 2.0 * y * y
    jp[..., 0, 3], jp[..., 1, 3] = r2 + 2.0 * x * x, xy2
    if len(d) == 8:
        for i, rk in ((5, r2), (6, r4), (7, r6)):
            jp[..., 0, i] = -x * c * rk / den
            jp[..., 1, i] = -y * c * rk / den
    return jp


def _theta_poly(theta: np.ndarray, k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Kannala-Brandt r(theta) = theta (1 + k1 t^2 + k2 t^4 + k3 t^6 + k4 t^8) and dr/dtheta."""
    t2 = theta * theta
    poly = 1.0 + t2 * (k[0] + t2 * (k[1] + t2 * (k[2] + t2 * k[3])))
    dpoly = 1.0 + t2 * (3.0 * k[0] + t2 * (5.0 * k[1] + t2 * (7.0 * k[2] + t2 * 9.0 * k[3])))
    return theta * poly, dpoly


def project(p_cam: np.ndarray, camera: CameraModel, get_gradients: bool = False, intrinsics_gradient: bool = True):
    """Pixels q (..., 2) of camera-frame points p_cam (..., 3) (any unit; only directions matter).

    With ``get_gradients`` returns (q, dq_dp (..., 2, 3), dq_dintrinsics (..., 2, 4 + n_params)), the
    intrinsics being ``camera.intrinsics``; dq_dintrinsics is None when ``intrinsics_gradient`` is False
    (a pose solver, which holds the intrinsics fixed). Pinhole lenses (radtan, rational) give NaN for points
    with z <= 0; the fisheye model projects every direction except straight backwards.
    """
    p = np.asarray(p_cam, dtype=np.float64)
    X, Y, Z = p[..., 0], p[..., 1], p[..., 2]
    d = camera.params
    if camera.lens == "fisheye":
        rho = np.hypot(X, Y)
        theta = np.arctan2(rho, Z)
        r, dr = _theta_poly(theta, d)
        small = rho <= 1e-12 * np.maximum(np.abs(Z), 1e-300)
        rho_s = np.where(small, 1.0, rho)
        # on the axis r / rho -> 1 / Z (theta ~ rho / Z): the pinhole limit
        s = np.where(small, 1.0 / np.where(Z > 0, Z, np.nan), r / rho_s)
        xd, yd = s * X, s * Y
    else:
        with np.errstate(divide="ignore", invalid="ignore"):
            zi = np.where(Z > 0, 1.0 / Z, np.nan)
        x, y = X * zi, Y * zi
        out = _radtan_distort(x, y, d, get_gradients)
        xd, yd = out[0], out[1]
    q = np.stack([camera.fx * xd + camera.cx, camera.fy * yd + camera.cy], axis=-1)
    if not get_gradients:
        return q
    f = np.array([camera.fx, camera.fy])
    if camera.lens == "fisheye":
        n2 = rho * rho + Z * Z
        # d theta / d(X, Y, Z)
        dth = np.stack([Z * X / (rho_s * n2), Z * Y / (rho_s * n2), -rho / n2], axis=-1)
        # xd = r X / rho: d/dp = dr dtheta/dp X/rho + r d(X/rho)/dp
        ux, uy = X / rho_s, Y / rho_s
        drho = np.stack([ux, uy, np.zeros_like(X)], axis=-1)
        jd = np.empty(X.shape + (2, 3))
        for i, (comp, e) in enumerate(((ux, 0), (uy, 1))):
            unit = np.zeros(X.shape + (3,))
            unit[..., e] = 1.0
            dcomp = (unit - comp[..., None] * drho) / rho_s[..., None]   # d(X/rho)/dp
            jd[..., i, :] = (dr * comp)[..., None] * dth + r[..., None] * dcomp
        zi = 1.0 / np.where(Z != 0, Z, np.nan)
        lim = np.zeros(X.shape + (2, 3))
        lim[..., 0, 0] = zi
        lim[..., 1, 1] = zi
        lim[..., 0, 2] = -X * zi * zi
        lim[..., 1, 2] = -Y * zi * zi
        jd = np.where(small[..., None, None], lim, jd)
        powers = theta[..., None] ** (2 * np.arange(1, 5) + 1)
        dparams = np.stack([ux[..., None] * powers, uy[..., None] * powers], axis=-2)
        dparams = np.where(small[..., None, None], 0.0, dparams)
    else:
        a, b, c, e = out[2]
        jx = np.stack([zi, np.zeros_like(zi), -x * zi], axis=-1)
        jy = np.stack([np.zeros_like(zi), zi, -y * zi], axis=-1)
        jd = np.stack([a[..., None] * jx + b[..., None] * jy, c[..., None] * jx + e[..., None] * jy], axis=-2)
    dq_dp = jd * f[:, None]
    if not intrinsics_gradient:
        return q, dq_dp, None
    if camera.lens != "fisheye":
        dparams = _radtan_param_jacobian(x, y, d)
    dq_di = np.zeros(X.shape + (2, 4 + len(d)))
    dq_di[..., 0, 0] = xd
    dq_di[..., 1, 1] = yd
    dq_di[..., 0, 2] = 1.0
    dq_di[..., 1, 3] = 1.0
    dq_di[..., 4:] = dparams * f[:, None]
    return q, dq_dp, dq_di


# ---------------------------------------------------------------------------------------------- inverses

def _normalised_distorted(q: np.ndarray, camera: CameraModel) -> tuple[np.ndarray, np.ndarray]:
    qq = np.asarray(q, dtype=np.float64)
    return (qq[..., 0] - camera.cx) / camera.fx, (qq[..., 1] - camera.cy) / camera.fy


def _radtan_undistort(xd: np.ndarray, yd: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Invert the radtan/rational distortion by Newton's method; NaN where there is no principal inverse.

    Only the solution reached from the optical axis without crossing a fold (where the model stops being
    one-to-one) counts: beyond a fold a pixel has other, unphysical preimages.
    """
    x, y = xd.copy(), yd.copy()
    for _ in range(_NEWTON_ITERATIONS):
        fx_, fy_, (a, b, c, e) = _radtan_distort(x, y, d, True)
        rx, ry = fx_ - xd, fy_ - yd
        det = a * e - b * c
        bad = ~(det > 1e-9)
        det = np.where(bad, 1.0, det)
        x = x - np.where(bad, 0.0, (e * rx - b * ry) / det)
        y = y - np.where(bad, 0.0, (a * ry - c * rx) / det)
        if np.all(bad | (np.abs(rx) + np.abs(ry) < _NEWTON_TOL)):
            break
    fx_, fy_ = _radtan_distort(x, y, d, False)
    ok = np.abs(fx_ - xd) + np.abs(fy_ - yd) < 1e-12
    # fold check: the Jacobian determinant stays positive on the segment from the axis (all the samples
    # of all the points in one call: elementwise, the same numbers as one call per sample)
    s = (np.arange(1, _FOLD_SAMPLES + 1) / _FOLD_SAMPLES).reshape((-1,) + (1,) * x.ndim)
    a, b, c, e = _radtan_distort(s * x, s * y, d, True)[2]
    ok &= np.all((a * e - b * c) > 1e-9, axis=0)
    return np.where(ok, x, np.nan), np.where(ok, y, np.nan)


def _fisheye_theta(theta_d: np.ndarray, k: np.ndarray) -> np.ndarray:
    """Solve r(theta) = theta_d for theta in [0, pi] by Newton's method; NaN where r is not monotonic."""
    theta = np.minimum(theta_d, np.pi)
    for _ in range(_NEWTON_ITERATIONS):
        r, dr = _theta_poly(theta, k)
        bad = ~(dr > 1e-9)
        step = np.where(bad, 0.0, (r - theta_d) / np.where(bad, 1.0, dr))
        theta = np.clip(theta - step, 0.0, np.pi)
        if np.all(bad | (np.abs(step) < _NEWTON_TOL)):
            break
    r, _ = _theta_poly(theta, k)
    ok = np.abs(r - theta_d) < 1e-12 * np.maximum(1.0, theta_d)
    for j in range(1, _FOLD_SAMPLES + 1):
        ok &= _theta_poly(theta * j / _FOLD_SAMPLES, k)[1] > 1e-9
    return np.where(ok, theta, np.nan)


def unproject(q: np.ndarray, camera: CameraModel) -> np.ndarray:
    """Unit rays (..., 3) in the camera frame through pixels q (..., 2); NaN where the lens has no inverse.

    Fisheye rays may point behind the camera plane (z <= 0) when the lens sees more than 180 degrees.
    """
    xd, yd = _normalised_distorted(q, camera)
    if camera.lens == "fisheye":
        theta_d = np.hypot(xd, yd)
        theta = _fisheye_theta(theta_d, camera.params)
        small = theta_d < 1e-15
        s = np.where(small, 1.0, np.sin(theta) / np.where(small, 1.0, theta_d))
        return np.stack([s * xd, s * yd, np.cos(theta)], axis=-1)
    x, y = _radtan_undistort(xd, yd, camera.params)
    v = np.stack([x, y, np.ones_like(x)], axis=-1)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def undistort_points(q: np.ndarray, camera: CameraModel) -> np.ndarray:
    """Ideal normalised coordinates (x/z, y/z) (..., 2) of pixels q (..., 2), as cv2.undistortPoints gives.

    NaN for pixels without an inverse and for fisheye rays at or behind 90 degrees from the axis.
    """
    if camera.lens != "fisheye":
        xd, yd = _normalised_distorted(q, camera)
        return np.stack(_radtan_undistort(xd, yd, camera.params), axis=-1)
    v = unproject(q, camera)
    with np.errstate(divide="ignore", invalid="ignore"):
        zi = np.where(v[..., 2] > 1e-12, 1.0 / v[..., 2], np.nan)
    return v[..., :2] * zi[..., None]


def transform_points(R_a_b: np.ndarray, t_a_b: np.ndarray, p_b: np.ndarray) -> np.ndarray:
    """Points (..., 3) of frame b expressed in frame a: X_a = R_a_b X_b + t_a_b."""
    return np.asarray(p_b, dtype=np.float64) @ np.asarray(R_a_b, dtype=np.float64).T + np.ravel(t_a_b)
