"""Errors that the CLI turns into one clear line and a non-zero exit.

Every error a user can cause (a missing file, an unreadable image, a wrong config field, a camera
that is absent or unplugs) is raised as an :class:`EdgecalError` whose message names the thing and
says what to do. The CLI prints ``edgecal: error: <message>`` and exits with ``exit_code``; it never
shows a traceback for these.
"""

from __future__ import annotations


class EdgecalError(Exception):
    """Base class of all user-facing errors; ``exit_code`` is what the CLI returns."""

    exit_code: int = 2


class InputError(EdgecalError):
    """A file or image given by the user is missing, unreadable or of the wrong kind."""


class ConfigError(EdgecalError):
    """A YAML config or target file has a missing or wrong field."""


class DeviceError(EdgecalError):
    """A camera is absent, cannot be opened, stops sending or unplugs."""

    exit_code = 3


class CalibrationRejected(EdgecalError):
    """A calibration whose residual or uncertainty is outside the configured bounds."""

    exit_code = 4
