"""Per-corner covariance (edgecal.detection.corner_covariance): checked against the scatter on renders with
exact truth, and unusable corners named without NaN (the full measurement is bench/corner_noise.py)."""

from __future__ import annotations

import json
from dataclasses import replace

import cv2
import numpy as np
import pytest

import edgecal
from edgecal.detection.candidates import estimate_noise_sigma, smooth_image, smoothing_sigma
from edgecal.detection.corner_covariance import (
    BEND_ERROR_SHARE,
    REASON_BORDER,
    REASON_DEGENERATE,
    REASON_DISAGREE,
    REASON_FLAT,
    _grid_steps_of_boards,
    corner_covariance,
    corner_statistics,
    covariance_noise_sigma,
    covariances_reference,
    grid_steps,
    noise_kernel,
    saddle_noise_term,
    saddle_statistics,
)
from edgecal.detection.params import DetectorParams
from edgecal.detection.subpixel import nearest_spacing, refine_corners, saddle_fit_setup
from edgecal.detection.tracking import track_boards
from edgecal.detection.types import CornerPrediction
from edgecal.synth.camera import camera_from_fov
from edgecal.synth.panels import panels_from_target
from edgecal.synth.photometric import Photometric, apply_photometric, random_photometric
from edgecal.synth.scenes import planar_view
from edgecal.synth.view import render_view
from edgecal.targets import planar_target

TARGET = planar_target(9, 6, 25.0)


def _nees(det, truth: np.ndarray) -> np.ndarray:
    ok = det.usable()
    xy, cov = det.corners[ok], det.covariance[ok]
    d = np.linalg.norm(xy[:, None] - truth[None], axis=2)
    j = d.argmin(axis=1)
    near = d[np.arange(len(j)), j] < 1.5
    e = xy[near] - truth[j[near]]
    return np.einsum("ni,nij,nj->n", e, np.linalg.inv(cov[near]), e)


def _view(photometric: str, k: int):
    """The k-th test render of a condition; "hard" without JPEG (see test_strong_jpeg_is_covered)."""
    if photometric == "light":
        phot = Photometric(blur_sigma=0.7, gradient=(0.6 * (-1) ** k, 0.45), vignetting=0.4,
                           black_level=10, white_level=240, noise_sigma=2.0)
        return planar_view([k, 71], photometric=phot)
    if photometric == "hard":
        phot = replace(random_photometric(np.random.default_rng([k, 72]), "hard"), jpeg_quality=None)
        return planar_view([k, 72], photometric=phot)
    if photometric == "foreshortened":
        return planar_view([k, 73], photometric="normal", tilt_max_deg=78.0)
    return planar_view([k, 72], photometric=photometric)


def _errors(photometric: str, params: DetectorParams | None = None, views: int = 10
            ) -> tuple[np.ndarray, np.ndarray]:
    """Errors (M, 2) and covariances (M, 2, 2) of the usable corners of ``views`` renders."""
    errors, covs = [], []
    for k in range(views):
        view = _view(photometric, k)
        if not view.truth["boards"]:
            continue
        truth = view.corners(0)
        for det in edgecal.detect(view.image, TARGET, params):
            assert det.covariance is not None and det.covariance.shape == (len(det.corners), 2, 2)
            ok = det.usable()
            xy, cov = det.corners[ok], det.covariance[ok]
            d = np.linalg.norm(xy[:, None] - truth[None], axis=2)
            j = d.argmin(axis=1)
            near = d[np.arange(len(j)), j] < 1.5
            errors.append(xy[near] - truth[j[near]])
            covs.append(cov[near])
    return np.concatenate(errors), np.concatenate(covs)


@pytest.mark.parametrize("photometric", ["clean", "normal", "hard", "light", "foreshortened"])
@pytest.mark.parametrize("refiner", ["saddle", "cornersubpix"])
def test_normalised_error_matches_the_scatter(photometric: str, refiner: str) -> None:
    """Mean e^T Sigma^-1 e near 2 (a consistent 2-D covariance) over a few renders of each condition, for
    the saddle fit (the detector's default) and cornerSubPix (tracking's refinement).

    Ten views leave the mean a wider spread than bench/corner_noise.py's 1.5-3 over 40-80 (a view's
    corners share its light and blur). Measured on the saddle fit's corners: its noise term alone gives
    5.6-22 (2.3 on hard, where noise dominates), cornerSubPix's covariance (before the saddle model) 0.9
    under uneven light and 1.2 foreshortened, the model without its light term 5.6 under uneven light."""
    # 20 views of the strongly foreshortened condition: its steepest corners give a heavy tail
    views = 20 if photometric == "foreshortened" else 10
    e, cov = _errors(photometric, DetectorParams(subpixel_refiner=refiner), views)
    nees = np.einsum("ni,nij,nj->n", e, np.linalg.inv(cov), e)
    assert len(nees) > 200
    # A covariance 2x too large in sigma would give 0.5, 2x too small 8.
    assert 1.3 < nees.mean() < 4.0, nees.mean()


@pytest.mark.parametrize("photometric", ["normal", "foreshortened"])
def test_covariance_shape_follows_the_errors(photometric: str) -> None:
    """The saddle fit's covariances are not more elongated than its errors: the mean squared error along
    each covariance's minor and major axis over the variance there are both near 1 (a model error in the
    shape of H^-1 or A^-1 gave 0.44-0.64 along the major axis and covariances 1.7-2.2x elongated)."""
    e, cov = _errors(photometric, views=20)
    w, v = np.linalg.eigh(cov)
    along = np.einsum("nji,nj->ni", v, e)
    minor, major = np.mean(along ** 2 / w, axis=0)
    assert 0.75 < minor / major < 1.33 and max(minor, major) < 2.5, (minor, major)


@pytest.mark.xfail(strict=True, reason="strong JPEG (quality < 70) on a blurred image: the compression's own error "
                                       "moves the corners, which no noise estimate sees (known gap, README)")
def test_strong_jpeg_is_covered() -> None:
    """A hard render (noise 3.1, blur 2.1 px) through JPEG quality 62: the half-resolution noise estimate sees
    1.0 grey levels, the saddle fit's corners err by 0.085 px against a sigma of 0.037 (mean normalised error
    10.8). (The default refiner's X-junction fit averages the compression's error over a larger disc.)"""
    view = planar_view([7, 72], photometric="hard")
    assert view.truth["render"]["photometric"]["jpeg_quality"] == 62
    truth = view.corners(0)
    det = edgecal.detect(view.image, TARGET, DetectorParams(subpixel_refiner="saddle"))[0]
    nees = _nees(det, truth)
    assert nees.mean() < 4.0, nees.mean()


def test_noise_term_alone_matches_noise_only_repeats() -> None:
    """The noise term (no model error: a noisy image, where it dominates) against repeats of one render
    with fresh noise, relative to the noise-free refinement: the physics without any fitted constant."""
    view = planar_view(5, photometric=Photometric(blur_sigma=1.0, black_level=40, white_level=160))
    clean = view.image.astype(np.float64)
    noise = 5.0
    sigma = smoothing_sigma(noise)
    det = edgecal.detect(view.image, TARGET)[0]
    start = refine_corners(smooth_image(view.image, sigma), det.corners, np.full(len(det.corners), 30.0))
    rng = np.random.default_rng(1)
    noisy = [np.clip(np.rint(clean + rng.normal(0, noise, clean.shape)), 0, 255).astype(np.uint8) for _ in range(12)]
    cc = corner_covariance(noisy[0], smooth_image(view.image, sigma), sigma, start, np.full(len(start), 30.0),
                           refiner="cornersubpix")
    cov, reasons = cc.covariance, cc.unusable
    assert not any(reasons)
    errs = np.array([refine_corners(smooth_image(im, sigma), start, np.full(len(start), 30.0)) - start for im in noisy])
    nees = np.einsum("kni,nij,knj->kn", errs, np.linalg.inv(cov), errs)
    assert 1.5 < nees.mean() < 2.8, nees.mean()


def test_saddle_noise_term_matches_noise_only_repeats() -> None:
    """The saddle fit's noise term against repeats of one render with fresh noise, relative to the
    noise-free detection: the noise carried through the fit without any fitted constant. (The saddle fit's
    own corners: the default refiner's X-junction fit moves them, its noise is 0.42 of this term, mean 0.85.)"""
    view = planar_view(5, photometric=Photometric(blur_sigma=1.0, black_level=40, white_level=160))
    clean = view.image.astype(np.float64)
    saddle = DetectorParams(subpixel_refiner="saddle")
    ref = edgecal.detect(view.image, TARGET, saddle)[0]
    index = {tuple(i): j for j, i in enumerate(ref.ids.tolist())}
    rng = np.random.default_rng(1)
    errors, covs = [], []
    for _ in range(12):
        noisy = np.clip(np.rint(clean + rng.normal(0, 5.0, clean.shape)), 0, 255).astype(np.uint8)
        sigma = smoothing_sigma(estimate_noise_sigma(noisy))
        for det in edgecal.detect(noisy, TARGET, saddle):
            spacing = nearest_spacing(det.corners)
            fit, half, blur_half, blur = saddle_fit_setup(spacing)
            sd = saddle_statistics(smooth_image(noisy, sigma), det.corners, blur, noise_kernel(sigma), fit, half,
                                   blur_half, spacing, grid_steps(det.ids, det.corners))
            j = np.array([index[tuple(i)] for i in det.ids.tolist()])
            errors.append(det.corners - ref.corners[j])
            covs.append(saddle_noise_term(sd, covariance_noise_sigma(noisy) ** 2))
    e, cov = np.concatenate(errors), np.concatenate(covs)
    assert len(e) > 500
    nees = np.einsum("ni,nij,nj->n", e, np.linalg.inv(cov), e)
    assert 1.5 < nees.mean() < 2.8, nees.mean()


def test_grid_steps() -> None:
    """Central differences inside the grid, one-sided at its ends, NaN for a lone corner."""
    ids = np.array([[0, 0], [1, 0], [2, 0], [0, 1], [5, 5]])
    xy = np.array([[0.0, 0.0], [10.0, 1.0], [22.0, 2.0], [0.0, 9.0], [50.0, 50.0]])
    steps = grid_steps(ids, xy)
    assert np.allclose(steps[1, 0], [11.0, 1.0]) and np.allclose(steps[0, 0], [10.0, 1.0])
    assert np.allclose(steps[2, 0], [12.0, 1.0]) and np.allclose(steps[0, 1], [0.0, 9.0])
    assert np.isnan(steps[1, 1]).all() and np.isnan(steps[4]).all()
    # add_board_covariances' kernel over several boards in one pass: the same steps per board
    ids2 = np.array([[3, 4], [4, 4], [3, 5], [4, 5], [5, 5]])
    xy2 = np.array([[5.0, 5.0], [15.0, 6.0], [4.0, 14.0], [14.5, 15.0], [25.0, 16.0]])
    both = _grid_steps_of_boards(np.concatenate([ids, ids2]), np.concatenate([xy, xy2]), np.array([0, 5, 10]))
    np.testing.assert_array_equal(both, np.concatenate([steps, grid_steps(ids2, xy2)]))


@pytest.mark.parametrize("refiner", ["xjunction", "saddle", "cornersubpix"])
def test_covariance_kernel_matches_the_numpy_reference(refiner: str) -> None:
    """corner_covariance's one-pass kernel gives covariances_reference's covariances, shares, light gradients
    and reasons, to rounding: on two boards (light averaged per board) of a render under uneven light, with
    some corners not placed by the X-junction fit, a lens-bend share, the fit's own noise term on most
    corners (NaN on some: the saddle fit's scaled) and corners at the border and off the board (unusable
    for different reasons)."""
    view = _view("light", 1)
    det = edgecal.detect(view.image, TARGET)[0]
    sigma = smoothing_sigma(2.0)
    smooth = smooth_image(view.image, sigma)
    h, w = view.image.shape
    pts = np.concatenate([det.corners, [[3.0, 3.0], [w - 2.0, h / 2], [w / 2, 5.0], [10.0, h / 2]]])
    n = len(pts)
    spacing = np.concatenate([nearest_spacing(det.corners), np.full(4, 20.0)])
    boards = (np.arange(n) >= n // 2).astype(np.int64)
    fitted = np.arange(n) % 7 != 3
    bend = 0.01 * (np.arange(n) % 5)
    steps = np.concatenate([grid_steps(det.ids, det.corners), np.full((4, 2, 2), np.nan)])
    fit_noise = np.concatenate([det.xjunction_noise, np.full((4, 2, 2), np.nan)])
    fit_noise[::5] = np.nan
    cc = corner_covariance(view.image, smooth, sigma, pts, spacing, 2.0, refiner=refiner, steps=steps,
                           boards=boards, xjunction_fitted=fitted, bend_px=bend, xjunction_noise=fit_noise)
    st, sd, half = corner_statistics(smooth, sigma, np.ascontiguousarray(pts), spacing, refiner, steps)
    ref = covariances_reference(st, sd, half, spacing, 4.0, refiner, boards, fitted, bend, fit_noise)
    assert cc.unusable == ref.unusable and len(set(ref.unusable)) >= 2
    np.testing.assert_allclose(cc.covariance, ref.covariance, rtol=1e-12, atol=1e-18)
    np.testing.assert_allclose(cc.shared_px2, ref.shared_px2, rtol=1e-12, atol=1e-18)
    np.testing.assert_allclose(cc.alternating_px2, ref.alternating_px2, rtol=1e-12, atol=1e-18)
    np.testing.assert_allclose(cc.light_gradient, ref.light_gradient, rtol=1e-12, atol=1e-18)
    if refiner == "xjunction":  # the lens-bend correction's error is all in the board's shared part
        placed = fitted & (np.array(cc.unusable) == "") & (bend > 0)
        assert placed.sum() > 10
        assert np.all(cc.shared_px2[placed] >= (BEND_ERROR_SHARE * bend[placed]) ** 2)


def test_tracked_corners_have_covariances() -> None:
    view = planar_view(3, photometric="normal")
    truth = view.corners(0)
    dets = track_boards(view.image, [CornerPrediction(TARGET.boards[0], view.ids(0), truth + 0.2)])
    assert len(dets) == 1
    nees = _nees(dets[0], truth)
    assert len(nees) == len(truth) and np.isfinite(nees).all()


def test_unusable_corners_are_named_and_json_has_no_nan() -> None:
    """Flat, saturated, edge-only and border windows are unusable with their reason, never NaN in JSON."""
    img = np.full((120, 160), 128, np.uint8)
    img[:, 80:] = 255                      # a straight edge: a line, not a corner
    img[60:, :40] = 255                    # a saturated flat block
    sigma = smoothing_sigma(0.0)
    smooth = smooth_image(img, sigma)
    pts = np.array([[80.0, 30.0], [20.0, 90.0], [2.0, 2.0], [130.0, 60.0]])
    cc = corner_covariance(img, smooth, sigma, pts, np.full(4, 20.0), refiner="saddle")
    cov, shared, reasons, light = cc.covariance, cc.shared_px2, cc.unusable, cc.light_gradient
    assert reasons == [REASON_DEGENERATE, REASON_FLAT, REASON_BORDER, REASON_FLAT]
    assert np.isnan(cov).all() and np.isnan(shared).all() and not light.any()
    view = planar_view(4, photometric="normal")
    det = edgecal.detect(view.image, TARGET)[0]
    det.covariance[3] = np.nan
    det.unusable[3] = REASON_DEGENERATE
    text = json.dumps(det.as_json(), allow_nan=False)
    out = json.loads(text)
    assert out["covariance_px2"][3] is None and len(out["covariance_px2"]) == len(det.corners)
    assert out["unusable"] == [{"id": [int(v) for v in det.ids[3]], "reason": REASON_DEGENERATE}]
    assert not det.usable()[3] and det.usable().sum() == len(det.corners) - 1


def test_corner_the_saddle_fit_would_move_far_is_unusable() -> None:
    """A corner 1.4 px off its X-junction (where the detector keeps cornerSubPix's position because the
    saddle fit would move it further than 1 px) is unusable with the reason, not given a covariance (on
    real photos such rim corners otherwise stayed in the calibration with a huge sigma)."""
    view = planar_view(4, photometric="normal")
    det = edgecal.detect(view.image, TARGET)[0]
    pts = det.corners.copy()
    pts[10] += [1.0, -1.0]
    sigma = smoothing_sigma(estimate_noise_sigma(view.image))
    steps = grid_steps(det.ids, det.corners)
    cc = corner_covariance(view.image, smooth_image(view.image, sigma), sigma, pts, refiner="saddle", steps=steps)
    cov, reasons = cc.covariance, cc.unusable
    assert reasons[10] == REASON_DISAGREE and np.isnan(cov[10]).all()
    assert reasons.count("") == len(pts) - 1


def test_noise_estimate_sees_compressed_noise() -> None:
    """JPEG removes pixel-to-pixel noise but not the noise that moves corners: the half-resolution estimate
    keeps the covariance from collapsing on a compressed image."""
    rng = np.random.default_rng(0)
    radiance = np.full((200, 200), 0.5, np.float32)
    noisy = apply_photometric(radiance, Photometric(noise_sigma=6.0), rng)
    jpeg = apply_photometric(radiance, Photometric(noise_sigma=6.0, jpeg_quality=60), rng)
    assert covariance_noise_sigma(noisy) == pytest.approx(6.0, rel=0.2)
    assert estimate_noise_sigma(jpeg) < 1.0          # the detector's pixel-level estimate is fooled
    assert covariance_noise_sigma(jpeg) > 2.5


def test_light_gradient_is_read_off_the_board() -> None:
    """Each detection reports the gradient of log light over its board (what the pose's common offset
    follows): under a 50 % / -30 % light ramp, over four views, it matches the render's within 25 % (views
    read 0.6-1.05 of it: steep ones lower); on clean renders it is a tenth of that at most."""
    phot = Photometric(blur_sigma=0.7, gradient=(0.5, -0.3), noise_sigma=1.0, white_level=230.0)
    read, expected, flat = [], [], []
    for k in range(4):
        view = planar_view([k, 74], photometric=phot)
        det = edgecal.detect(view.image, TARGET)[0]
        h, w = view.image.shape
        ok = det.usable()
        xn = (det.corners[ok, 0] - (w - 1) / 2.0) / (w / 2.0)
        yn = (det.corners[ok, 1] - (h - 1) / 2.0) / (h / 2.0)
        light = 1.0 + 0.5 * xn - 0.3 * yn
        expected.append(np.stack([0.5 / (w / 2.0) / light, -0.3 / (h / 2.0) / light], axis=1).mean(axis=0))
        assert det.light_gradient is not None
        read.append(det.light_gradient[ok].mean(axis=0))
        clean = edgecal.detect(planar_view([k, 74], photometric="clean").image, TARGET)[0]
        assert clean.light_gradient is not None
        flat.append(np.linalg.norm(clean.light_gradient.mean(axis=0)))
    assert np.mean(read, axis=0) == pytest.approx(np.mean(expected, axis=0), rel=0.25)
    assert max(flat) < 0.1 * np.linalg.norm(np.mean(expected, axis=0))


def test_the_x_junction_fits_light_shift_alternates_with_the_corners_polarity() -> None:
    """Under a strong light gradient (the other-rig robot scene's light) the X-junction fit's corners of a
    board move by one vector times +1/-1 in their checkerboard pattern; Detection.alternating_px2 says how
    much (per axis, within 2x of the RMS of that vector over six views: 0.74 here, 1.16 on the robot scene it
    was fitted on) and is part of each corner's covariance. Without a light gradient it is a small part of
    the covariance."""
    target = planar_target(9, 6, 30.0)
    board = target.boards[0]
    light = Photometric(blur_sigma=0.7, noise_sigma=2.0, gradient=(0.6, 0.35), vignetting=0.3, black_level=8.0,
                        white_level=235.0)
    for phot, strong in ((light, True), (replace(light, gradient=(0.0, 0.0), vignetting=0.0), False)):
        shifts, modelled, variances = [], [], []
        for k, (tx, ty, tz) in enumerate([(-20, 15, 0.1), (15, -25, 0.4), (25, 20, -0.3), (-10, -30, 0.2),
                                          (5, 35, 0.5), (-30, 5, -0.2)]):
            R = cv2.Rodrigues(np.radians([tx, ty, 0.0]) + np.array([0.0, 0.0, tz]))[0]
            t = -R @ board.centre_mm + np.array([60.0 * (k % 3 - 1), 30.0 * (k % 2), 650.0])
            view = render_view(camera_from_fov((640, 480), 60.0), panels_from_target(target), R, t,
                               photometric=phot, rng=k)
            (det,) = edgecal.detect(view.image, target)
            assert det.alternating_px2 is not None
            truth = {tuple(i): c for i, c in zip(view.ids(), view.corners())}
            error = np.array([c - truth[tuple(i)] for i, c in zip(det.ids.tolist(), det.corners)])
            parity = 1.0 - 2.0 * (det.ids.sum(axis=1) % 2)
            shifts.append((parity[:, None] * error).mean(axis=0))
            modelled.append(np.nanmean(det.alternating_px2))
            variances.append(np.nanmean(0.5 * (det.covariance[:, 0, 0] + det.covariance[:, 1, 1])))
        ratio = float(np.sqrt(np.mean(np.square(shifts)) / np.mean(modelled)))
        if strong:
            assert 0.5 < ratio < 2.0, ratio
        else:
            assert np.mean(modelled) < 0.2 * np.mean(variances), (np.mean(modelled), np.mean(variances))
