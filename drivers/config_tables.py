"""Configuration tables read into typed values: the one place that validates configuration.

The service's TOML file (:mod:`service.config`), the encoder link's and the C-arm's tables
(:mod:`drivers.encoder_link`, :mod:`drivers.kinematics`) are all read here, so every
problem is one :class:`ConfigError` that names the key (``dicom.port: expected an integer,
got 'x'``) and a bool, a string or a fraction is never coerced into a number.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
import types
import typing
from collections.abc import Mapping
from pathlib import Path
from typing import Any

__all__ = ["ConfigError", "build_table", "convert", "check_keys", "config_number"]


class ConfigError(ValueError):
    """A configuration value is missing, unknown, mistyped or out of range."""


def check_keys(table: Mapping, allowed: set[str], where: str) -> None:
    """Refuse keys that ``where`` does not know, naming them and the known ones."""
    unknown = set(table) - allowed
    if unknown:
        raise ConfigError(f"{where}: unknown keys {sorted(unknown)}; allowed: {sorted(allowed)}")


def config_number(value: Any, what: str, integer: bool = False) -> float | int:
    """A number from a configuration table. A bool, a string or a fraction for a count is
    refused rather than coerced (``true`` would become 1, ``100.7`` Hz would become 100)."""
    kind = "int (must be a whole number)" if integer else "float (must be a number)"
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise ConfigError(f"{what} = {value!r} is not of type {kind}")
    number = float(value)
    if not math.isfinite(number):
        raise ConfigError(f"{what} = {value!r} is not finite")
    if integer and number != int(number):
        raise ConfigError(f"{what} = {value!r} is not of type {kind}")
    return int(number) if integer else number


def convert(value: Any, hint: Any, where: str, base: Path | None = None) -> Any:
    """``value`` as the type ``hint`` says, or :class:`ConfigError` naming ``where``;
    relative paths are taken from ``base`` (the configuration file's folder)."""
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        options = [a for a in typing.get_args(hint) if a is not type(None)]
        if value is None or value == "":
            return None
        return convert(value, options[0], where, base)
    if isinstance(hint, type) and dataclasses.is_dataclass(hint):
        if not isinstance(value, Mapping):
            raise ConfigError(f"{where}: expected a table")
        return build_table(hint, value, where, base)
    if origin is list:
        if not isinstance(value, list):
            raise ConfigError(f"{where}: expected a list")
        (item,) = typing.get_args(hint)
        return [convert(v, item, f"{where}[{i}]", base) for i, v in enumerate(value)]
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where}: expected a list, got {value!r}")
        args = typing.get_args(hint)
        items = args[:1] * len(value) if args[-1:] == (Ellipsis,) else args
        if len(items) != len(value):
            raise ConfigError(f"{where}: expected {len(items)} values, got {len(value)}")
        return tuple(convert(v, t, f"{where}[{i}]", base) for i, (v, t) in enumerate(zip(value, items)))
    if hint is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{where}: expected true or false, got {value!r}")
        return value
    if hint is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where}: expected an integer, got {value!r}")
        return value
    if hint is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{where}: expected a number, got {value!r}")
        return float(value)
    if hint is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where}: expected a string, got {value!r}")
        return value
    if hint is dict:
        if not isinstance(value, Mapping):
            raise ConfigError(f"{where}: expected a table")
        return dict(value)
    if hint is Path:
        if not isinstance(value, (str, Path)):
            raise ConfigError(f"{where}: expected a path, got {value!r}")
        path = Path(value).expanduser()
        return path if path.is_absolute() or base is None else base / path
    raise ConfigError(f"{where}: unsupported type {hint}")  # a programming error, named


def build_table(cls: type, table: Mapping[str, Any], where: str, base: Path | None = None) -> Any:
    """An instance of the dataclass ``cls`` from a configuration table: every key declared by
    a typed field, every value converted (:func:`convert`); the class checks ranges."""
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls) if f.name != "source"}
    unknown = sorted(set(table) - names)
    if unknown:
        prefix = f"{where}." if where else ""
        raise ConfigError(f"{prefix}{unknown[0]}: unknown key (known: {', '.join(sorted(names))})")
    kwargs = {key: convert(value, hints[key], f"{where}.{key}" if where else key, base)
              for key, value in table.items()}
    return cls(**kwargs)
