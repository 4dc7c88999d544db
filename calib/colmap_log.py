"""COLMAP's log kept out of the stages' output: its thousands of INFO lines per registration hidden unless
``TEXSTREAM_COLMAP_LOG=1``, its errors shown (the registration's and the triangulation's pycolmap calls)."""

from __future__ import annotations

import contextlib
import os
import re
import sys
import tempfile
from collections.abc import Iterator
from typing import TextIO

from texstream.core.errors import TexstreamError


def quiet_colmap_log() -> None:
    """COLMAP's own log lines (thousands per registration) only with ``TEXSTREAM_COLMAP_LOG=1``; the stages
    print what they found, and errors still come through."""
    import pycolmap

    if os.environ.get("TEXSTREAM_COLMAP_LOG") != "1":
        pycolmap.logging.minloglevel = 2  # 0 info, 1 warning, 2 error


# a glog record: severity letter, date, time, thread, file:line] (after an optional colour code)
_GLOG_LINE = re.compile(r"^(?:\x1b\[[0-9;]*m)*([IWEF])\d{8} ")
_ANSI = re.compile(r"\x1b\[[0-9;]*m")


@contextlib.contextmanager
def colmap_quiet() -> Iterator[TextIO]:
    """Hide COLMAP's log lines during a pycolmap call unless ``TEXSTREAM_COLMAP_LOG=1``; its error records
    and anything else written to stderr are shown after the call. Yields a stream on the real stderr
    for progress bars.

    Why at the file-descriptor level and not only glog's ``minloglevel``: pycolmap 4.2.1's
    ``bundle_adjustment`` sets ``minloglevel`` back to 0 on every call (set to 2 before the call, it
    reads 0 after it, and the call prints its ``=== Global bundle adjustment ===`` and report INFO
    lines); COLMAP's C++ threads write to file descriptor 2 directly, past Python's ``sys.stderr``.
    """
    if os.environ.get("TEXSTREAM_COLMAP_LOG") == "1":
        yield sys.stderr
        return
    import pycolmap

    pycolmap.logging.minloglevel = 2
    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile() as sink, os.fdopen(os.dup(saved), "w", buffering=1) as term:
        os.dup2(sink.fileno(), 2)
        try:
            yield term
        finally:
            sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)
            pycolmap.logging.minloglevel = 2
            sink.seek(0)
            _replay_errors(sink.read().decode("utf-8", "replace"))


_held: list[str] | None = None
"""COLMAP's error records of the stage running under :func:`colmap_errors_held`, not yet printed"""


@contextlib.contextmanager
def colmap_errors_held() -> Iterator[None]:
    """Hold COLMAP's error records until the stage ends (a decorator of the stage function): a stage that
    fails with its own one-line error (a TexstreamError: "no model: none of the 4 photos could be registered
    ... Fix: ...") has said what COLMAP's "Failed to create any sparse model" says, so they are dropped and
    the error stays one line (``TEXSTREAM_COLMAP_LOG=1`` shows COLMAP's whole log); after a success or an
    unexpected error they are printed, as :func:`colmap_quiet` prints them without a stage around it."""
    global _held
    if _held is not None:  # an outer stage holds them
        yield
        return
    _held = []
    try:
        yield
    except TexstreamError:
        _held = None
        raise
    finally:
        held, _held = _held, None
        if held:
            print("\n".join(held), file=sys.stderr, flush=True)


def _replay_errors(text: str) -> None:
    """Print what COLMAP wrote but its INFO and WARNING records (and their continuation lines); under
    :func:`colmap_errors_held`, keep them for the end of the stage."""
    shown, keep = [], True
    for line in text.splitlines():
        m = _GLOG_LINE.match(line)
        if m:  # a record's continuation lines (the bundle-adjustment report) follow its severity
            keep = m.group(1) in "EF"
        if keep and line.strip():
            shown.append(_ANSI.sub("", line))
    if shown and _held is not None:
        _held.extend(shown)
    elif shown:
        print("\n".join(shown), file=sys.stderr, flush=True)
