"""Stage configs: documented dataclass fields, and the resolved config saved beside each output.

Config fields carry their help text in ``option(help=...)`` (``field(metadata={"help": ...})``); the CLI
turns it into ``--help`` and :func:`save_config` writes the resolved values as plain JSON that
:func:`load_config` reads back (unknown fields are an error).
"""

from __future__ import annotations

import dataclasses
import math
import os
import typing
from pathlib import Path
from typing import Any, TypeVar

from .errors import ConfigError
from .outputs import read_json, write_json_atomic

T = TypeVar("T")


def option(default: Any = dataclasses.MISSING, help: str = "", *, choices: tuple | None = None,
           default_factory: Any = dataclasses.MISSING, cli: bool = True, min: float | None = None,
           max: float | None = None, also: tuple = (), flat: bool = False) -> Any:
    """A dataclass field with help text, optional choices and an optional range [min, max] (``also``: values
    allowed outside it, such as 0 for "automatic"), used by the CLI (checked as the command line is
    parsed), the docs and :func:`check_config`. ``flat``: a nested config whose options the CLI spells
    without this field's name (``--max-iterations``, not ``--fit.max-iterations``)."""
    meta = {"help": help, "choices": choices, "cli": cli, "min": min, "max": max, "also": tuple(also), "flat": flat}
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
            values = v if isinstance(v, (list, tuple)) else (v,)
            for x in values:
                check_range(name, x, lo, hi, meta.get("also", ()))


def check_range(name: str, v: Any, lo: float | None, hi: float | None, also: tuple = ()) -> None:
    """ConfigError unless ``v`` is a finite number in [lo, hi] (either end open when None) or one of ``also``;
    NaN and Inf are never in range (no option means anything by them)."""
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise ConfigError(f"{name} must be a number, got {v!r}", fix="give a number")
    if v in also:
        return
    if (lo is not None and v < lo) or (hi is not None and v > hi) or not math.isfinite(v):
        span = range_text(lo, hi, also)
        raise ConfigError(f"{name} {v} is out of range {span}", fix=f"give a value in {span}")


def range_text(lo: float | None, hi: float | None, also: tuple = ()) -> str:
    """``[8, 16384] (or 0)``: a range as the errors and ``--help`` print it."""
    extra = f" (or {', '.join(map(str, also))})" if also else ""
    return f"[{'-inf' if lo is None else lo}, {'inf' if hi is None else hi}]{extra}"


class Number:
    """An argparse ``type=`` that converts to ``kind`` and checks the range at parse time, so a bad value
    fails before any work with the one-line ConfigError :func:`check_config` gives (the CLI prints it).
    Plain options of the commands use it as ``type=Number(int, "--renders", min=0)``; config fields get it
    from their ``option(min=, max=)``. ``min`` and ``max`` stay readable for the docs and the tests."""

    def __init__(self, kind: type, name: str, min: float | None = None, max: float | None = None,
                 also: tuple = ()):
        self.kind, self.name, self.min, self.max, self.also = kind, name, min, max, tuple(also)
        self.__name__ = kind.__name__  # argparse names the type in "invalid int value" messages

    @classmethod
    def of(cls, config: type, field: str, name: str) -> "Number":
        """The parse-time check of a config field's ``option`` range, for a command's plain option that
        fills it (``--texture-size`` of FitStageConfig.texture_size): one range, kept by the field."""
        f = next(f for f in dataclasses.fields(config) if f.name == field)
        kind = typing.get_type_hints(config)[field]
        meta = f.metadata or {}
        return cls(int if kind is int else float, name, meta.get("min"), meta.get("max"), meta.get("also", ()))

    def span(self) -> str:
        return f"range {range_text(self.min, self.max, self.also)}"

    def __call__(self, text: str) -> Any:
        try:
            v = self.kind(text)
        except ValueError:
            raise ConfigError(f"{self.name} {text!r} is not {'an integer' if self.kind is int else 'a number'}",
                              fix=f"give {'an integer' if self.kind is int else 'a number'}") from None
        check_range(self.name, v, self.min, self.max, self.also)
        return v


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
