"""What cameras are attached and which drivers are usable here (``edgecal sources``).

Every driver is asked in its own way and a failure of one never hides the others: a missing library
or permission becomes a line that says why. GigE Vision and DepthAI-over-TCP discovery broadcast on
the network; ``network=False`` skips that (only USB, FireWire, /dev/video* and explicit probes).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field

from edgecal.errors import EdgecalError


@dataclass
class DriverReport:
    """One driver: whether it can be used, why not, and the sources it found."""

    driver: str
    usable: bool
    why: str = ""
    sources: list[dict] = field(default_factory=list)

    def as_json(self) -> dict:
        """Plain JSON form."""
        return {"driver": self.driver, "usable": self.usable, "why": self.why, "sources": self.sources}


def _v4l2() -> DriverReport:
    import cv2

    from edgecal.drivers.v4l2 import list_devices
    if not cv2.videoio_registry.hasBackend(cv2.CAP_V4L2):
        return DriverReport("v4l2", False, "this OpenCV build has no V4L2 backend")
    devices = list_devices()
    why = "" if devices else "no /dev/video* device (no USB/CSI camera attached)"
    return DriverReport("v4l2", True, why, devices)


def _aravis(network: bool, fake: bool) -> DriverReport:
    from edgecal.drivers.aravis import load_aravis
    try:
        Aravis = load_aravis()
    except EdgecalError as exc:
        return DriverReport("aravis", False, str(exc))
    if fake:
        Aravis.enable_interface("Fake")
    if not network:
        Aravis.disable_interface("GigEVision")  # its discovery is a broadcast on every interface
    try:
        Aravis.update_device_list()
    finally:
        # Process-wide switch: opening a camera by IP (a probe) must still work afterwards.
        Aravis.enable_interface("GigEVision")
    found = []
    for i in range(Aravis.get_n_devices()):
        dev_id = Aravis.get_device_id(i)
        protocol = Aravis.get_device_protocol(i)
        address = Aravis.get_device_address(i)
        name = "fake" if protocol == "Fake" else (address if protocol == "GigEVision" and address else dev_id)
        found.append({"uri": f"aravis:{name}", "name": f"{Aravis.get_device_vendor(i)} {Aravis.get_device_model(i)}",
                      "protocol": protocol, "usable": True, "why": ""})
    why = "" if found else ("no camera found" + ("" if network else " on USB3 Vision (GigE Vision not searched)"))
    return DriverReport("aravis", True, why, found)


def _dc1394() -> DriverReport:
    from edgecal.drivers.dc1394 import list_cameras
    try:
        guids = list_cameras()
    except EdgecalError as exc:
        return DriverReport("dc1394", False, str(exc))
    return DriverReport("dc1394", True, "" if guids else "no IEEE-1394 camera on any FireWire bus",
                        [{"uri": f"dc1394:{g:016x}", "name": "IIDC camera", "usable": True, "why": ""} for g in guids])


def _depthai(network: bool) -> DriverReport:
    if not network:
        os.environ["DEPTHAI_PROTOCOL"] = "usb"   # read by depthai when it searches
    os.environ.setdefault("DEPTHAI_SEARCH_TIMEOUT", "1000")
    from edgecal.drivers.oak import load_depthai
    try:
        dai = load_depthai()
    except EdgecalError as exc:
        return DriverReport("depthai", False, str(exc))
    try:
        infos = dai.Device.getAllAvailableDevices()
    except RuntimeError as exc:
        return DriverReport("depthai", True, f"cannot search for devices ({exc})")
    found = [{"uri": f"depthai:{d.getDeviceId()}", "name": d.name, "usable": True, "why": ""} for d in infos]
    return DriverReport("depthai", True, "" if found else "no OAK device found", found)


def probe(uri: str) -> dict:
    """Open ``uri`` and read one frame: ``usable`` and, if not, the error's message."""
    from edgecal.drivers.factory import open_source
    try:
        with open_source(uri) as src:
            item = src.read()
            desc = src.describe()
    except EdgecalError as exc:
        return {"uri": uri, "usable": False, "why": str(exc)}
    frame = getattr(item, "left", item)
    shape = "x".join(str(v) for v in frame.image.shape[1::-1]) if frame is not None else "no frame"
    return {"uri": uri, "name": str(desc.get("device", "")) or desc.get("driver", ""), "usable": frame is not None,
            "why": "" if frame is not None else "the source gave no frame", "size": shape}


def survey(network: bool = True, fake: bool = False) -> list[DriverReport]:
    """Ask every hardware driver what it can see; replay is always usable."""
    reports = [DriverReport("replay", True, "folders of images, video files and edgecal recordings")]
    for ask in (_v4l2, lambda: _aravis(network, fake), _dc1394, lambda: _depthai(network)):
        reports.append(ask())
    return reports
