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
from typing import Literal, overload

import cv2
import numpy as np
import yaml

from edgecal.calibration.types import Calibration
from edgecal.camera import LENS_PARAMS, CameraModel, StereoRig
from edgecal.errors import ConfigError, InputError, quote
from edgecal.fileio import check_outputs, read_input, write_atomic_set


def camera_info_paths(rig_path: str | Path, stereo: bool) -> list[Path]:
    """The ROS camera_info files written beside ``rig_path``.

    NAME.left.camera_info.yaml and NAME.right.camera_info.yaml for a stereo rig, NAME.camera_info.yaml for one camera.
    """
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
        assert cal.rotation is not None and cal.translation_mm is not None  # set for every stereo calibration
        assert cal.rotation_std_rad is not None and cal.translation_std_mm is not None
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


# A rig file is a few KB; anything far bigger is not one (and FileStorage would parse it all in memory).
MAX_RIG_BYTES = 16 << 20


def _parse_file_storage(p: Path, data: bytes) -> cv2.FileStorage:
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError:
        raise InputError(f"{p}: not an OpenCV YAML/XML calibration file (binary content)") from None
    try:
        fs = cv2.FileStorage(text, cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY)
    except (cv2.error, SystemError):  # OpenCV reports a parse error as a SystemError from the constructor
        fs = None
    if fs is None or not fs.isOpened() or not fs.root().isMap():
        raise InputError(f"{p}: not an OpenCV YAML/XML calibration file (run `edgecal calibrate` to make one)")
    return fs


class _RigReader:
    """Typed access to the nodes of one rig file; every problem is a ConfigError naming file and node."""

    def __init__(self, path: Path, fs: cv2.FileStorage) -> None:
        self.path = path
        self.fs = fs

    def fail(self, name: str, what: str) -> ConfigError:
        return ConfigError(f"{self.path}: node '{name}' {what}")

    def has(self, name: str) -> bool:
        return not self.fs.getNode(name).empty()

    @overload
    def matrix(self, name: str, shapes: tuple[tuple[int, int], ...] | None, required: Literal[True] = True,
               finite: bool = True) -> np.ndarray: ...

    @overload
    def matrix(self, name: str, shapes: tuple[tuple[int, int], ...] | None, required: bool,
               finite: bool = True) -> np.ndarray | None: ...

    def matrix(self, name: str, shapes: tuple[tuple[int, int], ...] | None, required: bool = True,
               finite: bool = True) -> np.ndarray | None:
        """The node as a float64 matrix of one of ``shapes`` (None: any shape)."""
        n = self.fs.getNode(name)
        if n.empty():
            if required:
                raise self.fail(name, "is missing (is this a rig.yaml written by `edgecal calibrate`?)")
            return None
        try:
            m = n.mat() if n.isMap() else None
        except (cv2.error, SystemError):
            m = None
        if m is None:
            raise self.fail(name, "must be an OpenCV matrix (!!opencv-matrix with rows, cols, dt, data)")
        m = np.asarray(m, dtype=np.float64)
        if m.ndim == 1:
            m = m.reshape(-1, 1)
        if shapes is not None and m.shape[:2] not in shapes:
            want = " or ".join(f"{r}x{c}" for r, c in shapes)
            raise self.fail(name, f"must be a {want} matrix (is {m.shape[0]}x{m.shape[1]})")
        if finite and not np.all(np.isfinite(m)):
            raise self.fail(name, "holds NaN or infinite values")
        return m

    def string(self, name: str, default: str) -> str:
        n = self.fs.getNode(name)
        if n.empty():
            return default
        if not n.isString():
            raise self.fail(name, "must be a string")
        return n.string()

    def image_size(self) -> tuple[int, int]:
        name = "image_size"
        n = self.fs.getNode(name)
        if n.empty():
            raise self.fail(name, "is missing (is this a rig.yaml written by `edgecal calibrate`?)")
        try:
            if n.isSeq():
                values = [n.at(i).real() for i in range(n.size())]
            else:
                values = list(np.ravel(self.matrix(name, None)))
        except (cv2.error, SystemError):
            values = []
        if len(values) != 2 or not all(np.isfinite(v) and v == int(v) and v > 0 for v in values):
            raise self.fail(name, "must be [width, height], two positive integers")
        return int(values[0]), int(values[1])

    def camera(self, sfx: str, size: tuple[int, int]) -> CameraModel:
        lens = self.string("distortion_model" + sfx, "radtan")
        if lens not in LENS_PARAMS:
            raise self.fail("distortion_model" + sfx, f"is {quote(lens)}; known: {', '.join(LENS_PARAMS)}")
        k = self.matrix("camera_matrix" + sfx, ((3, 3),))
        if not (k[0, 0] > 0 and k[1, 1] > 0):
            raise self.fail("camera_matrix" + sfx, f"must have positive focal lengths (fx {k[0, 0]:g}, fy {k[1, 1]:g})")
        if k[1, 0] != 0 or k[2, 0] != 0 or k[2, 1] != 0 or k[2, 2] != 1:
            raise self.fail("camera_matrix" + sfx, "must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]")
        d = self.matrix("dist_coeffs" + sfx, None)
        if min(d.shape[:2]) > 1:
            raise self.fail("dist_coeffs" + sfx, f"must be a row of coefficients (is {d.shape[0]}x{d.shape[1]})")
        d = np.ravel(d)
        n_params = len(LENS_PARAMS[lens])
        # radtan files may carry OpenCV's longer vectors (8, 12, 14) with the extra terms zero
        if len(d) > n_params and (lens != "radtan" or np.any(d[n_params:] != 0)):
            raise self.fail("dist_coeffs" + sfx, f"has {len(d)} numbers; the {lens} model has {n_params}")
        return CameraModel(k[0, 0], k[1, 1], k[0, 2], k[1, 2], lens, d[:n_params], size)


# Longer than any stereo rig's baseline: a T this long is a unit mistake (mm for m) or a broken file.
MAX_BASELINE_M = 20.0


def load_rig(path: str | Path) -> RigFile:
    """Read a rig.yaml written by :func:`write_calibration` (or any file with the same OpenCV nodes).

    Raises InputError for a missing file, one this user may not read ("permission denied") or one that is
    not an OpenCV FileStorage file, and ConfigError naming the node that is missing, of the wrong shape,
    not finite, or not physical (focal lengths <= 0, R not a rotation, a zero baseline).
    """
    p = Path(path)
    if not p.is_file() and not p.is_dir():
        raise InputError(f"{p}: calibration file not found (run `edgecal calibrate` first)")
    fs = _parse_file_storage(p, read_input(p, "calibration file", max_bytes=MAX_RIG_BYTES))
    try:
        r = _RigReader(p, fs)
        size = r.image_size()
        stereo = r.has("camera_matrix_left")
        cams, stds = [], []
        for sfx in ("_left", "_right") if stereo else ("",):
            cam = r.camera(sfx, size)
            cams.append(cam)
            # NaN is allowed here: it marks a term that was held fixed
            std = r.matrix("intrinsics_std" + sfx, None, required=False, finite=False)
            stds.append({n: float(v) for n, v in zip(cam.intrinsic_names, np.ravel(std))} if std is not None else {})
        rig = RigFile(size, cams, stds)
        if stereo:
            rotation = r.matrix("R", ((3, 3),))
            rt = rotation @ rotation.T
            if abs(np.linalg.det(rotation) - 1) > 1e-6 or not np.allclose(rt, np.eye(3), atol=1e-6):
                raise r.fail("R", "is not a rotation matrix (R R^T = I, det R = 1)")
            translation = np.ravel(r.matrix("T", ((3, 1), (1, 3))))
            if not np.abs(translation).max() > 0:
                raise r.fail("T", "is zero: a stereo rig needs a baseline")
            if np.abs(translation).max() > MAX_BASELINE_M:
                raise r.fail("T", f"is {np.abs(translation).max():.3g} m long, more than any stereo rig's "
                                  f"{MAX_BASELINE_M:g} m: T is in metres (a T in mm is 1000x too large)")
            rig.stereo = StereoRig(cams[0], cams[1], rotation, translation)
            std_r = r.matrix("R_std_rad", ((3, 1), (1, 3)), required=False, finite=False)
            std_t = r.matrix("T_std_m", ((3, 1), (1, 3)), required=False, finite=False)
            rig.rotation_std_rad = None if std_r is None else np.ravel(std_r)
            rig.translation_std_m = None if std_t is None else np.ravel(std_t)
            for name, shape in (("R1", (3, 3)), ("R2", (3, 3)), ("P1", (3, 4)), ("P2", (3, 4)), ("Q", (4, 4))):
                m = r.matrix(name, (shape,), required=False)
                if m is not None:
                    rig.extra[name] = m
        prov = fs.getNode("provenance")
        if not prov.empty() and prov.isMap():
            try:
                provenance = _read_node(prov)
                assert isinstance(provenance, dict)  # a map node reads as a dict
                rig.provenance = provenance
            except (cv2.error, SystemError):
                raise r.fail("provenance", "cannot be read") from None
        return rig
    finally:
        fs.release()
