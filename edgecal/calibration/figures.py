"""The calibration report's figures, drawn with matplotlib: each function takes a calibration (and the
per-view results) and returns PNG bytes. No global pyplot state: every figure is its own Figure with
an Agg canvas, so figures can be drawn from any thread and nothing is shown on a screen.

What each figure is for (a person checking a calibration):
- per-view RMS: a view that fits worse than the others (a blurred or misdetected image), named by file;
- residual vectors: residuals that line up over the image mean a wrong model, random ones are noise;
- coverage: where the corners were; distortion is extrapolated where there were none;
- residual against radius: a trend with the distance from the centre is a lens model that is too weak;
- lens distortion: how far the lens moves each pixel (sanity of the distortion terms);
- rectified pair: corners of one row must lie on one horizontal line in both images.
"""

from __future__ import annotations

import io

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from edgecal.calibration.results import ViewResult
from edgecal.calibration.types import Calibration
from edgecal.camera import CameraModel

DPI = 100
CAMERA_COLOURS = ("tab:blue", "tab:orange")


def _png(fig: Figure) -> bytes:
    FigureCanvasAgg(fig)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI)
    return buf.getvalue()


def _image_axes(ax, size: tuple[int, int], title: str) -> None:
    """Axes in image pixels: x to the right, y down, the image's border drawn."""
    w, h = size
    ax.set_xlim(-0.5, w - 0.5)
    ax.set_ylim(h - 0.5, -0.5)
    ax.set_aspect("equal")
    ax.set_title(title, fontsize=10)
    ax.set_xlabel("x (px)")
    ax.set_ylabel("y (px)")
    ax.plot([-0.5, w - 0.5, w - 0.5, -0.5, -0.5], [-0.5, -0.5, h - 0.5, h - 0.5, -0.5], color="0.3", lw=0.8)


def _corners_of(cal: Calibration, c: int, inlier: bool | None = True) -> tuple[np.ndarray, np.ndarray]:
    """All detected pixels and residuals (N, 2) of camera ``c`` over the used views (inliers, outliers or all)."""
    px, res = [], []
    for cs, r, m in zip(cal.corners[c], cal.residuals_px[c], cal.inliers[c]):
        if not len(cs):
            continue
        keep = m if inlier is True else ~m if inlier is False else np.ones(len(m), bool)
        px.append(cs.image_px[keep])
        res.append(r[keep])
    if not px:
        return np.zeros((0, 2)), np.zeros((0, 2))
    return np.concatenate(px), np.concatenate(res)


def view_rms_figure(results: list[ViewResult], camera_names: tuple[str, ...]) -> bytes:
    """Horizontal bars: each view's RMS per camera, named by its file; skipped views and dropped corners marked."""
    n = len(results)
    fig = Figure(figsize=(8.0, max(2.2, 0.28 * n * len(camera_names) + 1.2)))
    ax = fig.add_subplot(1, 1, 1)
    height = 0.8 / len(camera_names)
    finite = [v for r in results for v in r.rms_px if np.isfinite(v)]
    top = max(finite) if finite else 1.0
    for c, name in enumerate(camera_names):
        y = np.arange(n) + (c - (len(camera_names) - 1) / 2) * height
        values = [r.rms_px[c] if r.used and np.isfinite(r.rms_px[c]) else 0.0 for r in results]
        ax.barh(y, values, height=height * 0.9, color=CAMERA_COLOURS[c % 2], label=name)
        for yi, r in zip(y, results):
            if r.used and r.dropped[c]:
                ax.text(r.rms_px[c] + 0.01 * top, yi, f"{len(r.dropped[c])} dropped", va="center", fontsize=7,
                        color="crimson")
    for i, r in enumerate(results):
        if not r.used:
            ax.text(0.01 * top, i, f"skipped: {r.why_not}", va="center", fontsize=7, color="0.35")
    ax.set_yticks(np.arange(n))
    ax.set_yticklabels([r.name if r.used else f"{r.name} (skipped)" for r in results], fontsize=7)
    ax.invert_yaxis()
    ax.set_xlabel("reprojection RMS of the kept corners (px)")
    ax.set_xlim(0, top * 1.35 if finite else 1.0)
    ax.set_title("RMS per view", fontsize=10)
    if len(camera_names) > 1:
        ax.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    return _png(fig)


def _quiver_scale(res: np.ndarray, width: int) -> float:
    """Arrow gain so that the 95th-percentile residual is drawn 4 % of the image width long."""
    if not len(res):
        return 1.0
    p95 = float(np.percentile(np.linalg.norm(res, axis=1), 95))
    return 0.04 * width / max(p95, 1e-6)


def residual_vectors_figure(cal: Calibration, c: int) -> bytes:
    """Each kept corner's residual (reprojected - detected) as an arrow over the image, magnified; dropped in red."""
    w, h = cal.image_size
    fig = Figure(figsize=(6.4, 6.4 * h / w + 0.8))
    ax = fig.add_subplot(1, 1, 1)
    px, res = _corners_of(cal, c)
    gain = _quiver_scale(res, w)
    if len(px):
        ax.quiver(px[:, 0], px[:, 1], res[:, 0] * gain, res[:, 1] * gain, angles="xy", scale_units="xy", scale=1,
                  width=0.0025, color="tab:blue")
    bad, _ = _corners_of(cal, c, inlier=False)
    if len(bad):
        ax.plot(bad[:, 0], bad[:, 1], "x", color="crimson", ms=6, label=f"{len(bad)} dropped")
        ax.legend(fontsize=8, loc="lower right")
    _image_axes(ax, (w, h), f"{cal.camera_names[c]}: residuals, magnified x{gain:.0f}")
    fig.tight_layout()
    return _png(fig)


def coverage_figure(cal: Calibration, c: int, cells: tuple[int, int] = (16, 12)) -> bytes:
    """Heat map of how many kept corners fell into each cell of the image."""
    w, h = cal.image_size
    fig = Figure(figsize=(6.4, 6.4 * h / w + 0.8))
    ax = fig.add_subplot(1, 1, 1)
    px, _ = _corners_of(cal, c, inlier=None)
    counts, xe, ye = np.histogram2d(px[:, 0] if len(px) else [], px[:, 1] if len(px) else [], bins=cells,
                                    range=[[-0.5, w - 0.5], [-0.5, h - 0.5]])
    im = ax.imshow(counts.T, extent=(xe[0], xe[-1], ye[-1], ye[0]), cmap="viridis", interpolation="nearest",
                   vmin=0)
    empty = float((counts == 0).mean())
    fig.colorbar(im, ax=ax, fraction=0.035, pad=0.02, label="corners per cell")
    _image_axes(ax, (w, h), f"{cal.camera_names[c]}: corner coverage ({100 * (1 - empty):.0f} % of cells)")
    fig.tight_layout()
    return _png(fig)


def residual_radius_figure(cal: Calibration, c: int) -> bytes:
    """Residual length and its radial part against the distance from the principal point, with binned means."""
    cam = cal.cameras[c]
    px, res = _corners_of(cal, c)
    fig = Figure(figsize=(6.4, 3.6))
    ax = fig.add_subplot(1, 1, 1)
    if len(px):
        d = px - [cam.cx, cam.cy]
        r = np.linalg.norm(d, axis=1)
        radial = np.sum(res * d, axis=1) / np.maximum(r, 1e-9)
        ax.plot(r, np.linalg.norm(res, axis=1), ".", ms=2, color="0.6", label="|residual|")
        ax.plot(r, radial, ".", ms=2, color="tab:blue", alpha=0.5, label="radial part")
        edges = np.linspace(0, r.max() + 1e-9, 11)
        idx = np.digitize(r, edges) - 1
        centres, means = [], []
        for b in range(10):
            m = idx == b
            if m.sum() >= 5:
                centres.append(0.5 * (edges[b] + edges[b + 1]))
                means.append(float(np.mean(radial[m])))
        ax.plot(centres, means, "-o", color="crimson", ms=4, label="mean radial part")
    ax.axhline(0, color="0.3", lw=0.8)
    ax.set_xlabel("distance from the principal point (px)")
    ax.set_ylabel("residual (px)")
    ax.set_title(f"{cal.camera_names[c]}: residual against radius ({cam.lens} lens); a trend = a lens model "
                 "too weak", fontsize=9)
    ax.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    return _png(fig)


def distortion_figure(cam: CameraModel, name: str) -> bytes:
    """How far the lens moves each pixel from where a pinhole camera would put it (px), with arrows."""
    w, h = cam.image_size
    fig = Figure(figsize=(6.4, 6.4 * h / w + 0.8))
    ax = fig.add_subplot(1, 1, 1)
    nx, ny = 64, max(2, int(round(64 * h / w)))
    gx, gy = np.meshgrid(np.linspace(0, w - 1, nx), np.linspace(0, h - 1, ny))
    q = np.stack([gx.ravel(), gy.ravel()], axis=1)
    xy = cam.undistort_points(q)
    ideal = np.stack([cam.fx * xy[:, 0] + cam.cx, cam.fy * xy[:, 1] + cam.cy], axis=1)
    shift = q - ideal   # distorted - ideal: the lens's displacement
    mag = np.linalg.norm(shift, axis=1).reshape(ny, nx)
    finite = np.isfinite(mag)
    im = ax.imshow(np.where(finite, mag, np.nan), extent=(-0.5, w - 0.5, h - 0.5, -0.5), cmap="magma",
                   interpolation="bilinear")
    fig.colorbar(im, ax=ax, fraction=0.035, pad=0.02, label="displacement (px)")
    if finite.any() and np.nanmax(mag) > 0:
        levels = [v for v in (0.5, 1, 2, 5, 10, 20, 50, 100, 200) if v < np.nanmax(mag)]
        if levels:
            cs = ax.contour(gx, gy, np.where(finite, mag, np.nan), levels=levels, colors="w", linewidths=0.6)
            ax.clabel(cs, fontsize=7, fmt="%g px")
        step = 8
        sub = (slice(None, None, step), slice(None, None, step))
        s = shift.reshape(ny, nx, 2)
        ax.quiver(gx[sub], gy[sub], -s[sub][..., 0], -s[sub][..., 1], angles="xy", scale_units="xy", scale=1,
                  color="cyan", width=0.003)
    _image_axes(ax, (w, h), f"{name}: lens distortion ({cam.lens}), arrows point from the image to the pinhole "
                "position")
    fig.tight_layout()
    return _png(fig)


def rectified_pair_figure(left: np.ndarray, right: np.ndarray, cal: Calibration, view: int) -> bytes:
    """The rectified left and right images of one view side by side, with horizontal epipolar lines and the
    rectified corners: a corner and its match lie on one line."""
    import cv2

    from edgecal.calibration.stereo import rectification_maps
    rect = cal.rectification
    assert rect is not None
    size = (cal.image_size[0], cal.image_size[1])
    out = []
    for img, cam, R, P in ((left, cal.cameras[0], rect.r1, rect.p1), (right, cal.cameras[1], rect.r2, rect.p2)):
        mx, my = rectification_maps(cam, R, P, size)
        out.append(cv2.remap(img, mx, my, cv2.INTER_LINEAR))
    w, h = size
    fig = Figure(figsize=(10.0, 10.0 * h / (2 * w) + 0.9))
    axes = [fig.add_subplot(1, 2, i + 1) for i in range(2)]
    lines = np.linspace(0, h - 1, 17)[1:-1]
    for i, (ax, img) in enumerate(zip(axes, out)):
        ax.imshow(img, cmap="gray", vmin=0, vmax=255, extent=(-0.5, w - 0.5, h - 0.5, -0.5))
        for y in lines:
            ax.axhline(y, color="lime", lw=0.5, alpha=0.7)
        cam = cal.cameras[i]
        cs = cal.corners[i][view]
        if len(cs):
            xy = cam.undistort_points(cs.image_px)
            R = rect.r1 if i == 0 else rect.r2
            P = rect.p1 if i == 0 else rect.p2
            ray = np.c_[xy, np.ones(len(xy))] @ R.T
            q = ray @ P[:, :3].T
            ax.plot(q[:, 0] / q[:, 2], q[:, 1] / q[:, 2], "+", color="red", ms=4, mew=0.8)
        _image_axes(ax, size, f"{cal.camera_names[i]}, rectified")
    fig.suptitle(f"epipolar error RMS {rect.epipolar_rms_px:.3f} px, max {rect.epipolar_max_px:.3f} px", fontsize=10)
    fig.tight_layout()
    return _png(fig)


def residual_histogram_figure(cal: Calibration) -> bytes:
    """Histogram of residual lengths of the kept corners, per camera."""
    fig = Figure(figsize=(6.4, 3.2))
    ax = fig.add_subplot(1, 1, 1)
    for c, name in enumerate(cal.camera_names):
        _, res = _corners_of(cal, c)
        if len(res):
            ax.hist(np.linalg.norm(res, axis=1), bins=30, alpha=0.6, color=CAMERA_COLOURS[c % 2], label=name)
    ax.set_xlabel("residual length (px)")
    ax.set_ylabel("corners")
    ax.set_title(f"residuals of the kept corners, RMS {cal.rms_px:.3f} px", fontsize=10)
    if cal.is_stereo:
        ax.legend(fontsize=8)
    fig.tight_layout()
    return _png(fig)


def per_board_figure(cal: Calibration) -> bytes:
    """Bar chart of the RMS per camera and board."""
    per_board = cal.per_board_rms_px()
    fig = Figure(figsize=(6.4, max(2.0, 0.35 * len(per_board) + 1.0)))
    ax = fig.add_subplot(1, 1, 1)
    ax.barh(list(per_board), list(per_board.values()), color="tab:blue")
    ax.invert_yaxis()
    ax.set_xlabel("RMS (px)")
    ax.set_title("reprojection RMS per camera/board", fontsize=10)
    fig.tight_layout()
    return _png(fig)


__all__ = ["coverage_figure", "distortion_figure", "per_board_figure", "rectified_pair_figure",
           "residual_histogram_figure", "residual_radius_figure", "residual_vectors_figure", "view_rms_figure"]
