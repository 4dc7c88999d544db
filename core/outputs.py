"""Stage outputs: JSON read with one-line errors, atomic files and folders, and the stage result.

Every stage is a plain function over folders. It validates inputs, writes into a temporary
sibling folder, saves its resolved config there (``<stage>_config.json``), and renames the folder
into place only when everything succeeded, so a failure never leaves a half-written output.
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import json
import math
import os
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any, Iterator

from .errors import InputError, StageError


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
    """Write JSON to a temporary file beside ``path`` and rename it into place. NaN and Inf are refused
    (JSON has no such numbers; a reader would fail on them): a StageError names the file and the key path."""
    try:
        text = json.dumps(data, indent=indent, allow_nan=False, default=_json_default) + "\n"
    except ValueError as e:
        where = _first_nonfinite(data) if str(e).startswith("Out of range float") else None
        if where is None:
            raise
        key, value = where
        raise StageError(f"{key or 'the value'} is {value}: JSON cannot hold a non-finite number; nothing was "
                         "written", path, "report this with the command that made it; --debug shows where it "
                         "came from") from None
    write_atomic_with(Path(path), lambda fh: fh.write(text.encode()))


def _first_nonfinite(value: Any, key: str = "") -> tuple[str, float] | None:
    """(key path such as ``views[3].residual``, the value) of the first NaN or Inf in plain data, or None."""
    if isinstance(value, dict):
        for k, v in value.items():
            found = _first_nonfinite(v, f"{key}.{k}" if key else str(k))
            if found:
                return found
        return None
    if isinstance(value, (list, tuple)):
        for i, v in enumerate(value):
            found = _first_nonfinite(v, f"{key}[{i}]")
            if found:
                return found
        return None
    if type(value).__module__ == "numpy":  # an array or a numpy scalar, as _json_default writes it
        value = _json_default(value)
        if isinstance(value, list):
            return _first_nonfinite(value, key)
    if isinstance(value, float) and not math.isfinite(value):
        return key, value
    return None


def write_atomic_with(p: Path, write) -> None:
    """Call ``write(binary file)`` on a temporary file beside ``p`` and rename it to ``p``: readers
    see the old file or the whole new one, never a half-written one (removed on any error). An OSError
    (a full disk) names ``p`` when the system did not name a file."""
    p.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".tmp", dir=p.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            write(fh)
        _chmod_like_open(tmp)
        os.replace(tmp, p)
    except BaseException as e:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        _name_write_error(e, p)
        raise


_WRITE_ERRNOS = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EROFS, errno.EIO)
"""errors of a write that the system reports without a file name (a full disk, a quota, a failing disk)"""


def _name_write_error(e: BaseException, path: Path) -> None:
    """Give a nameless write error the output's path, so the CLI's one line says where (cli.os_error_line)."""
    if isinstance(e, OSError) and not e.filename and e.errno in _WRITE_ERRNOS:
        e.filename = str(path)


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
    except BaseException as e:
        shutil.rmtree(tmp, ignore_errors=True)
        _name_write_error(e, out)  # a write into tmp that named no file
        raise
    old = None
    try:
        if out.exists():
            old = out.parent / f".{out.name}.old.{os.getpid()}.{time.monotonic_ns()}"
            os.replace(out, old)
        os.replace(tmp, out)
    except BaseException as e:  # a rename refused (a full or read-only disk, Ctrl-C): the previous output back
        if old is not None and not out.exists():
            with contextlib.suppress(OSError):
                os.replace(old, out)
                old = None
        shutil.rmtree(tmp, ignore_errors=True)
        _name_write_error(e, out)
        raise
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


@dataclasses.dataclass
class StageResult:
    """What a stage returns: where it wrote, and a short summary for logs and the pipeline."""

    output: Path
    summary: dict = dataclasses.field(default_factory=dict)
    skipped: bool = False
    reason: str = ""


@dataclasses.dataclass
class OutputTarget:
    """What a command writes, for the checks before its work (:func:`check_output`, :func:`check_room`) and
    its lock (:mod:`texstream.core.lock`)."""

    path: Path
    folder: bool = True
    """a folder (else one file)"""
    estimated_bytes: int = 0
    """a conservative estimate of what the command writes there (0: small, not checked)"""
    what: str = "the output"


def check_output(path: str | os.PathLike, folder: bool = True) -> None:
    """Fail at once, with one line naming the path and the fix, when ``path`` cannot be written: a part of
    it is a file, it exists as the other kind (a file for a folder output), or its folder refuses a new file
    (read-only, no permission). A probe file is created in the folder the output goes to and removed; the
    folders above the output are created, as the stage would create them."""
    out = Path(path)
    if out.exists() and out.is_dir() != folder:
        kind = "folder" if out.is_dir() else "file"
        raise InputError(f"output path exists and is a {kind}", out, "choose another -o path")
    where = out if folder and out.is_dir() else out.parent
    blocker = next((p for p in [where, *where.parents] if p.exists() and not p.is_dir()), None)
    if blocker is not None:
        raise InputError("this part of the output path is a file, not a folder", blocker, "choose another -o path")
    try:
        where.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(prefix=".texstream-write-check.", dir=where)
        os.close(fd)
        os.unlink(probe)
    except OSError as e:
        raise InputError(f"cannot write the output here ({e.strerror or e})", where,
                         "make the folder writable (or free space on its disk), or write elsewhere with -o") from None


def check_room(path: str | os.PathLike, need_bytes: int, what: str = "the output") -> None:
    """Fail at once when the disk that ``path`` goes to has less free space than ``need_bytes`` (a command's
    conservative estimate of what it writes), instead of after the work."""
    if need_bytes <= 0:
        return
    folder = next(p for p in [Path(path).absolute(), *Path(path).absolute().parents] if p.is_dir())
    free = shutil.disk_usage(folder).free
    if free < need_bytes:
        raise InputError(f"{what} needs about {_size(need_bytes)} but its disk has {_size(free)} free", folder,
                         "free space on that disk, or write elsewhere with -o")


def _size(n: float) -> str:
    for unit in ("bytes", "KiB", "MiB", "GiB"):
        if n < 1024 or unit == "GiB":
            return f"{n:.0f} {unit}" if unit == "bytes" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} GiB"
