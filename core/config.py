"""Stage configs: documented dataclass fields, and the resolved config saved beside each output.

Config fields carry their help text in ``option(help=...)`` (``field(metadata={"help": ...})``); the CLI
turns it into ``--help`` and :func:`save_config` writes the resolved values as plain JSON that
:func:`load_config` reads back (unknown fields are an error).
"""

from __future__ import annotations

import dataclasses
import os
import typing
from pathlib import Path
from typing import Any, TypeVar

from .errors import ConfigError
from .outputs import read_json, write_json_atomic

T = TypeVar("T")


def option(default: Any = dataclasses.MISSING, help: str = "", *, choices: tuple | None = None,
           default_factory: Any = dataclasses.MISSING, cli: bool = True) -> Any:
    """A dataclass field with help text (and optional choices) used by the CLI and the docs."""
    meta = {"help": help, "choices": choices, "cli": cli}
    if default_factory is not dataclasses.MISSING:
        return dataclasses.field(default_factory=default_factory, metadata=meta)
    return dataclasses.field(default=default, metadata=meta)


def config_to_dict(cfg: Any) -> dict:
    """Plain-data dict of a (nested) dataclass config, with its type name for reloading."""
    def conv(v: Any) -> Any:
        if dataclasses.is_dataclass(v):
            return {f.name: conv(getattr(v, f.name)) for f in dataclasses.fields(v)}
        if isinstance(v, (list, tuple)):
            return [conv(x) for x in v]
        if isinstance(v, dict):
            return {str(k): conv(x) for k, x in v.items()}
        if isinstance(v, Path):
            return str(v)
        return v
    return {"_type": type(cfg).__qualname__, **conv(cfg)}


def config_from_dict(cls: type[T], data: dict) -> T:
    """Rebuild a dataclass config from :func:`config_to_dict` output; unknown keys are an error."""
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = set(data) - names - {"_type"}
    if unknown:
        raise ConfigError(f"unknown {cls.__name__} field(s) {sorted(unknown)}",
                          fix=f"use only {sorted(names)}")
    kwargs = {}
    for f in dataclasses.fields(cls):
        if f.name not in data:
            continue
        v = data[f.name]
        t = hints.get(f.name)
        if dataclasses.is_dataclass(t) and isinstance(v, dict):
            v = config_from_dict(t, v)
        elif typing.get_origin(t) is tuple and isinstance(v, list):
            v = tuple(v)
        kwargs[f.name] = v
    return cls(**kwargs)


def save_config(cfg: Any, path: str | os.PathLike) -> None:
    """Write the resolved config as JSON (atomically)."""
    write_json_atomic(path, config_to_dict(cfg))


def load_config(cls: type[T], path: str | os.PathLike) -> T:
    """Load a config written by :func:`save_config`."""
    data = read_json(path, what=f"{cls.__name__} config")
    return config_from_dict(cls, data)
