"""A calibration report a person can read: overlays, residual histogram, per-board error, summary text."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from edgecal.calibration.settings import Acceptance
from edgecal.calibration.types import Calibration
from edgecal.calibration.views import View
from edgecal.errors import EdgecalError
from edgecal.fileio import check_outputs, png_bytes, write_atomic_set
from edgecal.images import DEFAULT_MAX_PIXELS, load_grey

VECTOR_GAIN = 20.0  # residual vectors are drawn this many times longer than they are


def _pm(value: float, std: float, fmt: str = ".2f") -> str:
    if np.isnan(std):
        return f"{value:{fmt}} (fixed)"
    return f"{value:{fmt}} ± {std:{fmt}}"


def format_summary(cal: Calibration) -> str:
    """The values ± 1-sigma, RMS, reconstruction and epipolar error, dropped corners: plain text."""
    lines = [f"calibration: {cal.kind}, image {cal.image_size[0]}x{cal.image_size[1]} px"]
    for name, cam, std in zip(cal.camera_names, cal.cameras, cal.camera_std):
        k, d = cam.camera_matrix, np.ravel(cam.dist_coeffs)
        lines.append(f"{name}: fx {_pm(k[0, 0], std['fx'])}  fy {_pm(k[1, 1], std['fy'])}  "
                     f"cx {_pm(k[0, 2], std['cx'])}  cy {_pm(k[1, 2], std['cy'])} px")
        lines.append(f"{' ' * len(name)}  {cam.lens} lens: " + "  ".join(
            f"{n} {_pm(float(v), std.get(n, np.nan), '.5f')}" for n, v in zip(cam.param_names, d)
            if not np.isnan(std.get(n, np.nan)) or v != 0))
        if name in cal.init or "camera" in cal.init:
            info = cal.init.get(name, cal.init.get("camera", {}))
            starts = [m for m in ("tsai", "dlt") if f"{m}_refined_rms_px" in info]
            chosen = next((m for m in starts if info.get("chosen_" + m)), "?")
            lines.append(f"{' ' * len(name)}  start: " + ", ".join(
                f"{m} (linear {info[f'{m}_linear_rms_px']:.3f} px, refined {info[f'{m}_refined_rms_px']:.3f} px)"
                for m in starts) + f"; kept {chosen}")
    if cal.kind.startswith("box") and cal.view_poses:
        # The extrinsics of Table 2: where the box is in each camera.
        pose, std = cal.view_poses[0], (cal.view_pose_std[0] if cal.view_pose_std else np.full(6, np.nan))
        lines.append(f"box in {cal.camera_names[0]} camera: t (mm) " + ", ".join(
            _pm(v, s, ".2f") for v, s in zip(np.ravel(pose.tvec), std[3:])) + "; rotation vector (deg) " + ", ".join(
            _pm(np.degrees(v), np.degrees(s), ".3f") for v, s in zip(np.ravel(pose.rvec), std[:3])))
        if cal.is_stereo:
            t_r = cal.rotation @ np.ravel(pose.tvec) + np.ravel(cal.translation_mm)
            r_r = cv2.Rodrigues(cal.rotation @ pose.rotation)[0].ravel()
            lines.append("box in right camera: t (mm) " + ", ".join(f"{v:.2f}" for v in t_r)
                         + "; rotation vector (deg) " + ", ".join(f"{np.degrees(v):.3f}" for v in r_r))
    if cal.is_stereo:
        om = cv2.Rodrigues(cal.rotation)[0].ravel()
        t, ts = np.ravel(cal.translation_mm), np.ravel(cal.translation_std_mm)
        rs = np.ravel(cal.rotation_std_rad)
        lines.append("left->right R (rotation vector, deg): " + ", ".join(
            _pm(np.degrees(a), np.degrees(s), ".4f") for a, s in zip(om, rs)))
        lines.append("left->right T (mm): " + ", ".join(_pm(a, s, ".3f") for a, s in zip(t, ts))
                     + f"  |T| = {np.linalg.norm(t):.3f} mm")
    lines.append(f"reprojection RMS {cal.rms_px:.3f} px (noise estimate {cal.sigma_px:.3f} px per axis)")
    for board, rms in cal.per_board_rms_px().items():
        lines.append(f"  {board}: RMS {rms:.3f} px")
    if cal.reconstruction is not None:
        r = cal.reconstruction
        lines.append(f"3-D reconstruction error over {r.count} corners: mean {r.mean_mm:.3f} mm, "
                     f"std {r.std_mm:.3f} mm, max {r.max_mm:.3f} mm")
        for board, e in r.per_board_mm.items():
            lines.append(f"  {board}: mean {e:.3f} mm")
    if cal.rectification is not None:
        lines.append(f"rectified epipolar error: RMS {cal.rectification.epipolar_rms_px:.3f} px, "
                     f"max {cal.rectification.epipolar_max_px:.3f} px")
    if cal.dropped:
        lines.append(f"{len(cal.dropped)} corners dropped as outliers:")
        lines += [f"  {d}" for d in cal.dropped]
    lines += [f"note: {n}" for n in cal.notes]
    return "\n".join(lines)


def overlay(image: np.ndarray, detected: np.ndarray, residual: np.ndarray, inlier: np.ndarray) -> np.ndarray:
    """BGR image: detected corners (green), reprojections (red), residual x20 (yellow), dropped (magenta)."""
    out = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR) if image.ndim == 2 else image.copy()
    scale = 16  # fixed-point drawing for sub-pixel positions
    for p, r, ok in zip(detected, residual, inlier):
        q = p + r
        pi = tuple(int(round(v * scale)) for v in p)
        qi = tuple(int(round(v * scale)) for v in q)
        vi = tuple(int(round(v * scale)) for v in p + VECTOR_GAIN * r)
        if ok:
            cv2.line(out, pi, vi, (0, 255, 255), 1, cv2.LINE_AA, shift=4)
            cv2.circle(out, pi, 4 * scale, (0, 200, 0), 1, cv2.LINE_AA, shift=4)
            cv2.drawMarker(out, (int(round(q[0])), int(round(q[1]))), (0, 0, 255), cv2.MARKER_CROSS, 6, 1)
        else:
            cv2.circle(out, pi, 6 * scale, (255, 0, 255), 2, cv2.LINE_AA, shift=4)
            cv2.line(out, pi, qi, (255, 0, 255), 1, cv2.LINE_AA, shift=4)
    cv2.putText(out, f"green detected, red reprojected, yellow residual x{VECTOR_GAIN:g}, magenta dropped",
                (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
    return out


def bar_chart(labels: list[str], values: list[float], title: str, unit: str,
              size: tuple[int, int] = (640, 360)) -> np.ndarray:
    """A plain bar chart drawn with OpenCV (no plotting library needed)."""
    w, h = size
    img = np.full((h, w, 3), 255, np.uint8)
    cv2.putText(img, title, (10, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (0, 0, 0), 1, cv2.LINE_AA)
    if not values:
        return img
    top, bottom, left = 40, h - 60, 50
    vmax = max(max(values), 1e-12)
    bw = (w - left - 10) / len(values)
    for i, (lab, v) in enumerate(zip(labels, values)):
        x0 = int(left + i * bw + 0.1 * bw)
        x1 = int(left + (i + 1) * bw - 0.1 * bw)
        y = int(bottom - (bottom - top) * v / vmax)
        cv2.rectangle(img, (x0, y), (max(x1, x0 + 1), bottom), (180, 120, 40), -1)
        if len(values) <= 24:
            cv2.putText(img, lab, (x0, bottom + 16), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.line(img, (left, bottom), (w - 10, bottom), (0, 0, 0), 1)
    cv2.putText(img, f"max {vmax:.3g} {unit}", (left, top - 4), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1,
                cv2.LINE_AA)
    return img


def residual_histogram(cal: Calibration, bins: int = 20) -> np.ndarray:
    """Histogram of per-corner residual lengths (kept corners) as an image."""
    norms = np.concatenate([np.linalg.norm(r[m], axis=1) for per_cam, inl in zip(cal.residuals_px, cal.inliers)
                            for r, m in zip(per_cam, inl)])
    hi = float(norms.max()) if len(norms) else 1.0
    counts, edges = np.histogram(norms, bins=bins, range=(0.0, max(hi, 1e-6)))
    labels = [f"{e:.2f}" if i % 4 == 0 else "" for i, e in enumerate(edges[:-1])]
    return bar_chart(labels, [float(c) for c in counts],
                     f"residual length histogram (px), {len(norms)} corners, RMS {cal.rms_px:.3f} px", "corners")


def _file_stem(view_name: str) -> str:
    """A file-name-safe stem of a view's name (``left/000003.png`` -> ``left_000003``)."""
    stem = view_name.rsplit(".", 1)[0] if "." in Path(view_name).name else view_name
    return "".join(ch if ch.isalnum() or ch in "-_." else "_" for ch in stem)


def _view_images(views: list[View], cal: Calibration, max_pixels: int) -> dict[tuple[int, int], np.ndarray]:
    """The images of the used views that can still be read, keyed by (camera, calibration view)."""
    order = list(cal.view_index) if cal.view_index else list(range(len(cal.corners[0])))
    out = {}
    for v, i in enumerate(order):
        for c in range(len(cal.cameras)):
            try:
                out[(c, v)] = load_grey(views[i].files[c], max_pixels)
            except (EdgecalError, IndexError):
                continue  # a re-solve from a corners file whose images are gone: no overlay for them
    return out


def write_report(cal: Calibration, views: list[View], folder: str | Path, force: bool = False,
                 problems: list[str] | None = None, bounds: Acceptance | None = None,
                 provenance: dict | None = None, max_pixels: int = DEFAULT_MAX_PIXELS) -> list[Path]:
    """Write overlays (one per camera and view, named by the view's file), the histogram, the per-board
    chart and summary.txt. Returns the paths written.
    """
    out = Path(folder)
    multi = len(views) > 1
    order = list(cal.view_index) if cal.view_index else list(range(len(cal.corners[0])))
    images = _view_images(views, cal, max_pixels)
    plan: list[tuple[Path, np.ndarray | str]] = []
    for c, name in enumerate(cal.camera_names):
        for v, cs in enumerate(cal.corners[c]):
            if (c, v) not in images or not len(cs):
                continue
            fname = f"overlay_{name}_{_file_stem(views[order[v]].name)}.png" if multi else f"overlay_{name}.png"
            plan.append((out / fname, overlay(images[(c, v)], cs.image_px, cal.residuals_px[c][v],
                                              cal.inliers[c][v])))
    plan.append((out / "residual_histogram.png", residual_histogram(cal)))
    per_board = cal.per_board_rms_px()
    plan.append((out / "per_board_error.png",
                 bar_chart(list(per_board), list(per_board.values()), "reprojection RMS per camera/board (px)", "px")))
    plan.append((out / "summary.txt", format_summary(cal) + "\n"))
    check_outputs([p for p, _ in plan], force, create_folders=True)
    write_atomic_set({p: content.encode("utf-8") if isinstance(content, str) else png_bytes(content)
                      for p, content in plan})
    return [p for p, _ in plan]
