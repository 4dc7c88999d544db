"""Stage outputs: JSON read with one-line errors, atomic files and folders, and the stage result.

Every stage is a plain function over folders. It validates inputs, writes into a temporary
sibling folder, saves its resolved config there (``<stage>_config.json``), and renames the folder
into place only when everything succeeded, so a failure never leaves a half-written output.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any, Iterator

from .errors import InputError


def read_json(path: str | os.PathLike, what: str = "JSON file") -> Any:
    """Read JSON with a one-line error naming the file on any failure."""
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{what} not found", p, "check the path")
    try:
        return json.loads(p.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as e:  # RecursionError: nested too deep
        raise InputError(f"{what} is not valid JSON ({e})", p, "repair or regenerate the file") from None


def write_json_atomic(path: str | os.PathLike, data: Any, indent: int = 2) -> None:
    """Write JSON to a temporary file beside ``path`` and rename it into place."""
    text = json.dumps(data, indent=indent, allow_nan=False, default=_json_default) + "\n"
    write_atomic_with(Path(path), lambda fh: fh.write(text.encode()))


def write_atomic_with(p: Path, write) -> None:
    """Call ``write(binary file)`` on a temporary file beside ``p`` and rename it to ``p``: readers
    see the old file or the whole new one, never a half-written one (removed on any error)."""
    p.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".tmp", dir=p.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            write(fh)
        _chmod_like_open(tmp)
        os.replace(tmp, p)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def _chmod_like_open(path: str) -> None:
    """mkstemp creates files 0600; give the result the mode a plain open() would (0666 & ~umask)."""
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(path, 0o666 & ~umask)


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
