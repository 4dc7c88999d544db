"""User-facing errors.

Every error a user can cause (a missing file, a corrupt image, a bad field) is raised as a
:class:`TexstreamError` naming the file and the fix. The CLI catches it once, at the entry point,
and prints one line; ``--debug`` shows the traceback. Internal invariants use ``assert``.
"""

from __future__ import annotations

import os


class TexstreamError(Exception):
    """An error the user can fix.

    Args:
        message: what is wrong (expected vs got where it applies).
        path: the file or folder at fault, if any.
        fix: one short sentence saying what to do about it.
    """

    def __init__(self, message: str, path: str | os.PathLike | None = None, fix: str | None = None):
        self.message = message
        self.path = None if path is None else str(path)
        self.fix = fix
        super().__init__(self.one_line())

    def one_line(self) -> str:
        parts = []
        if self.path:
            parts.append(f"{self.path}: ")
        parts.append(self.message.rstrip("."))
        if self.fix:
            parts.append(f". Fix: {self.fix.rstrip('.')}")
        return "".join(parts) + "."


class InputError(TexstreamError):
    """Bad or missing input data (images, capture.json, meshes)."""


class ConfigError(TexstreamError):
    """A bad option or configuration value."""


class StageError(TexstreamError):
    """A stage could not produce its output from valid input (e.g. SfM registered nothing)."""
