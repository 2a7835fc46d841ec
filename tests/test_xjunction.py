"""The X-junction model fit (subpixel.xjunction_fit): the default refiner's last step."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

import edgecal
from edgecal.detection.candidates import smooth_image
from edgecal.detection.params import DetectorParams
from edgecal.detection.subpixel import (
    RIM_EDGE_MARGIN_PX,
    grid_line_angles,
    nearest_spacing,
    on_board_rim,
    saddle_refine,
    xjunction_fit,
    xjunction_radius,
)
from edgecal.scoring import FoundGrid, corner_rms, score_image
from edgecal.synth.scenes import planar_view
from edgecal.synth.truth import ground_truth_from_mapping
from edgecal.targets import planar_target
from tests.test_board_rim import _cut_board_view


def _junction(centre: tuple[float, float], angles_deg: tuple[float, float], blur: float, size: int = 64,
              supersample: int = 16) -> np.ndarray:
    """A uint8 image of one X-junction: two straight lines through ``centre`` (px, OpenCV convention), the
    quadrants alternately 40 and 200, every pixel the mean over supersample^2 points, then a Gaussian blur
    and rounding to grey levels."""
    n = size * supersample
    pos = (np.arange(n) + 0.5) / supersample - 0.5  # sample positions in pixel coordinates
    x, y = np.meshgrid(pos - centre[0], pos - centre[1])
    a1, a2 = np.radians(angles_deg)
    d1 = -x * np.sin(a1) + y * np.cos(a1)
    d2 = -x * np.sin(a2) + y * np.cos(a2)
    fine = np.where(d1 * d2 >= 0, 200.0, 40.0)
    img = fine.reshape(size, supersample, size, supersample).mean(axis=(1, 3))
    return np.clip(np.rint(cv2.GaussianBlur(img, (0, 0), blur)), 0, 255).astype(np.uint8)


@pytest.mark.parametrize("angle_deg", [3.0, 6.0])
def test_an_edge_near_a_pixel_axis_is_not_locked_to_the_pixel_grid(angle_deg: float) -> None:
    """Noise-free junctions with edges a few degrees off the pixel axes, at 25 sub-pixel positions: the
    X-junction fit's error stays below 0.008 px and below half the saddle fit's, whose resampled, smoothed
    quadratic pulls such corners towards pixel positions (up to 0.02 px: pixel locking). (Part of what is
    left is the test image's: 16x16 samples per pixel put an edge along a pixel axis on a 1/16 px grid.)"""
    errors: dict[str, list[float]] = {"saddle": [], "xjunction": []}
    for fx in np.linspace(0.0, 0.8, 5):
        for fy in np.linspace(0.0, 0.8, 5):
            centre = (32.0 + fx, 31.0 + fy)
            img = _junction(centre, (angle_deg, angle_deg + 90.0), blur=0.7)
            start = np.array([[32.4, 31.4]])
            spacing = np.array([30.0])
            saddle = saddle_refine(smooth_image(img, 1.0), start, spacing)
            xj = xjunction_fit(img, saddle, np.radians([[angle_deg, angle_deg + 90.0]]), np.array([12.0]))[0]
            errors["saddle"].append(float(np.hypot(*(saddle[0] - centre))))
            errors["xjunction"].append(float(np.hypot(*(xj[0] - centre))))
    worst = {k: max(v) for k, v in errors.items()}
    assert worst["xjunction"] < 0.008 and worst["xjunction"] < 0.5 * worst["saddle"], worst


def test_a_slanted_junction_is_found_from_rough_line_directions() -> None:
    """Lines at 20 and 80 degrees (a foreshortened corner), started 0.4 px and 8 degrees off."""
    centre = (30.3, 33.7)
    img = _junction(centre, (20.0, 80.0), blur=1.2)
    out = xjunction_fit(img, np.array([[30.6, 33.4]]), np.radians([[28.0, 72.0]]), np.array([10.0]))[0]
    assert np.hypot(*(out[0] - centre)) < 0.01


@pytest.mark.parametrize(("blur", "angles_deg", "noise"), [(0.8, (10.0, 100.0), 4.0), (2.0, (25.0, 70.0), 6.0)])
def test_the_fits_noise_covariance_matches_the_scatter_under_white_noise(
        blur: float, angles_deg: tuple[float, float], noise: float) -> None:
    """One junction (sharp and square, or blurred and slanted) under 300 draws of white noise: the scatter of
    the fitted corners matches noise^2 x the fit's covariance per unit noise variance (its third output), per
    axis and in the correlation, to the sampling error of 300 draws; and a corner it did not fit has NaN."""
    centre = (32.3, 31.6)
    clean = _junction(centre, angles_deg, blur).astype(np.float64)
    rng = np.random.default_rng(5)
    start = np.array([[32.0, 32.0]])
    angles = np.radians([angles_deg])
    fits, covs = [], []
    for _ in range(300):
        img = np.clip(np.rint(clean + rng.normal(0.0, noise, clean.shape)), 0, 255).astype(np.uint8)
        out, fitted, cov = xjunction_fit(img, start, angles, np.array([10.0]))
        assert fitted[0]
        fits.append(out[0])
        covs.append(cov[0])
    scatter = np.cov(np.array(fits).T)
    predicted = noise ** 2 * np.mean(covs, axis=0)
    ratio = np.diag(scatter) / np.diag(predicted)
    assert np.all((ratio > 0.75) & (ratio < 1.3)), (ratio, scatter, predicted)
    corr = lambda c: c[0, 1] / np.sqrt(c[0, 0] * c[1, 1])  # noqa: E731
    assert abs(corr(scatter) - corr(predicted)) < 0.15, (scatter, predicted)
    _out, fitted, cov = xjunction_fit(np.full((64, 64), 120, np.uint8), start, angles, np.array([10.0]))
    assert not fitted[0] and np.isnan(cov).all()


def test_the_fits_exp_matches_math_exp_to_an_ulp() -> None:
    """The arithmetic exp(-u^2) of the fit's SIMD loop against math.exp over every argument it sees (u from
    0 to the flat edge of the sharpest blur), and a clean floor far beyond."""
    import math

    from edgecal.detection.subpixel import _exp_neg_square

    for u in np.concatenate([np.linspace(0.0, 26.0, 20001), [1e-8, 0.5, 1.0, 10.0, 26.4]]):
        want = math.exp(-u * u)
        assert abs(_exp_neg_square(u) - want) <= 2.5e-16 * want, u
    assert 0.0 <= _exp_neg_square(40.0) <= 1e-300 and _exp_neg_square(1e10) <= 1e-300


def test_no_junction_or_a_disc_beyond_the_image_keeps_the_start() -> None:
    """A flat patch has no lines to fit and a disc past the border no pixels: both corners stay put."""
    flat = np.full((64, 64), 120, np.uint8)
    start = np.array([[32.0, 32.0], [3.0, 40.0]])
    out = xjunction_fit(flat, start, np.radians([[0.0, 90.0], [0.0, 90.0]]), np.array([8.0, 8.0]))[0]
    np.testing.assert_array_equal(out, start)


@pytest.mark.parametrize("cut", [0.35, 0.45, 0.6, 1.0])
def test_the_disc_of_a_rim_corner_stays_inside_the_outer_squares(cut: float) -> None:
    """A board whose outer squares are ``cut`` of a square wide, then the background: the rim corners' discs
    end before the board's edge (which would pull them outwards), inner corners keep 0.6 of the square
    (up to 12 px); the rim corners come out as accurate as with the saddle fit or better."""
    target, view = _cut_board_view(cut, 5.0, 1)
    (det,) = edgecal.detect(view.image, target)
    smooth = smooth_image(view.image, 1.0)
    radius = xjunction_radius(smooth, det.corners, det.ids)
    rim = on_board_rim(det.ids)
    square = float(np.median(nearest_spacing(det.corners)))
    np.testing.assert_allclose(radius[~rim], np.clip(0.6 * nearest_spacing(det.corners)[~rim], 3.0, 12.0))
    # the outer squares end cut x square beyond the rim (measured: 6.6-9.4 px against 10.7 at 0.35, 0 at the
    # board's corners, where the fit is left out)
    assert radius[rim].max() < max(cut * square - 0.5 * RIM_EDGE_MARGIN_PX, 12.0 if cut >= 0.6 else 0.0)
    (saddle,) = edgecal.detect(view.image, target, DetectorParams(subpixel_refiner="saddle"))
    truth = {tuple(i): c for i, c in zip(view.ids(), view.corners())}
    err = {name: np.array([np.linalg.norm(c - truth[tuple(i)]) for i, c in zip(d.ids, d.corners)])
           for name, d in (("xjunction", det), ("saddle", saddle))}
    assert err["xjunction"][rim].max() < 0.1
    assert corner_rms(err["xjunction"][rim]) <= 1.05 * corner_rms(err["saddle"][rim]), err


def test_grid_line_angles_follow_a_rotated_grid() -> None:
    """A 4x3 grid rotated by 30 degrees: rows at 30, columns at 120 degrees, at inner and outer corners."""
    ids = np.array([(c, r) for r in range(3) for c in range(4)])
    rot = np.array([[np.cos(np.pi / 6), -np.sin(np.pi / 6)], [np.sin(np.pi / 6), np.cos(np.pi / 6)]])
    xy = 20.0 * ids @ rot.T + 100.0
    angles = np.degrees(grid_line_angles(xy, ids))
    np.testing.assert_allclose(angles[:, 0], 30.0, atol=1e-9)
    np.testing.assert_allclose(angles[:, 1], 120.0, atol=1e-9)


@pytest.mark.parametrize("photometric,gain,rms_max", [("clean", 0.95, 0.0065), ("normal", 0.85, 0.02)])
def test_xjunction_fit_beats_the_saddle_fit(photometric: str, gain: float, rms_max: float) -> None:
    """The default refiner (cornerSubPix, the saddle fit, the X-junction fit) against the saddle fit alone on
    the same renders, and its RMS itself (measured: clean 0.0053 against 0.0069 px, normal 0.014 against
    0.022)."""
    errors: dict[str, list[np.ndarray]] = {"saddle": [], "xjunction": []}
    for seed in range(4):
        view = planar_view(seed, size=(640, 480), square_px=(20.0, 45.0), photometric=photometric,
                           background="uniform")
        truth = ground_truth_from_mapping(view.truth, "xj")
        for refiner in errors:
            dets = edgecal.detect(view.image, planar_target(9, 6), DetectorParams(subpixel_refiner=refiner))
            score = score_image([FoundGrid(d.corners, d.ids, d.grid) for d in dets], truth, "grid")
            assert score.n_found == 1
            errors[refiner].append(score.found_errors())
    rms = {k: corner_rms(np.concatenate(v)) for k, v in errors.items()}
    assert rms["xjunction"] < gain * rms["saddle"], rms
    assert rms["xjunction"] <= rms_max, rms
