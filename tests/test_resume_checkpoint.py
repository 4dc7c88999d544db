"""The stage work folders (core/checkpoint.py) the long stages resume from: a write cut short leaves the previous
checkpoint whole, work of another key is dropped with a line, damage is only a lost head start."""

from __future__ import annotations

import numpy as np
import pytest

from texstream.core.checkpoint import StageCheckpoint, work_dir_for
from texstream.core.progress import reporting


def test_a_write_cut_short_leaves_the_previous_checkpoint(tmp_path, monkeypatch):
    ck = StageCheckpoint(work_dir_for(tmp_path / "out", "stage"), "key-a", "stage")
    assert ck.open() is False and ck.folder == tmp_path / ".out.stage-work"
    ck.write_arrays("state.npz", step=np.array(1), x=np.arange(5.0))

    def half_then_killed(fh, **arrays):
        fh.write(b"PK\x03\x04 half a zip")  # what a process killed mid-write leaves in its file
        raise KeyboardInterrupt

    monkeypatch.setattr(np, "savez", half_then_killed)
    with pytest.raises(KeyboardInterrupt):
        ck.write_arrays("state.npz", step=np.array(2), x=np.zeros(5))
    monkeypatch.undo()
    again = StageCheckpoint(ck.folder, "key-a", "stage")
    assert again.open() is True
    state = again.read_arrays("state.npz")
    assert int(state["step"]) == 1 and state["x"].tolist() == [0.0, 1.0, 2.0, 3.0, 4.0]


def test_work_of_another_key_is_dropped_with_a_line(tmp_path):
    ck = StageCheckpoint(tmp_path / "work", "key-a", "stage")
    ck.open()
    ck.write_json("start.json", {"rms": 0.5})
    lines = []
    with reporting(lines.append, bars=False):
        other = StageCheckpoint(tmp_path / "work", "key-b", "stage")
        assert other.open() is False
    assert lines == [f"  stage: {tmp_path / 'work'} holds work of other inputs or options: ignored, starting afresh"]
    assert other.read_json("start.json") is None


def test_a_damaged_file_is_only_a_lost_head_start(tmp_path):
    ck = StageCheckpoint(tmp_path / "work", "key", "stage")
    ck.open()
    (ck.folder / "state.npz").write_bytes(b"not a zip")
    (ck.folder / "start.json").write_text("{")
    assert ck.read_arrays("state.npz") is None and ck.read_json("start.json") is None
    ck.remove()
    assert not ck.folder.exists()


def test_files_signature_resolves_paths_as_path_resolve_does(tmp_path):
    """The signature's paths are Path.resolve's (links in folders and in the file itself, ".." after a linked
    folder, missing files and folders, relative paths, "..", "." or "" last, doubled and trailing slashes), though it
    resolves each folder once."""
    import os
    from pathlib import Path

    from texstream.core.checkpoint import files_signature

    (tmp_path / "a" / "images").mkdir(parents=True)
    (tmp_path / "b").mkdir()
    for i in range(5):
        (tmp_path / "a" / "images" / f"f{i}.png").write_bytes(b"x" * i)
    os.symlink(tmp_path / "a", tmp_path / "link_a")
    os.symlink(tmp_path / "a" / "images" / "f1.png", tmp_path / "b" / "file_link.png")
    paths = [tmp_path / "a/images/f0.png", tmp_path / "link_a/images/f2.png", tmp_path / "b/../a/images/f3.png",
             tmp_path / "link_a/../b/file_link.png", tmp_path / "b/file_link.png", tmp_path / "missing/x.png",
             tmp_path / "a/images", "relative_missing.png", tmp_path / "b/../link_a/images/f4.png",
             f"{tmp_path}/a//images/./f0.png", tmp_path / "a/images/..", f"{tmp_path}/a/.", f"{tmp_path}/b/", "",
             f"{tmp_path}/a/images/f1.png/"]
    expected = []
    for p in map(Path, paths):
        st = p.stat() if p.is_file() else None
        expected.append([str(p.resolve()), st.st_size if st else None, st.st_mtime_ns if st else None])
    assert files_signature(paths) == expected
