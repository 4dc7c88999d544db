"""The fuzz and fault harness (issue 41): every command run on damaged inputs, out-of-range options and
injected faults, and the one property checked on each outcome.

The property: exit status 0 with a valid output, or an exit status != 0 with ONE line on stderr that names
the path (or the option) and the fix; never a traceback; never an output left half-written (a temporary
file or ``.partial`` folder, an output folder changed by a failed command) or one a later run mistakes for
finished. argparse's own errors (exit status 2: its usage block, then one ``texstream CMD: error:`` line)
are counted apart as ``argparse``, as the standard form of a malformed command line.

Cases run in-process through :func:`texstream.pipelines.cli.main` with stdout and stderr captured at the
file-descriptor level (so a C++ library's log line counts as a line on stderr); with ``stub=True`` the
command's stage function is replaced by a sentinel, so a generated option costs milliseconds and an
out-of-range value that reaches the stage counts as accepted (issue 41 item 3: options are checked at
parse time, before any work). Faults are injected in-process the way SQLite's test harness does it: the
Nth write (a file opened for writing, a folder made, a rename) under the case's folder raises
``OSError(ENOSPC)`` / ``EACCES`` / ``EROFS`` or ``KeyboardInterrupt``; no root and no real full disk needed.
Signals (SIGINT, SIGKILL at a random time) need a real process: :func:`run_subprocess`.

``tests/test_fuzz_inputs.py`` and ``tests/test_fuzz_faults.py`` run a CI-sized draw; ``scripts/fuzz.py``
runs the large one and writes the counts as JSON.
"""

from __future__ import annotations

import builtins
import contextlib
import dataclasses
import errno
import hashlib
import io
import os
import re
import subprocess
import sys
import tempfile
import traceback
from pathlib import Path
from typing import Any, Callable, Iterator, Sequence

ROOT = Path(__file__).resolve().parent.parent

COMMANDS = ("run", "ingest", "register", "mesh", "atlas", "refine", "fit", "eval", "export", "calibrate",
            "import", "synth")
"""the commands the harness covers (issue 41's list; lights, preview and the checks are not in it)"""

STAGE_FUNCTIONS: dict[str, tuple[tuple[str, str], ...]] = {
    "run": (("texstream.pipelines.cmd_run", "run_pipeline"), ("texstream.pipelines.cmd_run", "synthesize")),
    "ingest": (("texstream.pipelines.cmd_ingest", "ingest"),),
    "register": (("texstream.pipelines.cmd_register", "register"),),
    "mesh": (("texstream.pipelines.cmd_mesh", "make_mesh"),),
    "atlas": (("texstream.pipelines.cmd_atlas", "atlas_stage"),),
    "refine": (("texstream.pipelines.cmd_refine", "refine_stage"),),
    "fit": (("texstream.pipelines.cmd_fit", "fit_stage"), ("texstream.pipelines.cmd_fit", "fit_single_view_stage")),
    "eval": (("texstream.pipelines.cmd_eval", "eval_stage"),),
    "export": (("texstream.pipelines.cmd_export", "export_stage"),),
    "calibrate": (("texstream.pipelines.cmd_calibrate", "calibrate"),),
    "import": (("texstream.pipelines.cmd_import", "import_middlebury"), ("texstream.pipelines.cmd_import", "import_metashape"),
               ("texstream.pipelines.cmd_import", "import_realitycapture"), ("texstream.calib.colmap_io", "import_colmap"),
               ("texstream.calib.colmap_io", "import_nerfstudio")),
    "synth": (("texstream.pipelines.cmd_synth", "synthesize"),),
}
"""per command, the stage functions its ``run(args)`` calls (replaced by a sentinel with ``stub=True``)"""

TEMP_NAME = re.compile(r"^\..*(\.partial|\.tmp[^/]*|\.old\.\d+\.\d+)$")
"""names the atomic writers give their temporary files and folders (core/outputs.py, capture/imageio.py)"""


class ReachedStage(Exception):
    """Raised by a stubbed stage function: the command got past its checks to the work."""


@dataclasses.dataclass
class Outcome:
    """What one command did."""

    argv: list[str]
    rc: int | None
    stdout: str
    stderr: str
    error: str | None = None
    """the traceback of an exception that escaped the CLI's main (a bug)"""
    reached: str | None = None
    """with ``stub=True``: the stage function the command called"""
    fault_fired: bool = False

    @property
    def stderr_lines(self) -> list[str]:
        return [ln for ln in self.stderr.splitlines() if ln.strip()]

    def form(self) -> str:
        """'ok' (exit 0), 'line' (one error line), 'argparse', 'interrupted' or 'bad' (anything else)."""
        if self.error is not None or "Traceback (most recent call last)" in self.stderr:
            return "bad"
        if self.rc == 0:
            return "ok"
        lines = self.stderr_lines
        if self.rc == 2 and lines and lines[0].startswith("usage:") and re.match(r"^texstream( \S+)?: error: ", lines[-1]):
            return "argparse"
        if len(lines) != 1:
            return "bad"
        if self.rc == 130 and lines[0].startswith("texstream: interrupted"):
            return "interrupted"
        return "line" if re.match(r"^texstream( \S+)?: error: .*\S", lines[0]) else "bad"


# --------------------------------------------------------------------------- running a command


@contextlib.contextmanager
def _captured_fds() -> Iterator[Callable[[], tuple[str, str]]]:
    """stdout and stderr captured at the descriptor level (C++ logs too) and at Python's level."""
    saved = {fd: os.dup(fd) for fd in (1, 2)}
    files = {fd: tempfile.TemporaryFile() for fd in (1, 2)}
    py_out, py_err = sys.stdout, sys.stderr
    text = {1: io.StringIO(), 2: io.StringIO()}
    try:
        sys.stdout.flush()
        sys.stderr.flush()
        for fd in (1, 2):
            os.dup2(files[fd].fileno(), fd)
        sys.stdout, sys.stderr = text[1], text[2]

        def read() -> tuple[str, str]:
            out = []
            for fd in (1, 2):
                files[fd].seek(0)
                out.append(text[fd].getvalue() + files[fd].read().decode(errors="replace"))
            return out[0], out[1]
        yield read
    finally:
        sys.stdout, sys.stderr = py_out, py_err
        for fd in (1, 2):
            os.dup2(saved[fd], fd)
            os.close(saved[fd])
            files[fd].close()


@contextlib.contextmanager
def stubbed_stages(command: str) -> Iterator[dict]:
    """Replace the command's stage functions with a sentinel that records which was called and raises
    :class:`ReachedStage`."""
    import importlib

    seen: dict = {}
    saved = []
    for module_name, attr in STAGE_FUNCTIONS.get(command, ()):
        mod = importlib.import_module(module_name)

        def stub(*args, _name=attr, **kwargs):
            seen["stage"] = _name
            seen["args"] = (args, kwargs)
            raise ReachedStage(_name)
        saved.append((mod, attr, getattr(mod, attr)))
        setattr(mod, attr, stub)
    try:
        yield seen
    finally:
        for mod, attr, fn in saved:
            setattr(mod, attr, fn)


def run_cli(argv: Sequence[str], *, stub: bool = False, faults: "FaultInjector | None" = None) -> Outcome:
    """Run ``texstream ARGV`` in this process; an exception escaping main is recorded, not raised."""
    from texstream.pipelines import cli

    argv = [str(a) for a in argv]
    command = next((a for a in argv if not a.startswith("-")), None)
    rc, error, reached = None, None, None
    with contextlib.ExitStack() as stack:
        read = stack.enter_context(_captured_fds())
        seen = stack.enter_context(stubbed_stages(command)) if stub and command in STAGE_FUNCTIONS else {}
        if faults is not None:
            stack.enter_context(faults)
        try:
            rc = int(cli.main(argv))
        except SystemExit as e:  # argparse: --help (0) and usage errors (2)
            rc = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
        except ReachedStage as e:
            reached = str(e)
            rc = 0
        except BaseException:  # noqa: BLE001 - what escapes main is exactly what the harness looks for
            error = traceback.format_exc()
        reached = reached or seen.get("stage")
        stdout, stderr = read()
    fired = faults.fired if faults is not None else False
    return Outcome(argv, rc, stdout, stderr, error, reached, fired)


def python_env() -> dict:
    """The environment a subprocess ``texstream`` needs (the worktree's package links first)."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT / ".pkg"), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    env.pop("TEXSTREAM_DEBUG", None)
    return env


def run_subprocess(argv: Sequence[str], cwd: Path, *, signal_after: float | None = None, sig: int = 9,
                   timeout: float = 300) -> Outcome:
    """Run ``python -m texstream.pipelines.cli ARGV`` as a process; with ``signal_after`` send ``sig`` that
    many seconds after the start (if it is still running)."""
    cmd = [sys.executable, "-m", "texstream.pipelines.cli", *map(str, argv)]
    proc = subprocess.Popen(cmd, cwd=cwd, env=python_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    if signal_after is not None:
        try:
            proc.wait(timeout=signal_after)
        except subprocess.TimeoutExpired:
            proc.send_signal(sig)
    out, err = proc.communicate(timeout=timeout)
    return Outcome(list(map(str, argv)), proc.returncode, out.decode(errors="replace"), err.decode(errors="replace"))


# --------------------------------------------------------------------------- the property


def tree_digest(path: Path) -> dict[str, str] | None:
    """{relative path: sha1} of every file under ``path`` (a file: its own), None when absent."""
    path = Path(path)
    if not path.exists():
        return None
    files = [path] if path.is_file() else sorted(p for p in path.rglob("*") if p.is_file())
    return {str(p.relative_to(path)) if p != path else ".": hashlib.sha1(p.read_bytes()).hexdigest() for p in files}


def leftovers(root: Path) -> list[str]:
    """Temporary files and folders of the atomic writers left anywhere under ``root``."""
    return sorted(str(p) for p in Path(root).rglob(".*") if TEMP_NAME.match(p.name))


def violations(outcome: Outcome, *, names: Sequence[str] = (), root: Path | None = None,
               outputs: dict[Path, dict | None] | None = None, must_fail: bool = False,
               valid: Callable[[], str | None] | None = None) -> list[str]:
    """What of the property one outcome breaks (empty: it holds).

    Args:
        names: on failure the error line must contain one of these (the damaged file, the option).
        root: the case's folder, searched for temporary files left behind.
        outputs: output path -> its :func:`tree_digest` before the command: a failed command must leave
            each as it was (absent or unchanged).
        must_fail: the input or option is invalid: exit status 0 (or reaching a stubbed stage) is a silent
            acceptance.
        valid: on exit status 0, checks the output; returns what is wrong with it, or None.
    """
    out = []
    form = outcome.form()
    if outcome.error is not None or "Traceback (most recent call last)" in outcome.stderr:
        out.append("traceback: " + (outcome.error or outcome.stderr).strip().splitlines()[-1][:300])
    elif form == "bad":
        out.append(f"stderr is not one error line (exit {outcome.rc}): {outcome.stderr.strip()[:400]!r}")
    if must_fail and (outcome.rc == 0 or outcome.reached):
        out.append("silent acceptance: " + ("reached the stage " + outcome.reached if outcome.reached else "exit 0"))
    if form in ("line", "argparse") and names:
        line = outcome.stderr_lines[-1]
        if not any(n in line for n in names):
            out.append(f"the error line names none of {list(names)}: {line[:300]!r}")
    if form == "line" and "Fix:" not in outcome.stderr_lines[-1] and "usage" not in outcome.stderr_lines[-1]:
        out.append(f"the error line gives no fix: {outcome.stderr_lines[-1][:300]!r}")
    if root is not None:
        left = leftovers(root)
        if left:
            out.append(f"half-written: temporary files left: {left[:3]}")
    if outcome.rc != 0 and outputs:
        for p, before in outputs.items():
            if tree_digest(p) != before:
                out.append(f"half-written: a failed command changed its output {p}")
    if outcome.rc == 0 and not outcome.reached and valid is not None and form == "ok":
        why = valid()
        if why:
            out.append(f"exit 0 with an invalid output: {why}")
    return out


# --------------------------------------------------------------------------- faults


FAULTS = {"enospc": (errno.ENOSPC, "No space left on device"), "eacces": (errno.EACCES, "Permission denied"),
          "erofs": (errno.EROFS, "Read-only file system"), "sigint": None}
"""the injected faults: three OSErrors, and Ctrl-C (KeyboardInterrupt) at the write"""

_WRITE_FLAGS = os.O_WRONLY | os.O_RDWR | os.O_CREAT | os.O_APPEND | os.O_TRUNC


class FaultInjector:
    """Count the writes under ``root`` (a file opened for writing, a folder made, a rename) and make the
    ``at``-th raise ``kind`` (one of :data:`FAULTS`); ``at=None`` only counts. An ENOSPC at a file's open
    creates the file empty first, as a disk that fills during the write leaves it."""

    def __init__(self, root: Path, at: int | None = None, kind: str = "enospc"):
        self.root = str(Path(root).resolve())
        self.at = at
        self.kind = kind
        self.count = 0
        self.fired = False
        self.where: str | None = None
        self._saved: list = []

    def _under_root(self, path: Any) -> bool:
        try:
            p = os.path.abspath(os.fsdecode(path))
        except TypeError:  # a file descriptor
            return False
        return p == self.root or p.startswith(self.root + os.sep)

    def _event(self, path: Any, create: Callable[[], None] | None = None) -> None:
        if not self._under_root(path):
            return
        self.count += 1
        if self.at is None or self.count != self.at or self.fired:
            return
        self.fired = True
        self.where = os.fsdecode(path)
        if FAULTS[self.kind] is None:
            raise KeyboardInterrupt
        code, text = FAULTS[self.kind]
        if code == errno.ENOSPC and create is not None:
            create()
        raise OSError(code, text, self.where)

    def __enter__(self) -> "FaultInjector":
        real_open, real_os_open = builtins.open, os.open
        real_mkdir, real_replace, real_rename = os.mkdir, os.replace, os.rename

        def fake_open(file, mode="r", *args, **kwargs):
            if isinstance(file, (str, bytes, os.PathLike)) and any(c in mode for c in "wax+"):
                def create():
                    with real_open(file, "wb"):
                        pass
                self._event(file, create)
            return real_open(file, mode, *args, **kwargs)

        def fake_os_open(path, flags, *args, **kwargs):
            if flags & _WRITE_FLAGS:
                self._event(path)
            return real_os_open(path, flags, *args, **kwargs)

        def fake_mkdir(path, *args, **kwargs):
            self._event(path)
            return real_mkdir(path, *args, **kwargs)

        def fake_replace(src, dst, *args, **kwargs):
            self._event(dst)
            return real_replace(src, dst, *args, **kwargs)

        def fake_rename(src, dst, *args, **kwargs):
            self._event(dst)
            return real_rename(src, dst, *args, **kwargs)

        for obj, name, fn in ((builtins, "open", fake_open), (io, "open", fake_open), (os, "open", fake_os_open),
                              (os, "mkdir", fake_mkdir), (os, "replace", fake_replace), (os, "rename", fake_rename)):
            self._saved.append((obj, name, getattr(obj, name)))
            setattr(obj, name, fn)
        return self

    def __exit__(self, *exc) -> None:
        for obj, name, fn in reversed(self._saved):
            setattr(obj, name, fn)
        self._saved.clear()


def count_writes(argv: Sequence[str], root: Path, stub: bool = False) -> tuple[int, Outcome]:
    """How many writes under ``root`` a clean run of ``argv`` makes (the fault points), and its outcome."""
    counter = FaultInjector(root, at=None)
    outcome = run_cli(argv, stub=stub, faults=counter)
    return counter.count, outcome
