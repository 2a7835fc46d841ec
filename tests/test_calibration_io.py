"""rig.yaml round trip through cv2.FileStorage, camera_info files, atomic and non-clobbering writes."""

import cv2
import numpy as np
import pytest
import yaml

from edgecal.calibration.io import camera_info_paths, load_rig, write_calibration
from edgecal.calibration.mono import calibrate_box_mono
from edgecal.calibration.stereo import calibrate_box_stereo
from edgecal.calibration.types import RigidTransform
from edgecal.errors import ConfigError, InputError
from edgecal.synth.corners import cube_box_target, project_target, stereo_truth

SIZE = (640, 480)


@pytest.fixture(scope="module")
def stereo_cal():
    cl, cr, pl, rig = stereo_truth()
    pr = RigidTransform.from_rt(rig.rotation @ pl.rotation, rig.rotation @ pl.tvec + rig.tvec)
    rng = np.random.default_rng(1)
    t = cube_box_target()
    return calibrate_box_stereo(project_target(t, cl, pl, SIZE, 0.1, rng), project_target(t, cr, pr, SIZE, 0.1, rng),
                                SIZE)


def test_rig_yaml_round_trip_with_opencv(tmp_path, stereo_cal):
    out = tmp_path / "rig.yaml"
    written = write_calibration(stereo_cal, out)
    assert written == [out, *camera_info_paths(out, True)]
    fs = cv2.FileStorage(str(out), cv2.FILE_STORAGE_READ)
    np.testing.assert_allclose(fs.getNode("camera_matrix_left").mat(), stereo_cal.cameras[0].camera_matrix)
    np.testing.assert_allclose(fs.getNode("dist_coeffs_right").mat().ravel(), stereo_cal.cameras[1].dist_coeffs)
    np.testing.assert_allclose(fs.getNode("R").mat(), stereo_cal.rotation)
    np.testing.assert_allclose(fs.getNode("T").mat().ravel(), stereo_cal.translation_mm * 1e-3)  # metres
    std = fs.getNode("intrinsics_std_left").mat().ravel()
    assert std[0] == pytest.approx(stereo_cal.camera_std[0]["fx"]) and np.isnan(std[6])  # p1 fixed
    assert [int(fs.getNode("image_size").at(i).real()) for i in range(2)] == list(SIZE)
    fs.release()
    rig = load_rig(out)
    assert rig.is_stereo and rig.image_size == SIZE
    np.testing.assert_allclose(rig.stereo.t_right_left_m, stereo_cal.translation_mm * 1e-3)
    np.testing.assert_allclose(rig.translation_std_m, stereo_cal.translation_std_mm * 1e-3)
    np.testing.assert_allclose(rig.cameras[1].camera_matrix, stereo_cal.cameras[1].camera_matrix)
    # Q from the file reprojects disparity to metres: Q[3, 2] = -1 / Tx with Tx in metres
    assert abs(1.0 / abs(rig.extra["Q"][3, 2]) - np.linalg.norm(stereo_cal.translation_mm) * 1e-3) < 0.01


def test_camera_info_is_ros_layout(tmp_path, stereo_cal):
    out = tmp_path / "rig.yaml"
    write_calibration(stereo_cal, out)
    info = yaml.safe_load(camera_info_paths(out, True)[1].read_text())
    assert info["camera_name"] == "right" and info["distortion_model"] == "plumb_bob"
    assert (info["image_width"], info["image_height"]) == SIZE
    p = np.array(info["projection_matrix"]["data"]).reshape(3, 4)
    # P2[0, 3] = -fx' * baseline, baseline in metres
    assert p[0, 3] / p[0, 0] == pytest.approx(-np.linalg.norm(stereo_cal.translation_mm) * 1e-3, rel=0.05)


def test_existing_file_is_not_replaced_without_force(tmp_path, stereo_cal):
    out = tmp_path / "rig.yaml"
    out.write_text("precious")
    with pytest.raises(InputError, match="--force"):
        write_calibration(stereo_cal, out)
    assert out.read_text() == "precious"
    assert not camera_info_paths(out, True)[0].exists()  # nothing written at all
    write_calibration(stereo_cal, out, force=True)
    assert load_rig(out).is_stereo
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temp files left


def test_mono_file(tmp_path):
    cam, _, pose, _ = stereo_truth()
    cal = calibrate_box_mono(project_target(cube_box_target(), cam, pose, SIZE, 0.05), SIZE)
    out = tmp_path / "cam.yaml"
    write_calibration(cal, out)
    fs = cv2.FileStorage(str(out), cv2.FILE_STORAGE_READ)
    assert fs.getNode("camera_matrix").mat().shape == (3, 3) and fs.getNode("R").empty()
    fs.release()
    rig = load_rig(out)
    assert not rig.is_stereo and rig.stereo is None
    assert (tmp_path / "cam.camera_info.yaml").is_file()


def test_load_rig_errors_name_the_problem(tmp_path):
    with pytest.raises(InputError, match="not found"):
        load_rig(tmp_path / "missing.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("%YAML:1.0\n---\nimage_size: [640, 480]\n")
    with pytest.raises(ConfigError, match="'camera_matrix' is missing"):
        load_rig(bad)


def test_missing_output_folder_is_an_input_error(tmp_path, stereo_cal):
    with pytest.raises(InputError, match="does not exist"):
        write_calibration(stereo_cal, tmp_path / "nope" / "rig.yaml")
