"""One writer per output: a lock file beside each command's output folder or file.

``texstream fit ... -o MODEL`` holds ``.MODEL.lock`` beside ``MODEL`` (never inside it: a stage renames a
finished temporary folder onto ``MODEL``, and the lock must not become part of the output) for as long as it
runs. A second command on the same output fails at once with one line naming the holder (pid, host, command,
start time) and the fix.

The exclusion is an ``flock`` on the lock file, which the kernel drops when its process ends in any way
(``kill -9`` included), so a lock of a killed process on this host is stale as soon as the process is gone;
its JSON text (pid, host, command, start time) is for the messages. A lock whose ``flock`` is free but whose
text names a process of *another* host is honoured until it is :data:`FOREIGN_STALE_AGE_S` old (a network
file system may not share ``flock`` between hosts, and this host cannot check another's pids); older, it is
taken over. Every takeover prints one line. The lock file is removed when the command ends, by an exception
and Ctrl-C included (the ``with`` block); a process killed outright leaves it, and the next command takes it
over.

Commands under a running ``texstream run -o OUT`` (``texstream fit ... -o OUT/model``) are refused too: a lock
of a live process on any folder above the output counts.
"""

from __future__ import annotations

import contextlib
import datetime
import errno
import fcntl
import glob
import json
import os
import re
import shutil
import socket
from pathlib import Path
from typing import Callable, Iterator

from .errors import TexstreamError

FOREIGN_STALE_AGE_S = 3 * 24 * 3600
"""a lock another host wrote is taken over once it is this old (3 days: longer than any run we know of takes;
the lock names its host, so a user can check sooner and remove it)"""


class OutputLocked(TexstreamError):
    """Another process is writing the same output."""


def lock_path(output: str | os.PathLike) -> Path:
    """The lock file of an output: ``.NAME.lock`` beside it."""
    out = Path(output).absolute()
    return out.parent / f".{out.name}.lock"


def _holder_text(info: dict) -> str:
    return (f"pid {info.get('pid', '?')} on host {info.get('host', '?')}, started {info.get('started', '?')}: "
            f"{info.get('command', '?')}")


def _read_info(fd: int) -> dict:
    try:
        os.lseek(fd, 0, os.SEEK_SET)
        data = json.loads(os.read(fd, 1 << 16).decode() or "{}")
        return data if isinstance(data, dict) else {}
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return {}


def _pid_alive(pid: object) -> bool:
    if not isinstance(pid, int) or pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # alive, another user's
        return True
    return True


def _age_s(info: dict) -> float:
    try:
        started = datetime.datetime.fromisoformat(str(info.get("started_iso")))
    except ValueError:
        return float("inf")  # no readable time: as old as can be
    return (datetime.datetime.now(datetime.timezone.utc) - started).total_seconds()


def _try_flock(fd: int) -> bool | None:
    """True: locked; False: another open file holds it; None: this file system has no flock (then the lock's
    text alone decides)."""
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        return True
    except BlockingIOError:
        return False
    except OSError as e:
        if e.errno in (errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOSYS, errno.EINVAL):
            return None
        raise


def _refuse(output: Path, path: Path, info: dict, above: bool = False) -> OutputLocked:
    where = f"a folder above this output ({path.parent / path.name[1:-5]})" if above else "this output"
    return OutputLocked(f"another texstream command is writing {where}: {_holder_text(info)}", output,
                        f"wait for it to end (or stop it), or write elsewhere with -o; if that process is gone, "
                        f"remove {path}")


def _check_above(output: Path) -> None:
    """Refuse when a live process holds the lock of a folder above ``output`` (``texstream run -o OUT``)."""
    for folder in output.parents:
        if folder.parent == folder:
            break
        path = lock_path(folder)
        try:
            fd = os.open(path, os.O_RDONLY)
        except OSError:
            continue
        try:
            free = _try_flock(fd)
            info = _read_info(fd)
            if free is False and info.get("pid") != os.getpid():
                raise _refuse(output, path, info, above=True)
        finally:
            os.close(fd)


def _stale_reason(info: dict, flocked: bool | None) -> str | None:
    """Why an existing lock text is stale (None: it is live and must be honoured)."""
    if not info:
        return ""  # an empty or unreadable file: a lock being written, or left by a crash before its text
    pid = info.get("pid")
    if info.get("host") == socket.gethostname():
        if not _pid_alive(pid):
            return f"pid {pid} is no longer running"
        if flocked:  # the pid lives on but holds no lock: the holder ended and its pid was reused
            return f"pid {pid} no longer holds it"
        return None
    age = _age_s(info)
    if age > FOREIGN_STALE_AGE_S:
        return f"it is {age / 3600:.0f} h old, older than the {FOREIGN_STALE_AGE_S // 3600} h after which " \
               f"a lock of another host counts as stale"
    return None


def acquire(output: str | os.PathLike, command: str, log: Callable[[str], None]) -> int:
    """Take the lock of ``output`` for this process; returns its open descriptor (see :func:`output_lock`)."""
    out = Path(output).absolute()
    _check_above(out)
    path = lock_path(out)
    path.parent.mkdir(parents=True, exist_ok=True)
    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            flocked = _try_flock(fd)
            info = _read_info(fd)
            if flocked is False:
                raise _refuse(out, path, info)
            if _same_file(fd, path):
                break
        except BaseException:
            os.close(fd)
            raise
        os.close(fd)  # the holder removed the file between our open and flock: open the new one
    try:
        if info:
            reason = _stale_reason(info, flocked)
            if reason is None:
                raise _refuse(out, path, info)
            log(f"texstream: took over the stale lock {path} ({_holder_text(info)}; {reason})")
        now = datetime.datetime.now(datetime.timezone.utc)
        text = json.dumps({"pid": os.getpid(), "host": socket.gethostname(), "command": command,
                           "started": now.strftime("%Y-%m-%d %H:%M:%S UTC"), "started_iso": now.isoformat(),
                           "output": str(out)})
        os.ftruncate(fd, 0)
        os.pwrite(fd, text.encode(), 0)
    except OutputLocked:
        os.close(fd)  # another host's lock: left as it is
        raise
    except BaseException as e:
        release(out, fd)  # Ctrl-C or a full disk while taking it: no lock file left behind
        if isinstance(e, OSError) and not e.filename:  # a full disk: the CLI's line names the lock file
            e.filename = str(path)
        raise
    return fd


def _same_file(fd: int, path: Path) -> bool:
    try:
        st = os.stat(path)
    except FileNotFoundError:
        return False
    own = os.fstat(fd)
    return (st.st_dev, st.st_ino) == (own.st_dev, own.st_ino)


def release(output: str | os.PathLike, fd: int) -> None:
    """Remove the lock file (while still holding it, so no one takes a file about to vanish) and close it."""
    path = lock_path(output)
    try:
        if _same_file(fd, path):
            os.unlink(path)
    except OSError:
        pass  # a lock file that cannot be removed is stale once this process ends; the next command takes it over
    finally:
        os.close(fd)


@contextlib.contextmanager
def output_lock(output: str | os.PathLike, command: str, log: Callable[[str], None] = print) -> Iterator[Path]:
    """Hold the lock of ``output`` for the ``with`` block (released on every exit, exceptions included).

    Raises:
        OutputLocked: another live process holds it (the message names the process and the fix).
    """
    fd = acquire(output, command, log)
    try:
        remove_leftovers(output, log)
        yield lock_path(output)
    finally:
        release(output, fd)


LEFTOVER = re.compile(r"^\..+(\.partial|\.tmp|\.old\.\d+\.\d+)$")
"""names the atomic writers give their temporary files and folders (core/outputs.py: ``.NAME.XXXX.partial``,
``.NAME.XXXX.tmp``, ``.NAME.old.PID.NS``)"""


def remove_leftovers(output: str | os.PathLike, log: Callable[[str], None]) -> int:
    """Remove what atomic writes killed outright (``kill -9``, a power cut) left beside ``output`` and directly
    inside it (a run's stage folders): with the output's lock held no other process writes there, so they are
    nobody's. Returns how many went (one line says so)."""
    out = Path(output).absolute()
    found = [q for q in out.parent.glob(f".{glob.escape(out.name)}.*") if LEFTOVER.match(q.name)]
    if out.is_dir():
        found += [q for q in out.glob(".*") if LEFTOVER.match(q.name)]
    for q in found:
        if q.is_dir() and not q.is_symlink():
            shutil.rmtree(q, ignore_errors=True)
        else:
            with contextlib.suppress(OSError):
                q.unlink()
    if found:
        log(f"texstream: removed {len(found)} temporary file(s) an interrupted command left in {out}")
    return len(found)
