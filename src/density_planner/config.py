"""Typed configuration: frozen dataclasses built from TOML files, dictionaries and ``key=value`` overrides.

Each component owns a frozen dataclass (``LiouvilleConfig``, ``DensityPlannerConfig``, ...) whose field defaults
come from the specification and whose ``__post_init__`` validates values. This module only converts between
those dataclasses and plain data:

* :func:`from_dict` builds a dataclass from a (nested) mapping, rejecting unknown keys with the list of valid ones;
* :func:`update` returns a copy of a dataclass with some (nested) fields replaced;
* :func:`apply_overrides` applies ``section.key=value`` strings (values parsed as TOML literals);
* :func:`load_config` reads a TOML file into a dataclass;
* :func:`to_dict` / :func:`dumps_toml` write the effective configuration next to results.

Library functions receive these objects (or explicit arguments); only the CLI parses files and flags.
"""

from __future__ import annotations

import dataclasses
import sys
import types
import typing
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Literal, TypeVar, Union, cast, get_args, get_origin

from .errors import ConfigError

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

T = TypeVar("T")

__all__ = ["from_dict", "update", "apply_overrides", "load_config", "to_dict", "dumps_toml", "parse_value"]


def _is_dataclass_type(tp: Any) -> bool:
    return isinstance(tp, type) and dataclasses.is_dataclass(tp)


def _type_name(tp: Any) -> str:
    return getattr(tp, "__name__", None) or str(tp).replace("typing.", "")


def _coerce(tp: Any, value: Any, where: str) -> Any:
    """Convert ``value`` to the annotated type ``tp`` or raise a :class:`ConfigError` naming ``where``."""
    origin = get_origin(tp)
    if tp is Any:
        return value
    if origin is Union or (hasattr(types, "UnionType") and isinstance(tp, types.UnionType)):
        args = get_args(tp)
        if value is None and type(None) in args:
            return None
        errors = []
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _coerce(arg, value, where)
            except ConfigError as exc:
                errors.append(str(exc))
        raise ConfigError(f"{where}: {value!r} does not match {_type_name(tp)}")
    if origin is Literal:
        choices = get_args(tp)
        if value not in choices:
            raise ConfigError(f"{where}: {value!r} is not one of {list(choices)}")
        return value
    if origin in (tuple, Sequence, list):
        if isinstance(value, (str, bytes)) or not isinstance(value, Sequence):
            raise ConfigError(f"{where}: expected a list, got {value!r}")
        args = get_args(tp)
        if origin is tuple and args and args[-1] is not Ellipsis:
            if len(args) != len(value):
                raise ConfigError(f"{where}: expected {len(args)} values, got {len(value)}")
            items = [_coerce(a, v, f"{where}[{i}]") for i, (a, v) in enumerate(zip(args, value))]
        else:
            inner = args[0] if args else Any
            items = [_coerce(inner, v, f"{where}[{i}]") for i, v in enumerate(value)]
        return tuple(items) if origin is not list else items
    if _is_dataclass_type(tp):
        if isinstance(value, tp):
            return value
        if not isinstance(value, Mapping):
            raise ConfigError(f"{where}: expected a table of {tp.__name__} keys, got {value!r}")
        return from_dict(tp, value, where=where)
    if tp is bool:
        if isinstance(value, bool):
            return value
        raise ConfigError(f"{where}: expected true or false, got {value!r}")
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            if isinstance(value, float) and value.is_integer():
                return int(value)
            raise ConfigError(f"{where}: expected an integer, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{where}: expected a number, got {value!r}")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where}: expected a string, got {value!r}")
        return value
    if tp is Path:
        if not isinstance(value, (str, Path)):
            raise ConfigError(f"{where}: expected a path, got {value!r}")
        return Path(value)
    return value


def _fields(cls: type) -> dict[str, Any]:
    hints = typing.get_type_hints(cls)
    return {f.name: hints[f.name] for f in dataclasses.fields(cls) if f.init}


def from_dict(cls: type[T], data: Mapping[str, Any], *, where: str | None = None) -> T:
    """Build the dataclass ``cls`` from a mapping; nested tables build nested dataclasses.

    Unknown keys raise :class:`ConfigError` listing the valid keys; values are type-checked against the
    annotations (ints are accepted for floats, lists for tuples). Missing keys keep their defaults.
    """
    where = where or cls.__name__
    if not isinstance(data, Mapping):
        raise ConfigError(f"{where}: expected a table of keys, got {data!r}")
    valid = _fields(cls)
    unknown = sorted(set(data) - set(valid))
    if unknown:
        raise ConfigError(f"unknown key(s) {unknown} in [{where}]; valid keys: {sorted(valid)}")
    kwargs = {name: _coerce(valid[name], value, f"{where}.{name}") for name, value in data.items()}
    try:
        return cls(**kwargs)
    except ConfigError:
        raise
    except (ValueError, TypeError) as exc:
        raise ConfigError(f"[{where}]: {exc}") from exc


def update(cfg: T, data: Mapping[str, Any], *, where: str | None = None) -> T:
    """Return a copy of ``cfg`` with the (possibly nested) fields in ``data`` replaced."""
    cls = type(cfg)
    where = where or cls.__name__
    valid = _fields(cls)
    unknown = sorted(set(data) - set(valid))
    if unknown:
        raise ConfigError(f"unknown key(s) {unknown} in [{where}]; valid keys: {sorted(valid)}")
    changes: dict[str, Any] = {}
    for name, value in data.items():
        tp = valid[name]
        current = getattr(cfg, name)
        if dataclasses.is_dataclass(current) and isinstance(value, Mapping):
            changes[name] = update(current, value, where=f"{where}.{name}")
        else:
            changes[name] = _coerce(tp, value, f"{where}.{name}")
    try:
        return dataclasses.replace(cast(Any, cfg), **changes)  # a dataclass instance: _fields(cls) read its fields
    except ConfigError:
        raise
    except (ValueError, TypeError) as exc:
        raise ConfigError(f"[{where}]: {exc}") from exc


def parse_value(text: str) -> Any:
    """Parse an override value as a TOML literal (``3``, ``1e-2``, ``true``, ``[1, 2]``, ``"rk4"``).

    Bare words that are not TOML literals are taken as strings, so ``integrator=rk4`` works.
    """
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text


def apply_overrides(cfg: T, overrides: Sequence[str]) -> T:
    """Apply ``dotted.key=value`` strings (as given to ``--set``) to a configuration dataclass."""
    for item in overrides:
        if "=" not in item:
            raise ConfigError(f"--set expects key=value, got {item!r}")
        key, text = item.split("=", 1)
        parts = [p for p in key.strip().split(".") if p]
        if not parts:
            raise ConfigError(f"--set expects key=value, got {item!r}")
        nested: Any = parse_value(text.strip())
        for part in reversed(parts):
            nested = {part: nested}
        cfg = update(cfg, nested)
    return cfg


#: folder of the named configurations shipped with the package (``--config paper``)
PRESETS = Path(__file__).parent / "data" / "presets"


def presets() -> list[str]:
    """Names of the shipped configurations (``--config NAME``; the TOML files in ``data/presets``)."""
    return sorted(p.stem for p in PRESETS.glob("*.toml"))


def load_config(cls: type[T], path: str | Path | None = None, overrides: Sequence[str] = ()) -> T:
    """Defaults of ``cls``, updated by the TOML file at ``path`` (if given; a bare name such as ``"paper"`` that is
    not a file names a shipped preset, :func:`presets`), then by ``overrides``."""
    cfg = cls()
    if path is not None:
        path = Path(path)
        if not path.is_file() and path.suffix == "" and path.parent == Path(".") and str(path) in presets():
            path = PRESETS / f"{path}.toml"
        if not path.is_file():
            raise ConfigError(f"config file not found: {path} (a TOML file, or a shipped preset: "
                              f"{', '.join(presets())})")
        try:
            data = tomllib.loads(path.read_text())
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
            raise ConfigError(f"config file {path} is not valid TOML: {exc}") from exc
        cfg = update(cfg, data, where=f"{path.name}")
    return apply_overrides(cfg, overrides)


def to_dict(cfg: Any) -> Any:
    """Plain nested dict/list form of a configuration dataclass (tuples become lists, paths strings)."""
    if dataclasses.is_dataclass(cfg) and not isinstance(cfg, type):
        return {f.name: to_dict(getattr(cfg, f.name)) for f in dataclasses.fields(cfg) if f.init}
    if isinstance(cfg, (list, tuple)):
        return [to_dict(v) for v in cfg]
    if isinstance(cfg, Mapping):
        return {str(k): to_dict(v) for k, v in cfg.items()}
    if isinstance(cfg, Path):
        return str(cfg)
    return cfg


def _toml_scalar(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        if isinstance(value, float) and value != value:
            return "nan"
        if isinstance(value, float) and value in (float("inf"), float("-inf")):
            return "inf" if value > 0 else "-inf"
        return repr(value)
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(value, list):
        return "[" + ", ".join(_toml_scalar(v) for v in value) + "]"
    raise ConfigError(f"cannot write {value!r} to TOML")


def dumps_toml(cfg: Any) -> str:
    """Serialise a configuration (dataclass or nested dict) to TOML text; ``None`` values are omitted."""
    data = to_dict(cfg)
    lines: list[str] = []

    def emit(table: Mapping[str, Any], prefix: str) -> None:
        scalars = {k: v for k, v in table.items() if not isinstance(v, Mapping) and v is not None}
        tables = {k: v for k, v in table.items() if isinstance(v, Mapping)}
        if prefix and scalars:
            lines.append(f"[{prefix}]")
        for k, v in scalars.items():
            lines.append(f"{k} = {_toml_scalar(v)}")
        if scalars:
            lines.append("")
        for k, v in tables.items():
            emit(v, f"{prefix}.{k}" if prefix else k)

    emit(data, "")
    return "\n".join(lines).rstrip() + "\n"
