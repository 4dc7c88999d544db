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
           default_factory: Any = dataclasses.MISSING, cli: bool = True, min: float | None = None,
           max: float | None = None, flat: bool = False) -> Any:
    """A dataclass field with help text, optional choices and an optional range [min, max], used by
    the CLI, the docs and :func:`check_config`. ``flat``: a nested config whose options the CLI
    spells without this field's name (``--max-iterations``, not ``--fit.max-iterations``)."""
    meta = {"help": help, "choices": choices, "cli": cli, "min": min, "max": max, "flat": flat}
    if default_factory is not dataclasses.MISSING:
        return dataclasses.field(default_factory=default_factory, metadata=meta)
    return dataclasses.field(default=default, metadata=meta)


def check_config(cfg: Any, prefix: str = "") -> None:
    """Check every field of a (nested) config against its choices and range; a ConfigError names the
    option (as the CLI spells it) and the allowed values. Stages call it before any long work, so a
    bad value from a config file or a script fails as clearly as one from the command line."""
    for f in dataclasses.fields(cfg):
        v = getattr(cfg, f.name)
        name = "--" + (prefix + f.name).replace("_", "-")
        if dataclasses.is_dataclass(v):
            check_config(v, prefix if (f.metadata or {}).get("flat") else prefix + f.name + ".")
            continue
        meta = f.metadata or {}
        if meta.get("choices") and v not in meta["choices"] and not (v is None and f.default is None):
            raise ConfigError(f"{name} {v!r} is not one of {list(meta['choices'])}",
                              fix=f"use one of {', '.join(map(str, meta['choices']))}")
        lo, hi = meta.get("min"), meta.get("max")
        if (lo is not None or hi is not None) and v is not None:
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                raise ConfigError(f"{name} must be a number, got {v!r}", fix="give a number")
            if (lo is not None and v < lo) or (hi is not None and v > hi) or v != v:
                span = f"[{'-inf' if lo is None else lo}, {'inf' if hi is None else hi}]"
                raise ConfigError(f"{name} {v} is out of range {span}", fix=f"give a value in {span}")


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
        if t is not None and not dataclasses.is_dataclass(v) and not _of_type(v, t):
            raise ConfigError(f"{f.name} = {v!r} is not {_type_name(t)}", fix=f"write {f.name} as {_type_name(t)}")
        kwargs[f.name] = v
    return cls(**kwargs)


def _of_type(v: Any, t: Any) -> bool:
    """Whether a value read from a config file fits its field's annotation (int for float fields too; NaN
    never: a config file's NaN is a typo, not a setting)."""
    if t is Any or isinstance(t, TypeVar):
        return True
    origin, args = typing.get_origin(t), typing.get_args(t)
    if origin is typing.Union or str(origin) == "<class 'types.UnionType'>":
        return any(_of_type(v, a) for a in args)
    if t is type(None):
        return v is None
    if origin in (tuple, list):
        if not isinstance(v, (tuple, list)):
            return False
        if len(args) == 2 and args[1] is Ellipsis:
            args = (args[0],) * len(v)
        return (not args or len(args) == len(v)) and all(_of_type(x, a) for x, a in zip(v, args))
    if t is float:
        return isinstance(v, (int, float)) and not isinstance(v, bool) and v == v
    if t is int:
        return isinstance(v, int) and not isinstance(v, bool)
    return isinstance(v, t) if isinstance(t, type) else True


def _type_name(t: Any) -> str:
    return {int: "a whole number", float: "a number", str: "a string", bool: "true or false"}.get(t, str(t))


def save_config(cfg: Any, path: str | os.PathLike) -> None:
    """Write the resolved config as JSON (atomically)."""
    write_json_atomic(path, config_to_dict(cfg))


def load_config(cls: type[T], path: str | os.PathLike) -> T:
    """Load a config written by :func:`save_config`."""
    data = read_json(path, what=f"{cls.__name__} config")
    return config_from_dict(cls, data)
