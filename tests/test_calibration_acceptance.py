"""Out-of-bounds calibrations are refused with the numbers; the settings file is validated."""

import numpy as np
import pytest

from edgecal.calibration.acceptance import acceptance_problems, require_acceptable
from edgecal.calibration.mono import calibrate_box_mono
from edgecal.calibration.settings import Acceptance, load_calibration_settings
from edgecal.errors import CalibrationRejected, ConfigError
from edgecal.synth.corners import cube_box_target, project_target, stereo_truth

SIZE = (640, 480)


def _cal(noise):
    cam, _, pose, _ = stereo_truth()
    return calibrate_box_mono(project_target(cube_box_target(), cam, pose, SIZE, noise, np.random.default_rng(2)), SIZE)


def test_good_calibration_passes_default_bounds():
    cal = _cal(0.1)
    assert acceptance_problems(cal, load_calibration_settings().acceptance) == []
    require_acceptable(cal, load_calibration_settings().acceptance)


def test_noisy_calibration_is_refused_with_numbers():
    cal = _cal(2.0)
    with pytest.raises(CalibrationRejected) as exc:
        require_acceptable(cal, Acceptance(max_rms_px=1.0, max_focal_std_percent=1.0))
    msg = str(exc.value)
    assert "reprojection RMS" in msg and f"{cal.rms_px:.3f} px > 1 px" in msg
    assert "fx std" in msg and exc.value.exit_code == 4


def test_tight_uncertainty_bound_refuses_even_a_clean_fit():
    cal = _cal(0.1)
    problems = acceptance_problems(cal, Acceptance(max_focal_std_percent=0.001, max_principal_point_std_px=0.01))
    assert any("fx std" in p for p in problems) and any("cx std" in p for p in problems)


def test_settings_file_errors_name_the_field(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text("distortion: k9\n")
    with pytest.raises(ConfigError, match="'distortion' must be one of"):
        load_calibration_settings(p)
    p.write_text("acceptance:\n  max_rms: 1\n")
    with pytest.raises(ConfigError, match="'acceptance.max_rms' is not a known field"):
        load_calibration_settings(p)
    p.write_text("acceptance:\n  max_rms_px: -1\n")
    with pytest.raises(ConfigError, match="'acceptance.max_rms_px' must be"):
        load_calibration_settings(p)
    p.write_text("distortion: k1k2p1p2\nacceptance:\n  max_rms_px: 0.5\n")
    s = load_calibration_settings(p)
    assert s.refine.distortion == "k1k2p1p2" and s.acceptance.max_rms_px == 0.5
