"""The live pose loop (``edgecal run``): source -> detect -> pose -> publish, with systemd integration."""

from edgecal.stream.config import LiveConfig, load_live_config
from edgecal.stream.loop import LiveLoop
from edgecal.stream.notify import SystemdNotifier
from edgecal.stream.stats import LoopStats

__all__ = ["LiveConfig", "LiveLoop", "LoopStats", "SystemdNotifier", "load_live_config"]
