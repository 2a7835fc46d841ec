"""Reading YAML config files with validation that names the offending field.

Config files are plain YAML mappings. :class:`ConfigReader` walks one and checks each field as it is
read, so that every mistake is reported as ``FILE: field 'a.b[2].c' <what is wrong>`` and the caller
never sees a KeyError or a TypeError. Unknown fields are rejected too: a typo must not silently fall
back to a default.
"""

from __future__ import annotations

import importlib.resources
import math
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import yaml

from edgecal.errors import QUOTE_MAX_CHARS, ConfigError, clip, quote
from edgecal.fileio import read_input

_MISSING = object()
MAX_CONFIG_BYTES = 16 << 20
# libyaml's safe loader where PyYAML was built with it: the same documents, ~10x faster (a daemon reloads
# its config, and a robot's target file has hundreds of nodes).
SAFE_LOADER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)


def packaged_config_path(name: str) -> Path:
    """Path of a YAML file shipped in configs/ (installed as the package ``edgecal.configs``)."""
    return Path(str(importlib.resources.files("edgecal.configs").joinpath(name)))


def load_yaml_mapping(path: str | Path) -> dict[str, Any]:
    """Load a YAML file whose top level must be a mapping; raise ConfigError naming the file otherwise."""
    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"{p}: config file not found (check the path)")
    # "permission denied" named as such, not as unreadable; a config is a few KB, never megabytes
    text = read_input(p, "config file", max_bytes=MAX_CONFIG_BYTES)
    try:
        data = yaml.load(text.decode("utf-8"), Loader=SAFE_LOADER)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}" if mark is not None else ""
        problem = clip(str(getattr(exc, "problem", None) or exc), QUOTE_MAX_CHARS)
        raise ConfigError(f"{p}: not valid YAML{where}: {problem}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{p}: cannot read config file ({clip(str(exc), QUOTE_MAX_CHARS)})") from None
    except (ValueError, RecursionError) as exc:
        # What PyYAML's constructors let through: an integer too long for int(), nesting deeper than the stack.
        raise ConfigError(f"{p}: not valid YAML: {clip(str(exc) or type(exc).__name__, QUOTE_MAX_CHARS)}") from None
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"{p}: the top level must be a mapping of field: value")
    return data


class ConfigReader:
    """Typed, validated access to one mapping of a config file.

    ``source`` names the file (or the command-line option) in messages; ``prefix`` is the dotted path
    of this mapping inside it.
    """

    def __init__(self, data: Mapping[str, Any], source: str, prefix: str = "") -> None:
        if not isinstance(data, Mapping):
            where = f"field '{prefix}'" if prefix else "the top level"
            raise ConfigError(f"{source}: {where} must be a mapping of field: value")
        self.data = data
        self.source = source
        self.prefix = prefix

    def path(self, key: str | int) -> str:
        """The dotted path of ``key`` for messages, e.g. ``boards[1].square_mm``."""
        if isinstance(key, int):
            return f"{self.prefix}[{key}]"
        key = key if len(key) <= QUOTE_MAX_CHARS else quote(key)    # a key can be as long as a value
        return f"{self.prefix}.{key}" if self.prefix else key

    def fail(self, key: str | int, what: str) -> ConfigError:
        """A ConfigError for ``key`` saying ``what`` is wrong."""
        return ConfigError(f"{self.source}: field '{self.path(key)}' {what}")

    def has(self, key: str) -> bool:
        """Whether ``key`` is present."""
        return key in self.data

    def reject_unknown(self, allowed: Sequence[str]) -> None:
        """Raise for any field not in ``allowed`` (a typo must not fall back to a default)."""
        for key in self.data:
            if key not in allowed:
                raise self.fail(str(key), f"is not a known field (known: {', '.join(allowed)})")

    def raw(self, key: str, default: Any = _MISSING) -> Any:
        """The value of ``key`` unchecked; raise if it is missing and has no default."""
        if key not in self.data or self.data[key] is None:
            if default is _MISSING:
                raise self.fail(key, "is missing")
            return default
        return self.data[key]

    def number(self, key: str, default: Any = _MISSING, *, minimum: float | None = None,
               maximum: float | None = None, positive: bool = False) -> float:
        """A finite real number, optionally bounded."""
        value = self.raw(key, default)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise self.fail(key, f"must be a number (got {quote(value)})")
        if positive and value <= 0:
            raise self.fail(key, f"must be greater than 0 (got {quote(value)})")
        if minimum is not None and value < minimum:
            raise self.fail(key, f"must be at least {minimum} (got {quote(value)})")
        if maximum is not None and value > maximum:
            raise self.fail(key, f"must be at most {maximum} (got {quote(value)})")
        return float(value)

    def integer(self, key: str, default: Any = _MISSING, *, minimum: int | None = None,
                maximum: int | None = None) -> int:
        """An integer, optionally bounded."""
        value = self.raw(key, default)
        if isinstance(value, bool) or not isinstance(value, int):
            raise self.fail(key, f"must be a whole number (got {quote(value)})")
        if minimum is not None and value < minimum:
            raise self.fail(key, f"must be at least {minimum} (got {quote(value)})")
        if maximum is not None and value > maximum:
            raise self.fail(key, f"must be at most {maximum} (got {quote(value)})")
        return int(value)

    def boolean(self, key: str, default: Any = _MISSING) -> bool:
        """A YAML boolean (true/false)."""
        value = self.raw(key, default)
        if not isinstance(value, bool):
            raise self.fail(key, f"must be true or false (got {quote(value)})")
        return value

    def string(self, key: str, default: Any = _MISSING, *, choices: Sequence[str] | None = None) -> str:
        """A string, optionally one of ``choices``."""
        value = self.raw(key, default)
        if not isinstance(value, str) or not value:
            raise self.fail(key, f"must be a non-empty string (got {quote(value)})")
        if choices is not None and value not in choices:
            raise self.fail(key, f"must be one of {', '.join(choices)} (got {quote(value)})")
        return value

    def vector(self, key: str, length: int, default: Any = _MISSING, *,
               check: Callable[[list[float]], str | None] | None = None) -> list[float]:
        """A list of ``length`` numbers; ``check`` may return a message for a bad value."""
        value = self.raw(key, default)
        if (not isinstance(value, (list, tuple)) or len(value) != length
                or any(isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v)
                       for v in value)):
            raise self.fail(key, f"must be a list of {length} numbers (got {quote(value)})")
        out = [float(v) for v in value]
        if check is not None:
            problem = check(out)
            if problem:
                raise self.fail(key, problem)
        return out

    def section(self, key: str, default: Any = _MISSING) -> ConfigReader:
        """The nested mapping at ``key``."""
        value = self.raw(key, default)
        return ConfigReader(value, self.source, self.path(key))

    def sections(self, key: str) -> Iterator[ConfigReader]:
        """Each mapping of the non-empty list at ``key``."""
        value = self.raw(key)
        if not isinstance(value, list) or not value:
            raise self.fail(key, "must be a non-empty list")
        base = self.path(key)
        for i, item in enumerate(value):
            yield ConfigReader(item, self.source, f"{base}[{i}]")
