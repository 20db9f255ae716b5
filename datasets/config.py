"""The one configuration loader: typed frozen dataclasses <-> plain YAML/TOML mappings.

Every module of satpose has its own frozen, keyword-only config dataclass; they nest into one
pipeline config. ``load_config`` reads a YAML or TOML file, rejects unknown keys (naming the key
path), fills missing keys with the dataclass defaults and converts values to the annotated types
(enums are written by name, tuples as lists). ``to_plain`` is the inverse used to write the
resolved config next to every output.
"""

from __future__ import annotations

import dataclasses
import enum
import tomllib
import types
import typing
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import yaml

from satpose.datasets.errors import ConfigError, shown

T = TypeVar("T")


def to_plain(obj: Any) -> Any:
    """Convert a config object to YAML-safe Python data (dicts, lists, str, int, float, bool)."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: to_plain(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, enum.Enum):
        return obj.name
    if isinstance(obj, dict):
        return {str(k): to_plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_plain(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return to_plain(obj.tolist())
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    return obj


def yaml_problem(exc: yaml.YAMLError) -> str:
    """What a PyYAML error says, with where: ``"line 7, column 12: expected ',' or ']', but
    got '<stream end>' (while parsing a flow sequence)"`` (1-based line and column, as
    editors count; PyYAML's ``problem_mark`` is 0-based)."""
    mark = getattr(exc, "problem_mark", None)
    text = str(exc).strip()
    problem = getattr(exc, "problem", None) or (text.splitlines()[0] if text else "parse error")
    context = getattr(exc, "context", None)
    what = f"{problem} ({context})" if context else str(problem)
    if mark is None:
        return what
    return f"line {mark.line + 1}, column {mark.column + 1}: {what}"


def from_plain(cls: type[T], data: Any, where: str = "") -> T:
    """Build the dataclass ``cls`` from a mapping, recursively.

    Args:
        cls: a dataclass type whose fields all have defaults or are present in ``data``.
        data: a mapping (e.g. parsed YAML). ``None`` means "all defaults".
        where: key path prefix used in error messages.

    Raises:
        ConfigError: unknown key, missing required key, or a value of the wrong type.
    """
    return typing.cast(T, _convert(cls, {} if data is None else data, where or cls.__name__))


def load_config(cls: type[T], path: str | Path) -> T:
    """Read a YAML (``.yaml``/``.yml``) or TOML (``.toml``) file into the dataclass ``cls``."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"{p}: cannot read config file ({exc.strerror or exc})") from None
    try:
        data = tomllib.loads(text) if p.suffix == ".toml" else yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ConfigError(f"{p}: not valid YAML: {yaml_problem(exc)}") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{p}: not valid TOML: {str(exc).splitlines()[0]}") from None
    try:
        return from_plain(cls, data)
    except ConfigError as exc:
        raise ConfigError(f"{p}: {exc}") from None


def replace_nested(obj: T, overrides: dict[str, Any]) -> T:
    """Return a copy of a config dataclass with nested fields overridden from a plain mapping.

    ``overrides`` has the same shape as the YAML form (unknown keys are rejected).
    """
    merged = _deep_merge(to_plain(obj), overrides)
    return from_plain(type(obj), merged)


def _deep_merge(base: dict[str, Any], extra: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for key, value in extra.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _deep_merge(out[key], value)
        else:
            out[key] = value
    return out


def _convert(tp: Any, value: Any, where: str) -> Any:
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if tp is Any:
        return value
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        errors = []
        for arg in (a for a in args if a is not type(None)):
            try:
                return _convert(arg, value, where)
            except ConfigError as exc:
                errors.append(str(exc))
        raise ConfigError(
            errors[0] if len(errors) == 1 else f"{where}: no accepted type matches {shown(value)}"
        )
    if origin is typing.Literal:
        if value not in args:
            raise ConfigError(f"{where}: must be one of {list(args)}, got {shown(value)}")
        return value
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, dict):
            raise ConfigError(f"{where}: expected a mapping, got {type(value).__name__}")
        hints = typing.get_type_hints(tp)
        fields = {f.name: f for f in dataclasses.fields(tp) if f.init}
        unknown = sorted(set(value) - set(fields))
        if unknown:
            raise ConfigError(f"{where}: unknown key(s) {unknown}; known keys: {sorted(fields)}")
        kwargs = {}
        for name, f in fields.items():
            if name in value:
                kwargs[name] = _convert(hints[name], value[name], f"{where}.{name}")
            elif f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                raise ConfigError(f"{where}.{name}: required key is missing")
        try:
            return typing.cast(Any, tp)(**kwargs)
        except ConfigError:
            raise
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"{where}: {exc}") from None
    if isinstance(tp, type) and issubclass(tp, enum.Enum):
        if isinstance(value, tp):
            return value
        try:
            return tp[str(value)]
        except KeyError:
            raise ConfigError(
                f"{where}: must be one of {[m.name for m in tp]}, got {shown(value)}"
            ) from None
    if origin in (tuple, list):
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where}: expected a list, got {shown(value)}")
        if origin is tuple and args and args[-1] is not Ellipsis:
            if len(value) != len(args):
                raise ConfigError(f"{where}: expected {len(args)} values, got {len(value)}")
            return tuple(
                _convert(a, v, f"{where}[{i}]")
                for i, (a, v) in enumerate(zip(args, value, strict=True))
            )
        item = args[0] if args else Any
        items = [_convert(item, v, f"{where}[{i}]") for i, v in enumerate(value)]
        return tuple(items) if origin is tuple else items
    if origin is dict:
        if not isinstance(value, dict):
            raise ConfigError(f"{where}: expected a mapping, got {shown(value)}")
        kt, vt = args if args else (Any, Any)
        return {_convert(kt, k, where): _convert(vt, v, f"{where}.{k}") for k, v in value.items()}
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{where}: expected true or false, got {shown(value)}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
            raise ConfigError(f"{where}: expected an integer, got {shown(value)}")
        return int(value)
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float, np.number)):
            raise ConfigError(f"{where}: expected a number, got {shown(value)}")
        out = float(value)
        if not np.isfinite(out):
            raise ConfigError(f"{where}: must be finite, got {shown(value)}")
        return out
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where}: expected a string, got {shown(value)}")
        return value
    if tp is Path:
        return Path(value)
    raise ConfigError(f"{where}: unsupported config type {tp!r}")
