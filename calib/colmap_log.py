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


def _replay_errors(text: str) -> None:
    """Print what COLMAP wrote but its INFO and WARNING records (and their continuation lines)."""
    shown, keep = [], True
    for line in text.splitlines():
        m = _GLOG_LINE.match(line)
        if m:  # a record's continuation lines (the bundle-adjustment report) follow its severity
            keep = m.group(1) in "EF"
        if keep and line.strip():
            shown.append(_ANSI.sub("", line))
    if shown:
        print("\n".join(shown), file=sys.stderr, flush=True)
