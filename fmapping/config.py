"""Dataclass configs with YAML overrides (unknown keys are errors, never silently ignored)."""
from __future__ import annotations

import dataclasses
import typing
from pathlib import Path
from typing import Any, Optional, TypeVar

import yaml

T = TypeVar("T")


class ConfigError(ValueError):
    pass


def _is_dataclass_type(tp) -> bool:
    return isinstance(tp, type) and dataclasses.is_dataclass(tp)


def merge(obj: T, updates: dict, where: str = "config") -> T:
    """Return a copy of dataclass ``obj`` with ``updates`` (nested dict) applied."""
    if not isinstance(updates, dict):
        raise ConfigError(f"{where}: expected a mapping, got {type(updates).__name__}")
    hints = typing.get_type_hints(type(obj))
    fields = {f.name for f in dataclasses.fields(obj)}
    changes = {}
    for key, val in updates.items():
        if key not in fields:
            raise ConfigError(f"{where}: unknown key {key!r} (valid: {', '.join(sorted(fields))})")
        cur = getattr(obj, key)
        if dataclasses.is_dataclass(cur) and isinstance(val, dict):
            changes[key] = merge(cur, val, f"{where}.{key}")
        else:
            changes[key] = _coerce(val, hints.get(key), f"{where}.{key}")
    return dataclasses.replace(obj, **changes)


def _coerce(val: Any, tp, where: str) -> Any:
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin is typing.Union and type(None) in args:
        if val is None:
            return None
        tp = next(a for a in args if a is not type(None))
        origin, args = typing.get_origin(tp), typing.get_args(tp)
    if tp is float and isinstance(val, (int, float)) and not isinstance(val, bool):
        return float(val)
    if tp is int and isinstance(val, int) and not isinstance(val, bool):
        return val
    if tp is bool and not isinstance(val, bool):
        raise ConfigError(f"{where}: expected true/false, got {val!r}")
    if tp in (int, float, str) and not isinstance(val, tp):
        raise ConfigError(f"{where}: expected {tp.__name__}, got {val!r}")
    if (tp is tuple or origin is tuple) and isinstance(val, (list, tuple)):
        # YAML has only lists: give a tuple field tuples again (nested too, e.g. init_rounds),
        # so a dumped default loads back equal to the default
        return _tuples(val)
    if origin is list and isinstance(val, (list, tuple)):
        return list(val)
    return val


def _tuples(val: Any) -> Any:
    return tuple(_tuples(v) for v in val) if isinstance(val, (list, tuple)) else val


def _plain(val: Any) -> Any:
    """Tuples -> lists, recursively (safe YAML has no tuples)."""
    if isinstance(val, dict):
        return {k: _plain(v) for k, v in val.items()}
    if isinstance(val, (list, tuple)):
        return [_plain(v) for v in val]
    return val


def read_yaml_mapping(path: str | Path) -> dict:
    """The top-level mapping of a YAML file (empty file -> ``{}``); :class:`ConfigError` naming
    the file when it is missing, not YAML, or not a mapping."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"config file not found: {path}")
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as e:
        raise ConfigError(f"{path}: invalid YAML: {e}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping at the top level, got {type(data).__name__}")
    return data


def load_config(default: T, path: Optional[str | Path] = None, overrides: Optional[dict] = None) -> T:
    """``default`` updated by the YAML file at ``path`` and then by ``overrides``."""
    cfg = default
    if path is not None:
        cfg = merge(cfg, read_yaml_mapping(path), str(path))
    if overrides:
        cfg = merge(cfg, overrides, "overrides")
    return cfg


def to_dict(cfg) -> dict:
    return dataclasses.asdict(cfg)


class _Dumper(yaml.SafeDumper):
    """Sections as blocks, lists on one line (``init_rounds: [[0, 32], [3, 64]]``), for reading and editing."""


_Dumper.add_representer(list, lambda d, v: d.represent_sequence("tag:yaml.org,2002:seq", v, flow_style=True))


def to_yaml(cfg) -> str:
    """A config (dataclass or dict) as YAML that :func:`load_config` reads back to an equal config."""
    d = to_dict(cfg) if dataclasses.is_dataclass(cfg) else cfg
    return yaml.dump(_plain(d), Dumper=_Dumper, sort_keys=False, default_flow_style=False)
