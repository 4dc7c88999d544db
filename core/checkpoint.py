"""A long stage's progress kept beside its output, so a rerun after Ctrl-C or ``kill -9`` resumes from it.

A stage writes its output folder atomically (:mod:`texstream.core.outputs`): a killed stage leaves no output,
and the pipeline's stamp, written after the folder, never marks it finished. What it had done is kept in a
work folder beside the output, ``.<output name>.<stage>-work/``, by a :class:`StageCheckpoint`:

- every file in it is written atomically (a kill during a write leaves the previous version);
- it carries a key, a hash of the stage's inputs and options: a rerun with other inputs or options says so
  in one line and starts afresh (the stale work is removed);
- the stage says what it resumes from, and removes the folder once its output is in place.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import stat
import zipfile
from pathlib import Path
from typing import Any, Callable

from .outputs import write_atomic_with
from .progress import say

KEY_FILE = "key.json"


def inputs_key(*parts: Any) -> str:
    """A hash of JSON-able parts (options as dicts, file lists from :func:`files_signature`)."""
    h = hashlib.sha256()
    for p in parts:
        h.update(json.dumps(p, sort_keys=True, default=str).encode())
    return h.hexdigest()[:24]


def files_signature(paths) -> list:
    """(path, size, modification time) of each file: changes when a photo or a mesh does, without reading it.
    The path is the file's resolved one (``Path.resolve``); each folder is resolved once and a file's own link
    only where it is one (a fit's 1,760 photos and masks took 0.49 s of stat calls resolving every component of
    every path on an H200's host, issue 40), the same strings."""
    out, folders = [], {}
    for p in paths:
        p = os.fspath(Path(p))  # Path's own normal form ("a//b", "a/./b")
        head, tail = os.path.split(p)
        try:
            link = os.lstat(p)
        except OSError:
            link = None
        if tail in ("", ".", "..") or (link is not None and stat.S_ISLNK(link.st_mode)):
            resolved, st = str(Path(p).resolve()), (os.stat(p) if os.path.isfile(p) else None)
        else:
            if head not in folders:  # the folder resolved as Path.resolve does (links before "..")
                folders[head] = str(Path(head).resolve())
            resolved = os.path.join(folders[head], tail)
            st = link if link is not None and stat.S_ISREG(link.st_mode) else None
        out.append([resolved, st.st_size if st else None, st.st_mtime_ns if st else None])
    return out


def work_dir_for(out: str | os.PathLike, stage: str) -> Path:
    """The work folder of ``stage`` writing ``out``: a hidden sibling, so it survives the output's atomic
    replacement and is not an input of a later stage (hidden files are not hashed as inputs)."""
    out = Path(out)
    return out.parent / f".{out.name}.{stage}-work"


class StageCheckpoint:
    """A stage's work folder tied to a key (see the module). ``say_line(message)`` prints the resume lines
    (default: the stage's phase line)."""

    def __init__(self, folder: str | os.PathLike, key: str, stage: str,
                 say_line: Callable[[str], None] | None = None):
        self.folder, self.key, self.stage = Path(folder), key, stage
        self.say = say_line or (lambda message: say(stage, message))

    def open(self) -> bool:
        """Make the work folder ready; True when it holds work of this key (a resume), False when it starts
        empty (none there, or another key's, which is removed with a line)."""
        key_path = self.folder / KEY_FILE
        if key_path.is_file():
            try:
                old = json.loads(key_path.read_text()).get("key")
            except (OSError, ValueError, AttributeError):
                old = None
            if old == self.key:
                return True
            self.say(f"{self.folder} holds work of other inputs or options: ignored, starting afresh")
        if self.folder.exists():
            shutil.rmtree(self.folder)
        self.folder.mkdir(parents=True)
        self.write_json(KEY_FILE, {"key": self.key})
        return False

    def path(self, name: str) -> Path:
        return self.folder / name

    def write_json(self, name: str, data: Any) -> None:
        text = json.dumps(data, allow_nan=False, default=str)
        write_atomic_with(self.folder / name, lambda fh: fh.write(text.encode()))

    def read_json(self, name: str) -> Any:
        """The JSON file ``name`` of the work folder, or None when it is missing or damaged (only a lost head
        start: the atomic writes make damage unlikely)."""
        try:
            return json.loads((self.folder / name).read_text())
        except (OSError, ValueError):
            return None

    def write_arrays(self, name: str, **arrays) -> None:
        """An uncompressed .npz (written often, read once) of the arrays, atomically."""
        import numpy as np  # local: core imports no third-party package at import

        write_atomic_with(self.folder / name, lambda fh: np.savez(fh, **arrays))

    def read_arrays(self, name: str) -> dict | None:
        """The arrays of ``name``, or None when the file is missing or damaged."""
        import numpy as np

        try:
            with np.load(self.folder / name, allow_pickle=False) as z:
                return {k: z[k] for k in z.files}
        except (OSError, ValueError, EOFError, zipfile.BadZipFile):
            return None

    def remove(self) -> None:
        """Drop the work folder (the stage's output is in place)."""
        shutil.rmtree(self.folder, ignore_errors=True)
