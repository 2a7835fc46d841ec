"""bench/live.py's per-axis ratio interval (ratio_interval): what the covariance targets are judged by."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

BENCH = Path(__file__).resolve().parents[1] / "bench" / "live.py"


@pytest.fixture(scope="module")
def live():
    spec = importlib.util.spec_from_file_location("bench_live", BENCH)
    module = importlib.util.module_from_spec(spec)
    sys.modules["bench_live"] = module
    try:
        spec.loader.exec_module(module)
        yield module
    finally:
        sys.modules.pop("bench_live", None)


def test_independent_frames_give_an_interval_around_the_ratio_of_the_expected_width(live) -> None:
    """300 frames of independent errors over sigma with RMS 0.8 ... 1.3 per axis: each interval holds the
    sample's RMS, and its width is what independent frames scatter by (1.645 x 2 x RMS / sqrt(2 n) = 0.13 RMS),
    within a factor of 1.5 (the bootstrap's own scatter)."""
    scale = np.array([0.8, 0.9, 1.0, 1.1, 1.2, 1.3])
    z = np.random.default_rng(3).normal(size=(300, 6)) * scale
    rms = np.sqrt(np.mean(z ** 2, axis=0))
    lo, hi = live.ratio_interval(z)
    assert np.all((lo < rms) & (rms < hi))
    width = (hi - lo) / rms
    expected = 2 * 1.645 / np.sqrt(2 * 300)
    assert np.all((width > expected / 1.5) & (width < expected * 1.5)), width


def test_errors_alike_over_consecutive_frames_widen_the_interval(live) -> None:
    """The same RMS, but each second (30 frames) of the sequence scaled alike, as a slowly changing geometry
    does: the blocks see it and the interval is at least 1.5x as wide as for independent frames (1.8-3.9x here)."""
    rng = np.random.default_rng(4)
    independent = rng.normal(size=(300, 6))
    slow = rng.normal(size=(300, 6)) * np.repeat(rng.uniform(0.3, 1.7, size=(10, 6)), 30, axis=0)
    slow *= np.sqrt(np.mean(independent ** 2, axis=0) / np.mean(slow ** 2, axis=0))
    lo_i, hi_i = live.ratio_interval(independent)
    lo_s, hi_s = live.ratio_interval(slow)
    assert np.all(hi_s - lo_s > 1.5 * (hi_i - lo_i))


def test_too_short_a_sequence_has_no_interval(live) -> None:
    """Fewer than two blocks of frames: no interval (NaN), and the printed form says so."""
    lo, hi = live.ratio_interval(np.ones((59, 6)))
    assert np.isnan(lo).all() and np.isnan(hi).all()
    assert live._intervals([[float(a), float(b)] for a, b in zip(lo, hi)]) == "n/a"
    assert live._intervals([[0.9, 1.1]] * 2) == "[0.90-1.10, 0.90-1.10]"
