"""Stage plumbing: documented dataclass configs saved beside outputs, and atomic outputs.

Every stage is a plain function over folders. It validates inputs, writes into a temporary
sibling folder, saves its resolved config there (``<stage>_config.json``), and renames the folder
into place only when everything succeeded, so a failure never leaves a half-written output.

Config fields carry their help text in ``field(metadata={"help": ...})``; the CLI turns it into
``--help`` and this module writes the resolved values as plain JSON.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import shutil
import tempfile
import time
import typing
from pathlib import Path
from typing import Any, Iterator, TypeVar

from .errors import ConfigError, InputError

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


def read_json(path: str | os.PathLike, what: str = "JSON file") -> Any:
    """Read JSON with a one-line error naming the file on any failure."""
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{what} not found", p, "check the path")
    try:
        return json.loads(p.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise InputError(f"{what} is not valid JSON ({e})", p, "repair or regenerate the file") from None


def write_json_atomic(path: str | os.PathLike, data: Any, indent: int = 2) -> None:
    """Write JSON to a temporary file beside ``path`` and rename it into place."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".tmp", dir=p.parent)
    try:
        with os.fdopen(fd, "w") as fh:
            json.dump(data, fh, indent=indent, allow_nan=False, default=_json_default)
            fh.write("\n")
        os.replace(tmp, p)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def _json_default(o: Any) -> Any:
    import numpy as np  # local: keep this module dependency-free at import

    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


@contextlib.contextmanager
def atomic_output_dir(out: str | os.PathLike, overwrite: bool = True) -> Iterator[Path]:
    """Yield a temporary folder beside ``out``; on success it replaces ``out``, on error it is removed.

    Example:
        with atomic_output_dir("model") as tmp:
            write_everything_into(tmp)
        # "model" now holds the complete output, or is untouched if anything raised.
    """
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError("output path exists and is not a folder", out, "choose another -o path")
    if out.exists() and not overwrite:
        raise InputError("output folder already exists", out, "remove it or pass --overwrite")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".partial", dir=out.parent))
    try:
        yield tmp
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    old = None
    if out.exists():
        old = out.parent / f".{out.name}.old.{os.getpid()}.{time.monotonic_ns()}"
        os.replace(out, old)
    os.replace(tmp, out)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


@dataclasses.dataclass
class StageResult:
    """What a stage returns: where it wrote, and a short summary for logs and the pipeline."""

    output: Path
    summary: dict = dataclasses.field(default_factory=dict)
    skipped: bool = False
    reason: str = ""
