"""A calibration report a person can read: one self-contained index.html (figures embedded, figures.py),
the same figures as PNGs, an overlay per camera and view, and summary.txt.

The page leads with the verdict and the acceptance bounds, then the parameters with their σ, then the
figures that show *why* a calibration is good or not, then every view (used or skipped, and why).
"""

from __future__ import annotations

import base64
import html
import json
from pathlib import Path

import cv2
import numpy as np

from edgecal.calibration import figures
from edgecal.calibration.results import ViewResult, view_results
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
        pose = cal.view_poses[0]
        pose_std = cal.view_pose_std[0] if cal.view_pose_std else np.full(6, np.nan)
        lines.append(f"box in {cal.camera_names[0]} camera: t (mm) " + ", ".join(
            _pm(v, s, ".2f") for v, s in zip(np.ravel(pose.tvec), pose_std[3:]))
            + "; rotation vector (deg) " + ", ".join(
            _pm(np.degrees(v), np.degrees(s), ".3f") for v, s in zip(np.ravel(pose.rvec), pose_std[:3])))
        if cal.is_stereo:
            assert cal.rotation is not None and cal.translation_mm is not None  # set for every stereo calibration
            t_r = cal.rotation @ np.ravel(pose.tvec) + np.ravel(cal.translation_mm)
            r_r = cv2.Rodrigues(cal.rotation @ pose.rotation)[0].ravel()
            lines.append("box in right camera: t (mm) " + ", ".join(f"{v:.2f}" for v in t_r)
                         + "; rotation vector (deg) " + ", ".join(f"{np.degrees(v):.3f}" for v in r_r))
    if cal.is_stereo:
        assert cal.rotation is not None and cal.translation_mm is not None  # set for every stereo calibration
        assert cal.rotation_std_rad is not None and cal.translation_std_mm is not None
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


def _file_stem(view_name: str) -> str:
    """A file-name-safe stem of a view's name (``left/000003.png`` -> ``left_000003``)."""
    stem = view_name.rsplit(".", 1)[0] if "." in Path(view_name).name else view_name
    return "".join(ch if ch.isalnum() or ch in "-_." else "_" for ch in stem)


def _load(path: str, max_pixels: int) -> np.ndarray | None:
    """A view's image, or None when it cannot be read (a re-solve from a corners file whose images are gone)."""
    try:
        return load_grey(path, max_pixels)
    except EdgecalError:
        return None


def _esc(value: object) -> str:
    return html.escape(str(value), quote=True)


def _img(png: bytes, alt: str) -> str:
    return f'<img alt="{_esc(alt)}" src="data:image/png;base64,{base64.b64encode(png).decode("ascii")}">'


def _fmt(value: float, std: float, digits: int) -> tuple[str, str]:
    v = f"{value:.{digits}f}"
    return v, ("fixed" if not np.isfinite(std) else f"± {std:.{digits}f}")


_CSS = """
body { font-family: system-ui, sans-serif; margin: 2em auto; max-width: 1100px; color: #222; padding: 0 1em; }
h1 { font-size: 1.5em; } h2 { font-size: 1.15em; margin-top: 2em; border-bottom: 1px solid #ccc; }
table { border-collapse: collapse; margin: 0.5em 0; font-size: 0.9em; }
td, th { border: 1px solid #ccc; padding: 0.2em 0.6em; text-align: left; }
td.num { text-align: right; font-variant-numeric: tabular-nums; }
.verdict { font-size: 1.3em; padding: 0.6em 1em; border-radius: 6px; color: white; }
.accepted { background: #2e7d32; } .refused { background: #c62828; }
.bad { color: #c62828; font-weight: bold; } .skipped { color: #777; }
.row { display: flex; flex-wrap: wrap; gap: 1em; } .row > div { flex: 1 1 480px; }
img { max-width: 100%; height: auto; } .note { color: #555; font-size: 0.9em; }
"""


def _bounds_rows(cal: Calibration, bounds: Acceptance) -> list[tuple[str, str, str, bool]]:
    """(what, value, limit, within) for every acceptance bound that applies to the calibration."""
    rows = [("reprojection RMS", f"{cal.rms_px:.3f} px", f"{bounds.max_rms_px:g} px", cal.rms_px <= bounds.max_rms_px)]
    for name, cam, std in zip(cal.camera_names, cal.cameras, cal.camera_std):
        for key, value in (("fx", cam.fx), ("fy", cam.fy)):
            pct = 100.0 * std.get(key, np.nan) / value
            rows.append((f"{name} {key} σ", f"{pct:.3f} %", f"{bounds.max_focal_std_percent:g} %",
                         bool(pct <= bounds.max_focal_std_percent)))
        for key in ("cx", "cy"):
            sd = std.get(key, np.nan)
            if np.isfinite(sd):
                rows.append((f"{name} {key} σ", f"{sd:.2f} px", f"{bounds.max_principal_point_std_px:g} px",
                             bool(sd <= bounds.max_principal_point_std_px)))
    if cal.is_stereo:
        assert cal.translation_std_mm is not None  # set for every stereo calibration
        t = np.ravel(cal.translation_std_mm)
        rows.append(("baseline T σ (largest)", f"{t.max():.3f} mm", f"{bounds.max_baseline_std_mm:g} mm",
                     bool(np.all(t <= bounds.max_baseline_std_mm))))
        if cal.reconstruction is not None:
            m = cal.reconstruction.mean_mm
            rows.append(("3-D reconstruction error, mean", f"{m:.3f} mm", f"{bounds.max_reconstruction_mean_mm:g} mm",
                         m <= bounds.max_reconstruction_mean_mm))
        if cal.rectification is not None:
            e = cal.rectification.epipolar_rms_px
            rows.append(("epipolar RMS", f"{e:.3f} px", f"{bounds.max_epipolar_rms_px:g} px",
                         e <= bounds.max_epipolar_rms_px))
    total = sum(len(m) for per_cam in cal.inliers for m in per_cam)
    dropped = total - sum(int(m.sum()) for per_cam in cal.inliers for m in per_cam)
    share = dropped / total if total else 0.0
    rows.append(("corners dropped as outliers", f"{dropped} of {total} ({100 * share:.1f} %)",
                 f"{100 * bounds.max_dropped_fraction:g} %", share <= bounds.max_dropped_fraction))
    return rows


def _parameter_table(cal: Calibration) -> str:
    out = ['<table><tr><th>camera</th><th>parameter</th><th>value</th><th>1σ</th></tr>']
    for name, cam, std in zip(cal.camera_names, cal.cameras, cal.camera_std):
        items = [(n, v, 2, "px") for n, v in zip(("fx", "fy", "cx", "cy"), (cam.fx, cam.fy, cam.cx, cam.cy))]
        items += [(n, float(v), 6, "") for n, v in zip(cam.param_names, cam.params)]
        for n, v, digits, unit in items:
            value, sd = _fmt(v, std.get(n, np.nan), digits)
            out.append(f"<tr><td>{_esc(name)} ({_esc(cam.lens)})</td><td>{n}</td><td class=num>{value} {unit}</td>"
                       f"<td class=num>{sd}</td></tr>")
    if cal.is_stereo:
        assert cal.rotation is not None and cal.translation_mm is not None  # set for every stereo calibration
        assert cal.rotation_std_rad is not None and cal.translation_std_mm is not None
        rv = cv2.Rodrigues(np.asarray(cal.rotation, dtype=np.float64))[0].ravel()
        for axis, a, sd in zip("xyz", rv, np.ravel(cal.rotation_std_rad)):
            value, s = _fmt(np.degrees(a), np.degrees(sd), 4)
            out.append(f"<tr><td>left→right</td><td>R rotation vector {axis}</td><td class=num>{value} °</td>"
                       f"<td class=num>{s}</td></tr>")
        for axis, a, sd in zip("xyz", np.ravel(cal.translation_mm), np.ravel(cal.translation_std_mm)):
            value, s = _fmt(a, sd, 3)
            out.append(f"<tr><td>left→right</td><td>T {axis}</td><td class=num>{value} mm</td>"
                       f"<td class=num>{s}</td></tr>")
        out.append(f"<tr><td>left→right</td><td>|T| (baseline)</td>"
                   f"<td class=num>{np.linalg.norm(cal.translation_mm):.3f} mm</td><td></td></tr>")
    out.append("</table>")
    return "\n".join(out)


def _views_table(results: list[ViewResult], camera_names: tuple[str, ...]) -> str:
    head = "".join(f"<th>RMS {c} (px)</th><th>corners {c}</th>" for c in camera_names)
    out = [f"<table><tr><th>view</th><th>files</th><th>used</th>{head}<th>dropped corners / why skipped</th></tr>"]
    for r in results:
        cells = "".join(f"<td class=num>{'' if not np.isfinite(v) else f'{v:.3f}'}</td><td class=num>{n}</td>"
                        for v, n in zip(r.rms_px, r.corners))
        dropped = "; ".join(f"{c}: {', '.join(d)}" for c, d in zip(camera_names, r.dropped) if d)
        why = r.why_not if not r.used else dropped
        cls = "" if r.used else " class=skipped"
        out.append(f"<tr{cls}><td>{_esc(r.name)}</td><td>{'<br>'.join(_esc(f) for f in r.files)}</td>"
                   f"<td>{'yes' if r.used else 'no'}</td>{cells}<td>{_esc(why)}</td></tr>")
    out.append("</table>")
    return "\n".join(out)


def _provenance_table(provenance: dict) -> str:
    rows = []
    for key in ("target", "target_source", "square_mm", "edgecal_version", "created", "corners_file"):
        if key in provenance:
            rows.append(f"<tr><th>{_esc(key)}</th><td>{_esc(provenance[key])}</td></tr>")
    settings = provenance.get("settings", {})
    if settings:
        text = json.dumps(settings, indent=1)
        rows.append(f"<tr><th>settings</th><td><pre>{_esc(text)}</pre></td></tr>")
    return "<table>" + "\n".join(rows) + "</table>"


def report_html(cal: Calibration, results: list[ViewResult], pngs: dict[str, bytes], problems: list[str],
                bounds: Acceptance, provenance: dict | None, overlays: list[str]) -> str:
    """The self-contained index.html: every figure embedded, tables of bounds, parameters and views."""
    verdict = "refused" if problems else "accepted"
    title = f"edgecal calibration: {cal.kind}, {cal.image_size[0]}x{cal.image_size[1]} px"
    parts = [f"<!DOCTYPE html><html lang=en><head><meta charset=utf-8><title>{_esc(title)}</title>"
             f"<style>{_CSS}</style></head><body>", f"<h1>{_esc(title)}</h1>"]
    used = sum(r.used for r in results)
    parts.append(f'<div class="verdict {verdict}">{verdict.upper()}: reprojection RMS {cal.rms_px:.3f} px, '
                 f"{used} of {len(results)} views used</div>")
    if problems:
        parts.append("<ul>" + "".join(f"<li class=bad>{_esc(p)}</li>" for p in problems) + "</ul>")
    parts.append("<h2>Acceptance bounds</h2><table><tr><th>what</th><th>value</th><th>limit</th><th></th></tr>")
    for what, value, limit, ok in _bounds_rows(cal, bounds):
        mark = "ok" if ok else "<span class=bad>exceeded</span>"
        parts.append(f"<tr><td>{_esc(what)}</td><td class=num>{_esc(value)}</td><td class=num>{_esc(limit)}</td>"
                     f"<td>{mark}</td></tr>")
    parts.append("</table>")
    parts.append("<h2>Parameters (1σ from the Jacobian)</h2>" + _parameter_table(cal))
    if cal.reconstruction is not None or cal.rectification is not None:
        parts.append("<p>")
        if cal.reconstruction is not None:
            r = cal.reconstruction
            parts.append(f"3-D reconstruction error over {r.count} corners: mean {r.mean_mm:.3f} mm, "
                         f"std {r.std_mm:.3f} mm, max {r.max_mm:.3f} mm. ")
        if cal.rectification is not None:
            parts.append(f"Rectified epipolar error: RMS {cal.rectification.epipolar_rms_px:.3f} px, "
                         f"max {cal.rectification.epipolar_max_px:.3f} px.")
        parts.append("</p>")

    def section(heading: str, keys: list[str], note: str = "") -> None:
        present = [k for k in keys if k in pngs]
        if not present:
            return
        parts.append(f"<h2>{_esc(heading)}</h2>" + (f"<p class=note>{_esc(note)}</p>" if note else ""))
        parts.append('<div class="row">' + "".join(f"<div>{_img(pngs[k], k)}</div>" for k in present) + "</div>")

    names = cal.camera_names
    section("Reprojection RMS per view", ["view_rms.png"],
            "One bar per view, named by its file; skipped views and dropped corners are marked.")
    section("Residual vectors over the image", [f"residuals_{n}.png" for n in names],
            "Arrows that line up or swirl mean a model error; random directions are detector noise.")
    section("Coverage", [f"coverage_{n}.png" for n in names],
            "Where the corners were. Distortion is extrapolated in empty cells: add views there.")
    section("Residual against radius", [f"residual_radius_{n}.png" for n in names],
            "A trend of the radial part with the radius means the lens model is too weak (try --distortion).")
    section("Lens distortion", [f"distortion_{n}.png" for n in names],
            "How far the lens moves each pixel from the pinhole position.")
    section("Rectified pair with epipolar lines", ["rectified_pair.png"],
            "Each corner (red) and its match in the other image must lie on the same horizontal line.")
    section("Residual histogram and per-board RMS", ["residual_histogram.png", "per_board_error.png"])
    parts.append("<h2>Views used and skipped</h2>" + _views_table(results, names))
    if cal.dropped:
        parts.append("<h2>Corners dropped as outliers</h2><ul>"
                     + "".join(f"<li>{_esc(d)}</li>" for d in cal.dropped) + "</ul>")
    if cal.notes:
        parts.append("<h2>Notes</h2><ul>" + "".join(f"<li>{_esc(n)}</li>" for n in cal.notes) + "</ul>")
    if overlays:
        parts.append("<h2>Overlays</h2><p class=note>Detected (green), reprojected (red), residual magnified "
                     "(yellow), dropped (magenta), one PNG per camera and view beside this file:</p><p>"
                     + " ".join(f'<a href="{_esc(o)}">{_esc(o)}</a>' for o in overlays) + "</p>")
    if provenance:
        parts.append("<h2>Provenance</h2>" + _provenance_table(provenance))
    parts.append("</body></html>")
    return "\n".join(parts)


def _figures(cal: Calibration, views: list[View], results: list[ViewResult], max_pixels: int) -> dict[str, bytes]:
    """Every report figure as PNG bytes, by file name."""
    names = cal.camera_names
    figs = {"view_rms.png": figures.view_rms_figure(results, names)}
    for c, n in enumerate(names):
        figs[f"residuals_{n}.png"] = figures.residual_vectors_figure(cal, c)
        figs[f"coverage_{n}.png"] = figures.coverage_figure(cal, c)
        figs[f"residual_radius_{n}.png"] = figures.residual_radius_figure(cal, c)
        figs[f"distortion_{n}.png"] = figures.distortion_figure(cal.cameras[c], n)
    if cal.is_stereo and cal.rectification is not None:
        order = _view_order(cal)
        # the view with the most corners in both images shows the epipolar lines best
        v = max(range(len(order)), key=lambda k: min(len(cal.corners[0][k]), len(cal.corners[1][k])))
        left, right = (_load(views[order[v]].files[c], max_pixels) for c in (0, 1))
        if left is not None and right is not None:
            figs["rectified_pair.png"] = figures.rectified_pair_figure(left, right, cal, v)
    figs["residual_histogram.png"] = figures.residual_histogram_figure(cal)
    figs["per_board_error.png"] = figures.per_board_figure(cal)
    return figs


def _view_order(cal: Calibration) -> list[int]:
    return list(cal.view_index) if cal.view_index else list(range(len(cal.corners[0])))


def write_report(cal: Calibration, views: list[View], folder: str | Path, force: bool = False,
                 problems: list[str] | None = None, bounds: Acceptance | None = None,
                 provenance: dict | None = None, max_pixels: int = DEFAULT_MAX_PIXELS) -> list[Path]:
    """Write the report into ``folder``: index.html (self-contained), its figures as PNGs, an overlay per
    camera and view (named by the view's file) and summary.txt, as one set. Returns the paths written."""
    out = Path(folder)
    bounds = bounds if bounds is not None else Acceptance()
    results = view_results(cal, views)
    multi = len(views) > 1
    order = _view_order(cal)
    files: dict[Path, bytes] = {}
    overlays = []
    for v, i in enumerate(order):
        for c, name in enumerate(cal.camera_names):
            cs = cal.corners[c][v]
            image = _load(views[i].files[c], max_pixels) if len(cs) else None
            if image is None:
                continue
            fname = f"overlay_{name}_{_file_stem(views[i].name)}.png" if multi else f"overlay_{name}.png"
            # encoded at once: a set of many large images is not kept in memory as pixels
            files[out / fname] = png_bytes(overlay(image, cs.image_px, cal.residuals_px[c][v], cal.inliers[c][v]))
            overlays.append(fname)
    figs = _figures(cal, views, results, max_pixels)
    files.update({out / k: v for k, v in figs.items()})
    files[out / "summary.txt"] = (format_summary(cal) + "\n").encode("utf-8")
    files[out / "index.html"] = report_html(cal, results, figs, problems or [], bounds, provenance,
                                            overlays).encode("utf-8")
    check_outputs(list(files), force, create_folders=True)
    write_atomic_set(files)
    return list(files)
