"""Configs as TOML: the resolved config of a run written for people to read and edit, and read back.

Reading uses the standard library's ``tomllib``; writing covers what configs hold (tables of
strings, numbers, booleans and lists of them; ``None`` fields are left out, so reading the file
back gives the field's default, which is ``None`` for every optional field).
"""

from __future__ import annotations

import json
import math
import os
import tomllib
from pathlib import Path
from typing import Any

from .errors import ConfigError, InputError


def _value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if not math.isfinite(v):
            return ("-inf" if v < 0 else "inf") if math.isinf(v) else "nan"
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)  # a TOML basic string is a JSON string for what configs hold
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {type(v).__name__} as TOML")


def dumps(data: dict, header: str = "") -> str:
    """TOML text of a nested dict (sub-dicts become [tables]); ``header`` lines become comments."""
    lines = [f"# {h}" if h else "#" for h in header.splitlines()]

    def table(d: dict, prefix: str) -> None:
        scalars = {k: v for k, v in d.items() if not isinstance(v, dict) and v is not None and not k.startswith("_")}
        if prefix and (scalars or not any(isinstance(v, dict) for v in d.values())):
            lines.append("")
            lines.append(f"[{prefix}]")
        for k, v in scalars.items():
            lines.append(f"{k} = {_value(v)}")
        for k, v in d.items():
            if isinstance(v, dict):
                table(v, f"{prefix}.{k}" if prefix else k)

    table(data, "")
    return "\n".join(lines).lstrip("\n") + "\n"


def read_toml(path: str | os.PathLike) -> dict:
    """Parse a TOML file with a one-line error naming it."""
    p = Path(path)
    if not p.is_file():
        raise InputError("config file not found", p, "check the path")
    try:
        return tomllib.loads(p.read_text())
    except (UnicodeDecodeError, tomllib.TOMLDecodeError) as e:
        raise ConfigError(f"not valid TOML ({e})", p, "repair the file, or write a fresh one with texstream run") from None
