"""JSON round trip for the (nested, frozen) config dataclasses.

``config_to_dict`` / ``config_from_dict`` let every trained stage write its config beside its
checkpoints so a model can be rebuilt from the folder alone.
"""

from __future__ import annotations

import dataclasses
import json
import os
import types
import typing
from typing import Any, TypeVar

__all__ = ["config_to_dict", "config_from_dict", "save_config", "load_config"]

T = TypeVar("T")


def config_to_dict(config: Any) -> dict:
    """Nested dataclass -> JSON-compatible dict (tuples become lists)."""
    return dataclasses.asdict(config)


def _convert(tp: Any, value: Any) -> Any:
    if dataclasses.is_dataclass(tp) and isinstance(tp, type):
        return config_from_dict(tp, value)
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        if value is None:
            return None
        return _convert(next(a for a in args if a is not type(None)), value)
    if origin is tuple:
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_convert(args[0], v) for v in value)
        return tuple(_convert(a, v) for a, v in zip(args, value))
    return value


def config_from_dict(cls: type[T], data: dict) -> T:
    """Rebuild dataclass ``cls`` from ``config_to_dict`` output; missing keys keep defaults."""
    hints = typing.get_type_hints(cls)
    kwargs = {
        f.name: _convert(hints[f.name], data[f.name])
        for f in dataclasses.fields(cls)
        if f.name in data
    }
    return cls(**kwargs)


def save_config(config: Any, path: str | os.PathLike, **extra: Any) -> None:
    """Write ``{"config": ..., **extra}`` as indented JSON."""
    with open(path, "w") as f:
        json.dump({"config": config_to_dict(config), **extra}, f, indent=2)


def load_config(cls: type[T], path: str | os.PathLike) -> tuple[T, dict]:
    """Read a file written by ``save_config``. Returns (config, extra fields)."""
    with open(path) as f:
        data = json.load(f)
    config = config_from_dict(cls, data.pop("config"))
    return config, data
