"""Reading YAML config files with validation that names the offending field.

Config files are plain YAML mappings. Each section is described by a frozen dataclass that sits beside
the code using it; its fields are declared with :func:`setting` (type from the annotation; bounds,
choices and a one-line doc as field metadata) and :func:`read_settings` fills it from a section, so every
section is read the same way. Every mistake is reported as ``FILE: field 'a.b[2].c' <what is wrong>``
and the caller never sees a KeyError or a TypeError. Unknown fields are rejected with the known ones
listed (a typo must not silently fall back to a default), and a renamed field says its new name.

:class:`ConfigReader` is the walker underneath: typed access to one mapping, with the field's path.
"""

from __future__ import annotations

import dataclasses
import functools
import importlib.resources
import math
import types
import typing
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any, TypeVar

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


# ---------------------------------------------------------------------------------------------------------
# Declarative sections: a dataclass whose fields say how to read them.

T = TypeVar("T")
_RULE = "edgecal.config"     # the key of a field's metadata that holds its Rule


@dataclasses.dataclass(frozen=True)
class Rule:
    """How one dataclass field is read from its config section (see :func:`setting`)."""

    doc: str = ""
    minimum: float | None = None
    maximum: float | None = None
    positive: bool = False                       # numbers: strictly greater than 0
    choices: tuple[str, ...] | None = None       # strings: one of these
    synonyms: Mapping[str, str] = dataclasses.field(default_factory=dict)  # accepted value -> stored value
    renamed_from: tuple[str, ...] = ()           # former keys: named as renamed, not as unknown
    inline: bool = False                         # a dataclass whose fields sit in this same section
    read: Callable[[ConfigReader, str], Any] | None = None   # own reader for a value of several forms


def setting(default: Any = dataclasses.MISSING, *, doc: str, default_factory: Any = dataclasses.MISSING,
            minimum: float | None = None, maximum: float | None = None, positive: bool = False,
            choices: Sequence[str] | None = None, synonyms: Mapping[str, str] | None = None,
            renamed_from: Sequence[str] = (), inline: bool = False,
            read: Callable[[ConfigReader, str], Any] | None = None) -> Any:
    """A dataclass field of a config section: its default, a one-line doc, and what a valid value is.

    The type comes from the annotation (bool, int, float, str, a nested settings dataclass, or one of
    these or None). No default makes the field required.
    """
    rule = Rule(doc, minimum, maximum, positive, tuple(choices) if choices is not None else None,
                dict(synonyms or {}), tuple(renamed_from), inline, read)
    return dataclasses.field(default=default, default_factory=default_factory, metadata={_RULE: rule})


@functools.cache
def _field_types(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def _value_type(annotation: Any) -> Any:
    """``X`` for ``X``, ``X | None`` and ``Optional[X]``."""
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(annotation) if a is not type(None)]
        if len(args) == 1:
            return args[0]
    return annotation


def settings_fields(cls: type) -> list[tuple[dataclasses.Field, Rule, Any]]:
    """(field, rule, value type) of every config field of a settings dataclass, in declaration order.

    Only fields declared with :func:`setting` are read from a file; a plain field (a solver's internal
    knob) keeps its default.
    """
    types_ = _field_types(cls)
    return [(f, f.metadata[_RULE], _value_type(types_[f.name])) for f in dataclasses.fields(cls)
            if _RULE in f.metadata]


def section_keys(cls: type) -> tuple[str, ...]:
    """The keys a section of ``cls`` accepts (the fields of inline sub-sections included)."""
    keys: list[str] = []
    for f, rule, kind in settings_fields(cls):
        keys.extend(section_keys(kind) if rule.inline else (f.name,))
    return tuple(keys)


def _renames(cls: type) -> dict[str, str]:
    out: dict[str, str] = {}
    for f, rule, kind in settings_fields(cls):
        if rule.inline:
            out.update(_renames(kind))
        out.update({old: f.name for old in rule.renamed_from})
    return out


def _read_value(r: ConfigReader, key: str, rule: Rule, kind: Any) -> Any:
    if rule.read is not None:
        return rule.read(r, key)
    if kind is bool:
        return r.boolean(key)
    if kind is int:
        return r.integer(key, minimum=None if rule.minimum is None else int(rule.minimum),
                         maximum=None if rule.maximum is None else int(rule.maximum))
    if kind is float:
        return r.number(key, minimum=rule.minimum, maximum=rule.maximum, positive=rule.positive)
    if kind is str:
        value = r.string(key, choices=rule.choices)
        return rule.synonyms.get(value, value)
    if isinstance(kind, type) and dataclasses.is_dataclass(kind):
        return read_settings(kind, r.section(key))
    raise TypeError(f"a settings field of type {kind!r} needs its own reader (setting(read=...))")


def read_settings(cls: type[T], r: ConfigReader, *, base: T | None = None, ignore: Sequence[str] = (),
                  unknown: Callable[[str, tuple[str, ...]], str] | None = None,
                  retired: Mapping[str, str] | None = None) -> T:
    """Fill the settings dataclass ``cls`` from the section ``r``; raise ConfigError naming the field.

    A key that is absent (or null) keeps the value of ``base`` if given, else the field's default; a
    field without a default must be present. ``ignore``: keys of this section that another reader owns.
    ``unknown(key, known)`` words the message for a key that is no field (default: the known ones listed);
    ``retired``: keys this section no longer reads -> what to write instead (a setting that moved elsewhere).
    After reading, a ``config_problem()`` method of the dataclass may return ``(key, what)`` for a rule
    between fields (e.g. a maximum below its minimum).
    """
    known = section_keys(cls)
    renames = _renames(cls)
    for key in r.data:
        name = str(key)
        if name in known or name in ignore:
            continue
        if name in renames:
            raise r.fail(name, f"was renamed to '{renames[name]}' (rename it in the file)")
        if retired and name in retired:
            raise r.fail(name, f"is no longer read here: {retired[name]}")
        raise r.fail(name, unknown(name, known) if unknown is not None
                     else f"is not a known field (known: {', '.join((*known, *ignore))})")
    values: dict[str, Any] = {}
    for f, rule, kind in settings_fields(cls):
        if rule.inline:
            others = tuple(k for k in known if k not in section_keys(kind)) + tuple(ignore)
            values[f.name] = read_settings(kind, r, base=getattr(base, f.name) if base is not None else None,
                                           ignore=others)
        elif r.has(f.name) and (r.data[f.name] is not None or rule.read is not None):
            values[f.name] = _read_value(r, f.name, rule, kind)
        elif base is None and f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            raise r.fail(f.name, "is missing")
    obj: Any = dataclasses.replace(base, **values) if base is not None else cls(**values)  # type: ignore[type-var]
    check = getattr(obj, "config_problem", None)
    problem = check() if check is not None else None
    if problem is not None:
        raise r.fail(*problem)
    return obj


def describe_settings(cls: type, prefix: str = "") -> list[tuple[str, Any, str]]:
    """(dotted key, default, doc) of every field of a section and its sub-sections (docs and tests)."""
    out: list[tuple[str, Any, str]] = []
    for f, rule, kind in settings_fields(cls):
        if isinstance(kind, type) and dataclasses.is_dataclass(kind) and rule.read is None:
            out.extend(describe_settings(kind, prefix if rule.inline else f"{prefix}{f.name}."))
            continue
        default = f.default if f.default is not dataclasses.MISSING else (
            f.default_factory() if f.default_factory is not dataclasses.MISSING else None)
        out.append((f"{prefix}{f.name}", default, rule.doc))
    return out
