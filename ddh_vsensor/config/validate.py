"""Decoded YAML into a :class:`~.schema.Config`: every value converted to its field's type
and checked against its bounds, every error naming the file, the key path and the problem."""

from __future__ import annotations

import dataclasses
import reprlib
import types
import typing
from typing import Any, Literal

from ddh_vsensor.config.errors import ConfigError
from ddh_vsensor.config.schema import Config

_REPR = reprlib.Repr()
_REPR.maxlevel, _REPR.maxstring, _REPR.maxother, _REPR.maxlist, _REPR.maxdict = 2, 60, 60, 4, 4


def _short(value: Any) -> str:
    """A bounded repr for error messages (a value may be a huge or deeply nested YAML)."""
    return _REPR.repr(value)


def _type_name(tp: Any) -> str:
    return getattr(tp, "__name__", str(tp))


def _convert(value: Any, tp: Any, path: str, source: str) -> Any:
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if dataclasses.is_dataclass(tp):
        return _build(tp, value, path, source)
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(source, path, f"expected a number, got {_short(value)}")
        if value != value or value in (float("inf"), float("-inf")):
            raise ConfigError(source, path, f"expected a finite number, got {_short(value)}")
        return float(value)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(source, path, f"expected a whole number, got {_short(value)}")
        return value
    if origin is Literal:
        if value not in args:
            raise ConfigError(source, path, f"{_short(value)} is not one of "
                              f"{', '.join(map(str, args))}")
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(source, path, f"expected true or false, got {_short(value)}")
        return value
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(source, path, f"expected text, got {_short(value)}")
        return value
    if origin is tuple:
        if not isinstance(value, list):
            raise ConfigError(source, path, f"expected a list, got {_short(value)}")
        return tuple(_convert(v, args[0], f"{path}[{i}]", source) for i, v in enumerate(value))
    if origin is dict:
        if not isinstance(value, dict):
            raise ConfigError(source, path, f"expected a mapping, got {_short(value)}")
        key_tp, val_tp = args
        allowed = typing.get_args(key_tp) if typing.get_origin(key_tp) is Literal else None
        out = {}
        for k, v in value.items():
            if allowed is not None and k not in allowed:
                raise ConfigError(source, f"{path}.{_short(k)}", f"unknown key (expected one of "
                                  f"{', '.join(allowed)})")
            out[k] = v if val_tp is Any else _convert(v, val_tp, f"{path}.{k}", source)
        return out
    if tp is Any:
        return value
    if origin in (typing.Union, types.UnionType):  # Optional[...] fields
        if value is None and type(None) in args:
            return None
        inner = [a for a in args if a is not type(None)]
        return _convert(value, inner[0], path, source)
    raise TypeError(f"unsupported config type {_type_name(tp)} at {path}")  # programming error


def _check_bounds(value: Any, meta: typing.Mapping[str, Any], path: str, source: str) -> None:
    bounds = {"gt": (lambda v, b: v > b, "greater than"),
              "ge": (lambda v, b: v >= b, "at least"),
              "lt": (lambda v, b: v < b, "less than"),
              "le": (lambda v, b: v <= b, "at most")}
    for key, (ok, words) in bounds.items():
        if key in meta and not ok(value, meta[key]):
            raise ConfigError(source, path, f"{_short(value)} is not physical here: must be {words} "
                              f"{meta[key]}")


def _build(cls: type, data: Any, path: str, source: str) -> Any:
    if not isinstance(data, dict):
        raise ConfigError(source, path or "(top level)", f"expected a mapping, got {_short(data)}")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if not f.metadata.get("internal")}
    for key in data:
        if key not in fields:
            raise ConfigError(source, f"{path}.{_short(key)}" if path else _short(key),
                              f"unknown key (known: {', '.join(fields)})")
    kwargs = {}
    for name, f in fields.items():
        sub = f"{path}.{name}" if path else name
        if name not in data:
            if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                raise ConfigError(source, sub, "missing key")
            continue
        value = _convert(data[name], hints[name], sub, source)
        if isinstance(value, (int, float)):
            _check_bounds(value, f.metadata, sub, source)
        kwargs[name] = value
    obj = cls(**kwargs)
    if hasattr(obj, "check"):
        problems = obj.check(path or "(top level)")
        if problems:
            raise ConfigError(source, *problems[0])
    return obj


def parse_config(data: Any, source: str = "<memory>") -> Config:
    """Validate a decoded YAML document into a :class:`Config`."""
    cfg = _build(Config, data, "", source)
    return dataclasses.replace(cfg, source=source)

