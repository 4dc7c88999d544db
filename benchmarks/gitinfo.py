"""The commit a benchmark ran at, for its JSON (imported by the benchmark scripts beside it)."""

from __future__ import annotations

import subprocess
from pathlib import Path


def commit() -> str:
    """The short hash of this checkout's HEAD, or "unknown" outside a git checkout."""
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                              cwd=Path(__file__).parent).stdout.strip() or "unknown"
    except OSError:
        return "unknown"
