"""Per-corner covariance (edgecal.detection.corner_covariance): checked against the scatter on renders with
exact truth, and unusable corners named without NaN (the full measurement is bench/corner_noise.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest

import edgecal
from edgecal.detection.candidates import estimate_noise_sigma, smooth_image, smoothing_sigma
from edgecal.detection.corner_covariance import (
    REASON_BORDER,
    REASON_DEGENERATE,
    REASON_FLAT,
    corner_covariance,
    covariance_noise_sigma,
)
from edgecal.detection.params import DetectorParams
from edgecal.detection.subpixel import refine_corners
from edgecal.detection.tracking import track_boards
from edgecal.detection.types import CornerPrediction
from edgecal.synth.photometric import Photometric, apply_photometric
from edgecal.synth.scenes import planar_view
from edgecal.targets import planar_target

TARGET = planar_target(9, 6, 25.0)


CORNERSUBPIX = DetectorParams(subpixel_refiner="cornersubpix")


def _nees(det, truth: np.ndarray) -> np.ndarray:
    ok = det.usable()
    xy, cov = det.corners[ok], det.covariance[ok]
    d = np.linalg.norm(xy[:, None] - truth[None], axis=2)
    j = d.argmin(axis=1)
    near = d[np.arange(len(j)), j] < 1.5
    e = xy[near] - truth[j[near]]
    return np.einsum("ni,nij,nj->n", e, np.linalg.inv(cov[near]), e)


@pytest.mark.parametrize("photometric", ["clean", "normal", "hard", "light"])
def test_normalised_error_matches_the_scatter(photometric: str) -> None:
    """Mean e^T Sigma^-1 e near 2 (a consistent 2-D covariance) over a few renders of each condition.

    Ten views leave the mean a wider spread than bench/corner_noise.py's 1.5-3 over 40-80 (a view's
    corners share its light and blur); a noise-only covariance would give 5-60 here. The model-error term
    for uneven light is sized for cornerSubPix's bias, and its floor for cornerSubPix's error on clean
    renders; the detector's default saddle fit is less biased and (since its 11x11 fit) 4x more accurate
    on clean renders, so there and under uneven light its covariance is conservative (checked below: mean
    0.8 on clean), and the consistency is checked on cornerSubPix's corners."""
    values, saddle = [], []
    for k in range(10):
        if photometric == "light":
            phot = Photometric(blur_sigma=0.7, gradient=(0.6 * (-1) ** k, 0.45), vignetting=0.4,
                               black_level=10, white_level=240, noise_sigma=2.0)
            view = planar_view([k, 71], photometric=phot)
        else:
            view = planar_view([k, 72], photometric=photometric)
        params = CORNERSUBPIX if photometric in ("light", "clean") else None
        for det in edgecal.detect(view.image, TARGET, params):
            assert det.covariance is not None and det.covariance.shape == (len(det.corners), 2, 2)
            values.append(_nees(det, view.corners(0)))
        if params is not None:
            saddle += [_nees(det, view.corners(0)) for det in edgecal.detect(view.image, TARGET)]
    nees = np.concatenate(values)
    assert len(nees) > 200
    assert 1.2 < nees.mean() < 4.0, nees.mean()
    if saddle:
        assert np.concatenate(saddle).mean() < 4.0  # conservative, never optimistic


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
    cov, reasons = corner_covariance(noisy[0], smooth_image(view.image, sigma), sigma, start,
                                     np.full(len(start), 30.0))
    assert not any(reasons)
    errs = np.array([refine_corners(smooth_image(im, sigma), start, np.full(len(start), 30.0)) - start for im in noisy])
    nees = np.einsum("kni,nij,knj->kn", errs, np.linalg.inv(cov), errs)
    assert 1.5 < nees.mean() < 2.8, nees.mean()


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
    cov, reasons = corner_covariance(img, smooth, sigma, pts, np.full(4, 20.0))
    assert reasons == [REASON_DEGENERATE, REASON_FLAT, REASON_BORDER, REASON_FLAT]
    assert np.isnan(cov).all()
    view = planar_view(4, photometric="normal")
    det = edgecal.detect(view.image, TARGET)[0]
    det.covariance[3] = np.nan
    det.unusable[3] = REASON_DEGENERATE
    text = json.dumps(det.as_json(), allow_nan=False)
    out = json.loads(text)
    assert out["covariance_px2"][3] is None and len(out["covariance_px2"]) == len(det.corners)
    assert out["unusable"] == [{"id": [int(v) for v in det.ids[3]], "reason": REASON_DEGENERATE}]
    assert not det.usable()[3] and det.usable().sum() == len(det.corners) - 1


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
