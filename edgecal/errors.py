"""Errors that the CLI turns into one clear line and a non-zero exit.

Every error a user can cause (a missing file, an unreadable image, a wrong config field, a camera
that is absent or unplugs) is raised as an :class:`EdgecalError` whose message names the thing and
says what to do. The CLI prints ``edgecal: error: <message>`` and exits with ``exit_code``; it never
shows a traceback for these.

A device's errors are split by what the caller does next: :class:`DeviceAbsent` (it cannot be opened:
retry later), :class:`DeviceTimeout` (open, but no frame in time: wait a little longer) and
:class:`DeviceLost` (it was there and is gone: close and reopen). ``except DeviceError`` catches all
three. Misusing a Source in code (``read()`` before ``open()``) is a RuntimeError: a bug, not an
error of the user's.
"""

from __future__ import annotations

import reprlib


class EdgecalError(Exception):
    """Base class of all user-facing errors; ``exit_code`` is what the CLI returns."""

    exit_code: int = 2


class InputError(EdgecalError):
    """A file or image given by the user is missing, unreadable or of the wrong kind."""


class ConfigError(EdgecalError):
    """A YAML config or target file has a missing or wrong field."""


class DeviceError(EdgecalError):
    """A camera is absent, cannot be opened, stops sending or unplugs (or refuses a setting)."""

    exit_code = 3


class DeviceAbsent(DeviceError):
    """A camera (or the library its driver needs) is not there, or cannot be opened now (busy, no permission)."""


class DeviceTimeout(DeviceError):
    """An open camera delivered no frame within the read timeout (it may only be slow, or wait for a trigger)."""


class DeviceLost(DeviceError):
    """An open camera is gone: unplugged, powered off, its device stopped, or its capture thread died."""


class PublishError(EdgecalError):
    """An output cannot start: the pose stream's socket cannot be bound, the Foxglove port is taken."""

    exit_code = 3


class CalibrationRejected(EdgecalError):
    """A calibration whose residual or uncertainty is outside the configured bounds."""

    exit_code = 4


# How many characters of an offending value a message quotes: enough to recognise it, never a flood
# (a 324-byte YAML alias bomb expands to a 39 MB repr).
QUOTE_MAX_CHARS = 80
# The longest message kept for later (e.g. the reason of a failed reload, repeated in every status message).
MESSAGE_MAX_CHARS = 400


def _short_repr() -> reprlib.Repr:
    r = reprlib.Repr()
    # Bounded at every level, so that building the text costs little whatever the value's size or depth.
    r.maxlevel, r.maxlist, r.maxtuple, r.maxdict, r.maxset = 3, 6, 6, 4, 6
    r.maxstring = r.maxother = r.maxlong = QUOTE_MAX_CHARS
    return r


_SHORT = _short_repr()


def quote(value: object) -> str:
    """``repr(value)`` for a message, at most QUOTE_MAX_CHARS characters (long or deep values elided with ...)."""
    if isinstance(value, (bytes, bytearray)) and len(value) > QUOTE_MAX_CHARS:
        value = bytes(value[:QUOTE_MAX_CHARS])     # reprlib would build the whole repr of bytes first
    try:
        text = _SHORT.repr(value)
    except Exception:  # noqa: BLE001 - e.g. an int too long for repr(): name its type instead
        text = f"<{type(value).__name__}>"
    return text if len(text) <= QUOTE_MAX_CHARS else text[: QUOTE_MAX_CHARS - 3] + "..."


def clip(text: str, limit: int = MESSAGE_MAX_CHARS) -> str:
    """``text`` cut to ``limit`` characters (with ... at the end when cut)."""
    return text if len(text) <= limit else text[: limit - 3] + "..."


def exception_summary(exc: BaseException) -> str:
    """One short line for an unexpected exception: its type and the last line of its text (OpenCV's are long)."""
    lines = str(exc).strip().splitlines()
    # OpenCV's text is "OpenCV(5.0.0) /path/file.cpp:123: error: (-215:Assertion failed) what": keep "what"
    last = lines[-1].rsplit(" error: ", 1)[-1].strip() if lines else ""
    return clip(f"{type(exc).__name__}: {last}" if last else type(exc).__name__, QUOTE_MAX_CHARS)
