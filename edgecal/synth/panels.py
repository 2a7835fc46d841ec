"""The scene's panels: flat rectangles (chessboards and plain plates) in the world frame, and the packed
(P, N_COLUMNS) array of them in a camera's frame that the numba kernels of render.py read.

Printed side: a board's pattern faces the side opposite its normal x_axis × y_axis (the board's z axis
points away from a camera that sees the pattern, as in OpenCV); from behind, a panel shows ``back_albedo``.
Column names (ORIGIN, X_AXIS, ..., BBOX) are the one description of the packed layout; the ray/panel
helpers (ray_plane, panel_uv, outside_panel) are the geometry on it that every kernel uses.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from edgecal.targets import Board, Target

# Columns of the packed per-panel array handed to the kernels (camera frame, mm); numba reads these module
# constants as compile-time literals. ORIGIN, X_AXIS, Y_AXIS and NORMAL start three columns each (x, y, z).
ORIGIN, X_AXIS, Y_AXIS, NORMAL = 0, 3, 6, 9              # origin, x axis, y axis, normal x_axis × y_axis
UMIN, VMIN, UMAX, VMAX = 12, 13, 14, 15  # the panel's extent along x_axis / y_axis (mm)
SQUARE, COLS, ROWS = 16, 17, 18         # the board's square (mm; 0 for a plain panel) and inner corners
BLACK, WHITE, BACK, FRONT = 19, 20, 21, 22  # albedos; FRONT 1.0 when the camera sees the printed side
BBOX = 23  # 23..26: bounding box (x0, y0, x1, y1) of the panel's image in undistorted normalised coordinates
N_COLUMNS = 27


# shared default arguments of panels_from_target: read-only so no caller can change them
_IDENTITY = np.eye(3)
_IDENTITY.flags.writeable = False
_NO_SHIFT = np.zeros(3)
_NO_SHIFT.flags.writeable = False


@dataclass(frozen=True)
class Panel:
    """A flat rectangle in the world frame, optionally printed with a chessboard.

    ``origin_mm`` is the board's inner corner (0, 0) (or any reference point of a plain panel);
    ``extent_mm`` = (umin, vmin, umax, vmax) is the rectangle along ``x_axis``/``y_axis`` relative to it.
    ``board`` is None for a plain panel (uniform ``white_albedo`` on its front).
    """

    name: str
    origin_mm: np.ndarray
    x_axis: np.ndarray
    y_axis: np.ndarray
    extent_mm: tuple[float, float, float, float]
    board: Board | None = None
    black_albedo: float = 0.06
    white_albedo: float = 0.85
    back_albedo: float = 0.55

    @property
    def normal(self) -> np.ndarray:
        """Unit normal x_axis × y_axis; the printed side faces -normal."""
        return np.cross(self.x_axis, self.y_axis)


def board_panel_extent(board: Board, margin_mm: float | None = None) -> tuple[float, float, float, float]:
    """Extent of a board's panel: the squares plus a white margin (default: one square, at least 6 mm)."""
    s = board.square_mm
    m = max(s, 6.0) if margin_mm is None else float(margin_mm)
    return (-s - m, -s - m, board.cols * s + m, board.rows * s + m)


def panels_from_target(target: Target, R_world_target: np.ndarray = _IDENTITY,
                       t_world_target_mm: np.ndarray = _NO_SHIFT, *,
                       extents: dict[str, tuple[float, float, float, float]] | None = None,
                       margin_mm: float | None = None, black_albedo: float = 0.06,
                       white_albedo: float = 0.85) -> list[Panel]:
    """One printed Panel per board of ``target``, placed in the world by the pose T_world_target.

    ``extents`` overrides the panel rectangle of named boards (e.g. a whole face of the calibration box).
    """
    R = np.asarray(R_world_target, dtype=np.float64)
    t = np.asarray(t_world_target_mm, dtype=np.float64).ravel()
    out = []
    for b in target.boards:
        ext = (extents or {}).get(b.name) or board_panel_extent(b, margin_mm)
        umin, vmin, umax, vmax = (float(v) for v in ext)
        out.append(Panel(b.name, R @ b.origin_mm + t, R @ b.x_axis, R @ b.y_axis, (umin, vmin, umax, vmax),
                         b, black_albedo, white_albedo))
    return out


def pack_panels(panels: list[Panel], R_cam_world: np.ndarray, t_cam_world_mm: np.ndarray) -> np.ndarray:
    """The (P, 27) float64 array of panels in the camera frame that the kernels read."""
    R = np.asarray(R_cam_world, dtype=np.float64)
    t = np.asarray(t_cam_world_mm, dtype=np.float64).ravel()
    arr = np.zeros((len(panels), N_COLUMNS))
    for i, p in enumerate(panels):
        o = R @ np.asarray(p.origin_mm, dtype=np.float64) + t
        ex = R @ np.asarray(p.x_axis, dtype=np.float64)
        ey = R @ np.asarray(p.y_axis, dtype=np.float64)
        n = np.cross(ex, ey)
        arr[i, ORIGIN:ORIGIN + 3] = o
        arr[i, X_AXIS:X_AXIS + 3] = ex
        arr[i, Y_AXIS:Y_AXIS + 3] = ey
        arr[i, NORMAL:NORMAL + 3] = n
        arr[i, UMIN:VMAX + 1] = p.extent_mm
        if p.board is not None:
            arr[i, SQUARE] = p.board.square_mm
            arr[i, COLS] = p.board.cols
            arr[i, ROWS] = p.board.rows
        arr[i, BLACK] = p.black_albedo
        arr[i, WHITE] = p.white_albedo
        arr[i, BACK] = p.back_albedo
        # The camera (origin) sees the printed side when it lies on the -normal side of the plane.
        arr[i, FRONT] = 1.0 if float(n @ o) > 0.0 else 0.0
        # A panel in front of the camera projects to a convex quadrilateral: its bounding box rejects most
        # rays with four comparisons. A panel reaching behind the camera gets no box.
        u0, v0, u1, v1 = p.extent_mm
        corners = np.array([o + a * ex + b * ey for a, b in ((u0, v0), (u1, v0), (u1, v1), (u0, v1))])
        if np.all(corners[:, 2] > 1e-6):
            xy = corners[:, :2] / corners[:, 2:3]
            arr[i, BBOX:BBOX + 4] = (xy[:, 0].min() - 1e-9, xy[:, 1].min() - 1e-9,
                                       xy[:, 0].max() + 1e-9, xy[:, 1].max() + 1e-9)
        else:
            arr[i, BBOX:BBOX + 4] = (-np.inf, -np.inf, np.inf, np.inf)
    return arr


# The ray/panel geometry every kernel shares. inline="always": numba inlines them in its own IR (as plain calls
# the chained extent test made the renderer 1.6x slower, measured with bench/render.py's scene).
@njit(cache=True, nogil=True, inline="always")
def ray_plane(x: float, y: float, z: float, panels: np.ndarray, p: int) -> float:
    """Where the ray t (x, y, z) from the camera centre meets panel ``p``'s plane: t, inf when parallel."""
    nx = panels[p, NORMAL]
    ny = panels[p, NORMAL + 1]
    nz = panels[p, NORMAL + 2]
    den = nx * x + ny * y + nz * z
    if abs(den) < 1e-15:
        return np.inf
    return (nx * panels[p, ORIGIN] + ny * panels[p, ORIGIN + 1] + nz * panels[p, ORIGIN + 2]) / den


@njit(cache=True, nogil=True, inline="always")
def panel_uv(t: float, x: float, y: float, z: float, panels: np.ndarray, p: int) -> tuple[float, float]:
    """Panel ``p``'s own coordinates (u, v) (mm along x_axis, y_axis from its origin) of the point t (x, y, z)."""
    dx = t * x - panels[p, ORIGIN]
    dy = t * y - panels[p, ORIGIN + 1]
    dz = t * z - panels[p, ORIGIN + 2]
    u = dx * panels[p, X_AXIS] + dy * panels[p, X_AXIS + 1] + dz * panels[p, X_AXIS + 2]
    v = dx * panels[p, Y_AXIS] + dy * panels[p, Y_AXIS + 1] + dz * panels[p, Y_AXIS + 2]
    return u, v


@njit(cache=True, nogil=True, inline="always")
def outside_panel(u: float, v: float, panels: np.ndarray, p: int) -> bool:
    """(u, v) lies off panel ``p`` (beyond its extent; the edges belong to the panel)."""
    return u < panels[p, UMIN] or u > panels[p, UMAX] or v < panels[p, VMIN] or v > panels[p, VMAX]
