"""Writing and reading calibration files: rig.yaml (cv2.FileStorage) and ROS camera_info YAML.

rig.yaml nodes (stereo): image_size [w, h], distortion_model_left/right (the lens model: radtan,
rational or fisheye, docs/conventions.md; radtan when absent, as in files before lens models),
camera_matrix_left, dist_coeffs_left, camera_matrix_right, dist_coeffs_right, R, T (metres;
X_right = R X_left + T), and their standard deviations (intrinsics_std_left/right: fx fy cx cy and the
lens model's parameters in order, .Nan where the term was fixed; R_std_rad, the std of R's rotation
vector; T_std_m), plus the rectification R1 R2 P1 P2 Q and quality figures. A single camera writes
distortion_model, camera_matrix, dist_coeffs and intrinsics_std instead. The ``provenance`` map says
what produced the file: target and boards, square_mm, the view files, the corners file, the edgecal
version, created (UTC ISO 8601) and the settings.

rig.yaml and its camera_info files are written as one set (edgecal.fileio.write_atomic_set: every
temporary, then every rename), so a reader or a rerun never finds half a file or half a set; an existing
file is replaced only with ``force``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import yaml

from edgecal.calibration.types import Calibration
from edgecal.camera import LENS_PARAMS, CameraModel, StereoRig
from edgecal.errors import ConfigError, InputError
from edgecal.fileio import check_outputs, write_atomic_set


def camera_info_paths(rig_path: str | Path, stereo: bool) -> list[Path]:
    """The ROS camera_info files written beside ``rig_path``: NAME.left/right.camera_info.yaml (or NAME.camera_info.yaml)."""
    p = Path(rig_path)
    stem = p.name[: -len(p.suffix)] if p.suffix else p.name
    names = ("left", "right") if stereo else ("",)
    return [p.with_name(f"{stem}.{n}.camera_info.yaml" if n else f"{stem}.camera_info.yaml") for n in names]


def _std_row(std: dict[str, float], cam: CameraModel) -> np.ndarray:
    return np.array([[std.get(n, np.nan) for n in cam.intrinsic_names]], dtype=np.float64)


def _write_node(fs: cv2.FileStorage, name: str, value: object) -> None:
    """Write a plain value (str, number, bool, None, list, dict) as a FileStorage node; "" names a sequence item."""
    if isinstance(value, dict):
        fs.startWriteStruct(name, cv2.FileNode_MAP)
        for k, v in value.items():
            _write_node(fs, str(k), v)
        fs.endWriteStruct()
    elif isinstance(value, (list, tuple)):
        fs.startWriteStruct(name, cv2.FileNode_SEQ)
        for v in value:
            _write_node(fs, "", v)
        fs.endWriteStruct()
    elif isinstance(value, (bool, int, np.integer)):
        fs.write(name, int(value))
    elif isinstance(value, (float, np.floating)):
        fs.write(name, float(value))
    else:
        fs.write(name, "" if value is None else str(value))


def _read_node(node: cv2.FileNode) -> object:
    """The plain value of a FileStorage node (the inverse of _write_node; booleans come back as 0/1)."""
    if node.isMap():
        return {k: _read_node(node.getNode(k)) for k in node.keys()}
    if node.isSeq():
        return [_read_node(node.at(i)) for i in range(node.size())]
    if node.isInt():
        return int(node.real())
    if node.isReal():
        return float(node.real())
    return node.string()


def rig_yaml(cal: Calibration, provenance: dict | None = None) -> str:
    """The rig.yaml text (OpenCV FileStorage YAML) of a calibration."""
    # written to memory: the file itself is written by write_atomic_set with the others of its set
    fs = cv2.FileStorage(".yaml", cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY)
    fs.writeComment("edgecal calibration; T in metres, X_right = R X_left + T (docs/conventions.md)")
    fs.startWriteStruct("image_size", cv2.FileNode_SEQ | cv2.FileNode_FLOW)
    fs.write("", int(cal.image_size[0]))
    fs.write("", int(cal.image_size[1]))
    fs.endWriteStruct()
    fs.write("calibration_kind", cal.kind)
    fs.write("rms_px", float(cal.rms_px))
    suffixes = ("_left", "_right") if cal.is_stereo else ("",)
    for cam, std, sfx in zip(cal.cameras, cal.camera_std, suffixes):
        fs.write("distortion_model" + sfx, cam.lens)
        fs.write("camera_matrix" + sfx, cam.camera_matrix)
        fs.write("dist_coeffs" + sfx, np.asarray(cam.dist_coeffs, dtype=np.float64).reshape(1, -1))
        fs.writeComment(f"std order: {' '.join(cam.intrinsic_names)} (.Nan = fixed)")
        fs.write("intrinsics_std" + sfx, _std_row(std, cam))
    if cal.is_stereo:
        fs.write("R", cal.rotation)
        fs.write("T", np.ravel(cal.translation_mm).reshape(3, 1) * 1e-3)
        fs.write("R_std_rad", np.ravel(cal.rotation_std_rad).reshape(3, 1))
        fs.write("T_std_m", np.ravel(cal.translation_std_mm).reshape(3, 1) * 1e-3)
        if cal.rectification is not None:
            rect = cal.rectification
            fs.write("R1", rect.r1)
            fs.write("R2", rect.r2)
            fs.write("P1", rect.p1)
            p2 = rect.p2.copy()
            p2[:, 3] *= 1e-3  # stereoRectify works in the unit of T (mm here); the file is in metres
            fs.write("P2", p2)
            q = rect.q.copy()
            q[3, :] *= 1e3
            fs.write("Q", q)
            fs.write("epipolar_rms_px", float(rect.epipolar_rms_px))
        if cal.reconstruction is not None:
            fs.write("reconstruction_error_mean_mm", float(cal.reconstruction.mean_mm))
            fs.write("reconstruction_error_std_mm", float(cal.reconstruction.std_mm))
    if provenance:
        _write_node(fs, "provenance", provenance)
    return fs.releaseAndGetString()


def _matrix(m: np.ndarray) -> dict:
    m = np.asarray(m, dtype=np.float64)
    return {"rows": int(m.shape[0]), "cols": int(m.shape[1]), "data": [float(v) for v in m.ravel()]}


def camera_info(cal: Calibration, index: int, camera_name: str | None = None) -> dict:
    """The ROS sensor_msgs/CameraInfo YAML mapping (camera_calibration_parsers layout) of one camera.

    ``camera_name`` should be the name the camera driver gives (camera_info_manager warns on a mismatch);
    default "left"/"right"/"camera".
    """
    cam = cal.cameras[index]
    name = camera_name or cal.camera_names[index]
    if cal.is_stereo and cal.rectification is not None:
        rect = cal.rectification.r1 if index == 0 else cal.rectification.r2
        proj = (cal.rectification.p1 if index == 0 else cal.rectification.p2).copy()
        proj[:, 3] *= 1e-3  # ROS wants the baseline term Tx * fx with Tx in metres
    else:
        rect = np.eye(3)
        proj = np.hstack([cam.camera_matrix, np.zeros((3, 1))])
    return {
        "image_width": int(cal.image_size[0]),
        "image_height": int(cal.image_size[1]),
        "camera_name": name,
        "camera_matrix": _matrix(cam.camera_matrix),
        "distortion_model": cam.ros_distortion_model,
        "distortion_coefficients": _matrix(np.asarray(cam.dist_coeffs, dtype=np.float64).reshape(1, -1)),
        "rectification_matrix": _matrix(rect),
        "projection_matrix": _matrix(proj),
    }


def write_calibration(cal: Calibration, path: str | Path, force: bool = False, provenance: dict | None = None,
                      camera_names: list[str] | None = None, also: dict[Path, bytes] | None = None) -> list[Path]:
    """Write rig.yaml and one camera_info YAML per camera as one set; return the paths written.

    ``provenance`` (plain values) becomes rig.yaml's provenance map; ``camera_names`` the camera_info
    camera_name of each camera; ``also`` are files written in the same set (the corners file).
    Nothing is written if any destination exists and ``force`` is off, or its folder is not writable.
    """
    rig = Path(path)
    infos = camera_info_paths(rig, cal.is_stereo)
    check_outputs([rig, *infos, *(also or {})], force)
    files = {rig: rig_yaml(cal, provenance).encode("utf-8")}
    for i, p in enumerate(infos):
        info = camera_info(cal, i, camera_names[i] if camera_names else None)
        files[p] = yaml.safe_dump(info, sort_keys=False, default_flow_style=None).encode("utf-8")
    files.update(also or {})
    write_atomic_set(files)
    return list(files)


@dataclass
class RigFile:
    """What a rig.yaml holds: one or two cameras, for two the StereoRig, and the figures written with them."""

    image_size: tuple[int, int]
    cameras: list[CameraModel]
    intrinsics_std: list[dict[str, float]]
    stereo: StereoRig | None = None
    rotation_std_rad: np.ndarray | None = None
    translation_std_m: np.ndarray | None = None
    extra: dict[str, np.ndarray] = field(default_factory=dict)  # R1 R2 P1 P2 Q when present
    provenance: dict = field(default_factory=dict)  # what produced the file (empty for older files)

    @property
    def is_stereo(self) -> bool:
        """Whether the file holds two cameras."""
        return self.stereo is not None


def load_rig(path: str | Path) -> RigFile:
    """Read a rig.yaml written by :func:`write_calibration` (or any file with the same OpenCV nodes).

    Raises InputError for a missing or unreadable file and ConfigError naming a missing or wrong node.
    """
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: calibration file not found (run `edgecal calibrate` first)")
    try:
        fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_READ)
    except cv2.error:
        raise InputError(f"{p}: not a readable OpenCV YAML/XML calibration file") from None
    if not fs.isOpened():
        raise InputError(f"{p}: not a readable OpenCV YAML/XML calibration file")
    try:
        def node(name: str, shape: tuple[int, ...] | None, required: bool = True) -> np.ndarray | None:
            n = fs.getNode(name)
            if n.empty():
                if required:
                    raise ConfigError(f"{p}: node '{name}' is missing")
                return None
            m = n.mat()
            if m is None:
                raise ConfigError(f"{p}: node '{name}' must be an OpenCV matrix")
            m = np.asarray(m, dtype=np.float64)
            if shape is not None and m.size != int(np.prod(shape)):
                raise ConfigError(f"{p}: node '{name}' must hold {int(np.prod(shape))} numbers (has {m.size})")
            return m.reshape(shape) if shape is not None else m

        size_node = fs.getNode("image_size")
        if size_node.empty():
            raise ConfigError(f"{p}: node 'image_size' is missing")
        if size_node.isSeq():
            size = [int(size_node.at(i).real()) for i in range(size_node.size())]
        else:
            size = [int(v) for v in np.ravel(size_node.mat())]
        if len(size) != 2 or min(size) <= 0:
            raise ConfigError(f"{p}: node 'image_size' must be [width, height]")
        stereo = not fs.getNode("camera_matrix_left").empty()
        sfx = ("_left", "_right") if stereo else ("",)
        cams, stds = [], []
        for s in sfx:
            model = fs.getNode("distortion_model" + s)
            lens = "radtan" if model.empty() else model.string()
            if lens not in LENS_PARAMS:
                raise ConfigError(f"{p}: node 'distortion_model{s}' is {lens[:40]!r}; known: {', '.join(LENS_PARAMS)}")
            k = node("camera_matrix" + s, (3, 3))
            d = np.ravel(node("dist_coeffs" + s, None))
            n_params = len(LENS_PARAMS[lens])
            if len(d) > n_params and (lens != "radtan" or np.any(d[n_params:] != 0)):
                raise ConfigError(f"{p}: node 'dist_coeffs{s}' has {len(d)} numbers; the {lens} model has {n_params}")
            cam = CameraModel(k[0, 0], k[1, 1], k[0, 2], k[1, 2], lens, d[:n_params], (size[0], size[1]))
            cams.append(cam)
            std = node("intrinsics_std" + s, None, required=False)
            stds.append({n: float(v) for n, v in zip(cam.intrinsic_names, np.ravel(std))} if std is not None else {})
        rig = RigFile((size[0], size[1]), cams, stds)
        if stereo:
            rotation = node("R", (3, 3))
            if abs(np.linalg.det(rotation) - 1) > 1e-6:
                raise ConfigError(f"{p}: node 'R' is not a rotation matrix")
            rig.stereo = StereoRig(cams[0], cams[1], rotation, node("T", (3,)))
            rig.rotation_std_rad = node("R_std_rad", (3,), required=False)
            rig.translation_std_m = node("T_std_m", (3,), required=False)
            for name in ("R1", "R2", "P1", "P2", "Q"):
                m = node(name, None, required=False)
                if m is not None:
                    rig.extra[name] = m
        prov = fs.getNode("provenance")
        if not prov.empty() and prov.isMap():
            rig.provenance = _read_node(prov)
        return rig
    finally:
        fs.release()
