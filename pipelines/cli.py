"""The ``texstream`` console script: one command, thin subcommands over stage functions.

Each subcommand lives in ``texstream.pipelines.cmd_<name>`` and defines
``add_arguments(parser)`` and ``run(args) -> int``; it is imported only when used, so
``texstream --help`` is instant and a stage's heavy dependencies load only for that stage.
User errors (:class:`TexstreamError`) are caught here, once, and printed as one line; ``--debug``
(before or after the subcommand) or ``TEXSTREAM_DEBUG=1`` lets them through with their traceback.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import os
import shlex
import sys
import typing
from typing import Any, Sequence

from texstream.core.config import Number
from texstream.core.errors import TexstreamError
from texstream.core.lock import output_lock
from texstream.core.outputs import check_output, check_room

# name -> (module, one-line help). The order is the pipeline's order.
SUBCOMMANDS: dict[str, tuple[str, str]] = {
    "run": ("texstream.pipelines.cmd_run", "end-to-end: photos (or a built-in synthetic set) to a fitted model"),
    "ingest": ("texstream.pipelines.cmd_ingest", "read a raw photo folder into a capture folder"),
    "calibrate": ("texstream.pipelines.cmd_calibrate", "camera intrinsics from chessboard / ChArUco photos"),
    "register": ("texstream.pipelines.cmd_register", "recover camera poses with COLMAP (pycolmap)"),
    "lights": ("texstream.pipelines.cmd_lights", "light position / direction from mirror-ball photos"),
    "chart": ("texstream.pipelines.cmd_chart", "the photos' response (tone curve) from a ColorChecker in view"),
    "import": ("texstream.pipelines.cmd_import", "convert Middlebury / COLMAP / nerfstudio / Metashape / RealityCapture cameras to a capture folder"),
    "synth": ("texstream.pipelines.cmd_synth", "render a synthetic capture set with ground truth"),
    "mesh": ("texstream.pipelines.cmd_mesh", "make, clean and simplify the mesh"),
    "atlas": ("texstream.pipelines.cmd_atlas", "UV atlas and texel bake for fitting"),
    "refine": ("texstream.pipelines.cmd_refine", "refine registered cameras and the mesh against the photos (Warp)"),
    "fit": ("texstream.pipelines.cmd_fit", "fit an appearance model to a posed capture (Warp)"),
    "export": ("texstream.pipelines.cmd_export", "glTF binary and OBJ+MTL of a fitted model, for viewers and DCC tools"),
    "eval": ("texstream.pipelines.cmd_eval", "PSNR / APE of a fitted model on a capture"),
    "relight": ("texstream.pipelines.cmd_relight", "render a relightable model under another light (env map or SH)"),
    "preview": ("texstream.pipelines.cmd_preview", "contact sheet of a capture folder"),
    "fpcheck": ("texstream.pipelines.cmd_fpcheck", "error in ULPs of the device's floating-point operations (Warp)"),
    "stiffcheck": ("texstream.pipelines.cmd_stiffcheck", "stiff and extreme fits against a float64 reference"),
}

DECODING_COMMANDS = ("fit", "run")
"""commands that decode a capture's photo files (their decoding processes are started with the command)"""


def _field_type(t: Any) -> Any:
    origin = typing.get_origin(t)
    if origin is typing.Union or str(origin) == "<class 'types.UnionType'>":
        args = [a for a in typing.get_args(t) if a is not type(None)]
        return _field_type(args[0]) if args else str
    return t


def add_config_arguments(parser: argparse.ArgumentParser, cls: type, prefix: str = "") -> None:
    """Add one ``--option`` per field of a dataclass config (help from the field's metadata)."""
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        meta = f.metadata or {}
        if not meta.get("cli", True):
            continue
        t = _field_type(hints[f.name])
        name = "--" + (prefix + f.name).replace("_", "-")
        default = f.default if f.default is not dataclasses.MISSING else (
            f.default_factory() if f.default_factory is not dataclasses.MISSING else None)
        if dataclasses.is_dataclass(t):
            add_config_arguments(parser, t, prefix=prefix + f.name + ".")
            continue
        help_text = meta.get("help", "").replace("%", "%%")  # argparse %-formats help strings
        kw: dict[str, Any] = {"dest": (prefix + f.name).replace(".", "__"), "default": argparse.SUPPRESS}
        if meta.get("choices"):
            kw["choices"] = list(meta["choices"])
        if t is bool:
            parser.add_argument(name, action=argparse.BooleanOptionalAction,
                                help=f"{help_text} (default: {default})", **kw)
            continue
        if typing.get_origin(t) in (tuple, list):
            args = typing.get_args(t)
            kw["type"] = args[0] if args and args[0] is not Ellipsis else float
            kw["nargs"] = "+"
        elif t in (int, float, str):
            kw["type"] = t
        else:
            kw["type"] = str
        span = ""
        if kw["type"] in (int, float) and (meta.get("min") is not None or meta.get("max") is not None):
            kw["type"] = Number(kw["type"], name, meta.get("min"), meta.get("max"), meta.get("also", ()))
            span = f"; {kw['type'].span()}"
        parser.add_argument(name, help=f"{help_text} (default: {default}{span})", **kw)


def config_from_args(cls: type, args: argparse.Namespace, prefix: str = "", **overrides: Any) -> Any:
    """Build a dataclass config from parsed arguments (fields not given keep their defaults)."""
    hints = typing.get_type_hints(cls)
    kwargs: dict[str, Any] = {}
    for f in dataclasses.fields(cls):
        t = _field_type(hints[f.name])
        if dataclasses.is_dataclass(t):
            sub = config_from_args(t, args, prefix=prefix + f.name + ".")
            kwargs[f.name] = sub
            continue
        dest = (prefix + f.name).replace(".", "__")
        if hasattr(args, dest):
            v = getattr(args, dest)
            if typing.get_origin(t) is tuple and isinstance(v, list):
                v = tuple(v)
            kwargs[f.name] = v
    kwargs.update(overrides)
    return cls(**kwargs)


def threads_asked_for(argv: Sequence[str]) -> bool:
    """Whether the command line sets ``--stream.photo-decoder threads`` (read before the parser exists, to
    start no decoding processes)."""
    flag = "--stream.photo-decoder"
    return any(a == f"{flag}=threads" or (a == flag and argv[i + 1:i + 2] == ["threads"]) for i, a in enumerate(argv))


class OneLineParser(argparse.ArgumentParser):
    """argparse with its errors (an unknown option, a missing argument, a bad choice) on one line naming
    the fix, as every other error of the CLI, instead of the usage block above the message."""

    def error(self, message: str) -> typing.NoReturn:
        self.exit(2, f"{self.prog}: error: {message}. Fix: see '{self.prog} --help'.\n")


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    parser = OneLineParser(
        prog="texstream",
        description="Photos to textured appearance models by image-streaming nonlinear optimization.")
    parser.add_argument("--debug", action="store_true", help="show tracebacks for errors")
    # --debug also after the subcommand (`texstream synth ... --debug`); SUPPRESS keeps a subparser
    # that did not see it from resetting the top-level value to False
    common = OneLineParser(add_help=False)
    common.add_argument("--debug", action="store_true", default=argparse.SUPPRESS,
                        help="show tracebacks for errors")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (module, help_text) in SUBCOMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text, parents=[common])
        if name == only:
            importlib.import_module(module).add_arguments(p)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    command = next((a for a in argv if not a.startswith("-")), None)
    debug = "--debug" in argv or os.environ.get("TEXSTREAM_DEBUG") == "1"
    decoding = command in DECODING_COMMANDS and not threads_asked_for(argv)
    if decoding:
        # the photo decoders start while this process imports Warp and reads the capture (fit/stream/decode_pool.py)
        from texstream.fit.stream import decode_pool

        decode_pool.start_in_background()
    try:
        parser = build_parser(only=command if command in SUBCOMMANDS else None)
        args = parser.parse_args(argv)
        if args.command is None:
            parser.print_help()
            return 2
        module = importlib.import_module(SUBCOMMANDS[args.command][0])
        return run_with_output_checks(module, args, " ".join(shlex.quote(a) for a in ["texstream", *argv]))
    except TexstreamError as e:
        if debug:
            raise
        print(f"texstream {command}: error: {e.one_line()}", file=sys.stderr)
        return 1
    except OSError as e:  # a full disk, a read-only folder: the stage's output was not left half-written
        if debug:
            raise
        print(f"texstream {command}: error: {os_error_line(e)}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("texstream: interrupted; no output was left half-written", file=sys.stderr)
        return 130
    finally:
        if decoding:
            from texstream.fit.stream import decode_pool

            decode_pool.shutdown(wait=False)  # the workers exit at the end of their input; nothing waits for it


def run_with_output_checks(module, args: argparse.Namespace, command_line: str) -> int:
    """Run a subcommand with its output checked and locked first: the command's ``output_target(args)``
    (absent or None: it writes nothing to check) must be writable (a probe file), is locked for the run
    (:mod:`texstream.core.lock`: a second command on it fails at once) and needs room on its disk for the
    command's estimate, all before any long work."""
    target_of = getattr(module, "output_target", None)
    target = target_of(args) if target_of is not None else None
    if target is None:
        return int(module.run(args) or 0)
    check_output(target.path, folder=target.folder)
    with output_lock(target.path, command_line, log=lambda line: print(line, file=sys.stderr, flush=True)):
        check_room(target.path, target.estimated_bytes, target.what)
        return int(module.run(args) or 0)


def console_main() -> None:
    """The ``texstream`` console script: :func:`main`, then the process ends without the interpreter's
    teardown. Every output was written (atomically) and closed by then; what the teardown would do is free
    memory the operating system frees anyway: Warp's kernel modules and arrays, the CUDA context (about
    0.5 s on a GPU machine, a tenth of a fit from disk). Other threads are waited for and exit handlers run
    first, as at a normal exit."""
    import atexit
    import threading

    code = main()
    try:
        for t in threading.enumerate():
            if t is not threading.main_thread() and not t.daemon:
                t.join()
        atexit._run_exitfuncs()
    finally:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)


def os_error_line(e: OSError) -> str:
    """One line for an operating-system error (what failed, where, and the fix): stages write atomically,
    so whatever failed left no half-written output, and a rerun of ``texstream run`` reuses the stages
    that completed."""
    import errno

    where = f"{e.filename}: " if e.filename else ""
    what = e.strerror or str(e) or type(e).__name__
    if e.errno in (errno.ENOSPC, errno.EDQUOT):
        fix = ("free space on that disk (or write elsewhere with -o) and run the same command again: "
               "completed stages are kept and reused, nothing half-written was left")
    elif e.errno in (errno.EACCES, errno.EPERM, errno.EROFS):
        fix = "make the folder writable, or write elsewhere with -o"
    else:
        fix = "check the path and the disk, then run the same command again (--debug shows the traceback)"
    return f"{where}{what.rstrip('.')}. Fix: {fix}."


if __name__ == "__main__":
    sys.exit(main())
