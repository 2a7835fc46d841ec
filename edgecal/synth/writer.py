"""Writing rendered views to disk: PNG + "edgecal-synth-gt/1" JSON, atomically, never clobbering.

Every file is written atomically with the umask's permissions (edgecal.fileio), so a reader never sees
half a file; a robot sequence's frames are fsynced in one batch before its truth.json. Existing files
are refused (InputError naming the first one) unless ``force`` is given; the check happens before
anything is written, so a refused call writes nothing.
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from edgecal.fileio import png_bytes, refuse_existing, sync_paths, write_atomic
from edgecal.synth.scenes.box import StereoView
from edgecal.synth.scenes.robot import RobotFrame, RobotRig
from edgecal.synth.view import RenderedView
from edgecal.targets import Target

ROBOT_FORMAT = "edgecal-synth-robot/1"


def json_bytes(doc: dict) -> bytes:
    """Compact but readable JSON (one level of indentation)."""
    return (json.dumps(doc, indent=1) + "\n").encode("utf-8")


def write_view(out_dir: str | Path, stem: str, view: RenderedView, force: bool = False) -> list[Path]:
    """Write STEM.png and STEM.json; returns the paths written."""
    out = Path(out_dir)
    png, js = out / f"{stem}.png", out / f"{stem}.json"
    refuse_existing([png, js], force)
    truth = dict(view.truth)
    truth["image"] = png.name
    write_atomic(png, png_bytes(view.image))
    write_atomic(js, json_bytes(truth))
    return [png, js]


def write_stereo(out_dir: str | Path, stem: str, pair: StereoView, force: bool = False) -> list[Path]:
    """Write STEM_L/_R .png/.json and STEM_pair.json (the rig truth)."""
    out = Path(out_dir)
    names = [out / f"{stem}_{s}.{e}" for s in ("L", "R") for e in ("png", "json")] + [out / f"{stem}_pair.json"]
    refuse_existing(names, force)
    written = []
    pair_name = f"{stem}_pair.json"
    for side, view in (("L", pair.left), ("R", pair.right)):
        truth = dict(view.truth)
        truth["image"] = f"{stem}_{side}.png"
        truth["pair"] = pair_name
        write_atomic(out / truth["image"], png_bytes(view.image))
        write_atomic(out / f"{stem}_{side}.json", json_bytes(truth))
        written += [out / truth["image"], out / f"{stem}_{side}.json"]
    doc = dict(pair.pair)
    doc["images"] = {"left": f"{stem}_L.png", "right": f"{stem}_R.png"}
    write_atomic(out / pair_name, json_bytes(doc))
    return written + [out / pair_name]


def _quat_xyzw(R: np.ndarray) -> list[float]:
    """Unit quaternion (x, y, z, w), w >= 0, of a rotation matrix (docs/conventions.md)."""
    from scipy.spatial.transform import Rotation

    q = Rotation.from_matrix(R).as_quat()
    return (q if q[3] >= 0 else -q).tolist()


def write_robot_sequence(out_dir: str | Path, frames: Iterable[RobotFrame], rig: RobotRig, target: Target,
                         fps: float, force: bool = False) -> int:
    """Write a robot sequence: left/NNNNNN.png, right/NNNNNN.png and truth.json; returns the frame count.

    The layout is the stereo image-folder layout that ``replay:`` reads (pairs by file order, ``fps``).
    truth.json ("edgecal-synth-robot/1") holds the rig, the target in the robot frame and, per frame,
    stamp_ns, T_rig_robot (R, t in mm and m, quaternion x,y,z,w) and each side's visible corners.
    """
    out = Path(out_dir)
    refuse_existing([out / "truth.json", out / "left", out / "right"], force)
    entries = []
    unsynced: list[Path] = []
    for fr in frames:
        name = f"{fr.index:06d}.png"
        for side, view in (("left", fr.left), ("right", fr.right)):
            write_atomic(out / side / name, png_bytes(view.image), durable=False)
            unsynced.append(out / side / name)
        entries.append({
            "index": fr.index, "stamp_ns": fr.stamp_ns, "left": f"left/{name}", "right": f"right/{name}",
            "R_rig_robot": fr.R_rig_robot.tolist(), "t_rig_robot_mm": fr.t_rig_robot_mm.tolist(),
            "t_rig_robot_m": (fr.t_rig_robot_mm / 1000.0).tolist(), "q_rig_robot_xyzw": _quat_xyzw(fr.R_rig_robot),
            "boards_left": fr.left.truth["boards"], "boards_right": fr.right.truth["boards"],
        })
    doc = {
        "format": ROBOT_FORMAT,
        "units": {"length": "mm (and _m where named)", "time": "ns"},
        "fps": fps,
        "rig": rig.as_json(),
        "target": {"name": target.name, "frame": "robot", "boards": [
            {"name": b.name, "cols": b.cols, "rows": b.rows, "square_mm": b.square_mm,
             "origin_mm": b.origin_mm.tolist(), "x_axis": b.x_axis.tolist(), "y_axis": b.y_axis.tolist()}
            for b in target.boards]},
        "convention": "X_rig = R_rig_robot @ X_robot + t_rig_robot_mm; rig = left camera frame",
        "frames": entries,
    }
    sync_paths(unsynced)  # truth.json never lists a frame that is not on the disk
    write_atomic(out / "truth.json", json_bytes(doc))
    # An overwritten (--force) longer sequence must not leave frames behind: replay reads every file.
    written = {f"{e['index']:06d}.png" for e in entries}
    for side in ("left", "right"):
        for old in (out / side).glob("[0-9][0-9][0-9][0-9][0-9][0-9].png"):
            if old.name not in written:
                old.unlink()
    return len(entries)
