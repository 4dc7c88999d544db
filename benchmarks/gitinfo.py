"""The commit a benchmark ran at, for its JSON (imported by the benchmark scripts beside it)."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path


def commit() -> str:
    """The short hash of this checkout's HEAD (``TEXSTREAM_COMMIT`` when set: a copy of a working tree whose
    git metadata is older than its files), or "unknown" outside a git checkout."""
    if os.environ.get("TEXSTREAM_COMMIT"):
        return os.environ["TEXSTREAM_COMMIT"]
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                              cwd=Path(__file__).parent).stdout.strip() or "unknown"
    except OSError:
        return "unknown"
