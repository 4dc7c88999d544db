"""The refine stage, interrupted after an iteration, resumes from its checkpoint to the uninterrupted result to
the last bit (geometry/refine_checkpoint.py); a checkpoint of other options is ignored with a line.

The interruption is raised in-process from the checkpoint's write (a KeyboardInterrupt right after the N-th
save): work after the last save is lost whether the process is killed there or later, so this is the state a
SIGKILL anywhere between two saves leaves, without a subprocess's start-up (seconds of imports and kernel
loads). scripts/kill_resume.py kills a real ``texstream run`` with SIGKILL at random times."""

from __future__ import annotations

import json

import numpy as np
import pytest

from texstream.core.checkpoint import work_dir_for
from texstream.core.progress import reporting
from texstream.geometry.refine import RefineConfig, refine_stage
from texstream.geometry.mesh_io import load_mesh

from conftest import interrupt_after, tiny_sphere_capture


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    return tiny_sphere_capture(tmp_path_factory.mktemp("refine_resume"), photos=8, image_size=24)


def config(**kw) -> RefineConfig:
    # two levels of two iterations, the shading normals short: 4 checkpoints (saved after every iteration), a
    # few seconds
    return RefineConfig(**{"holdout_every": 8, "blur": "1,0", "iterations": 2, "normal_iterations": 1,
                           "intensity_iterations": 1, "checkpoint_every_s": 0.0, **kw})


def outputs(folder):
    record = json.loads((folder / "refine.json").read_text())
    record.pop("seconds")
    cap = json.loads((folder / "capture.json").read_text())
    return record, [f["transform_matrix"] for f in cap["frames"]], load_mesh(folder / "mesh.obj").vertices


def test_an_interrupted_refine_resumes_to_the_uninterrupted_result(capture, tmp_path, monkeypatch):
    gt = capture / "ground_truth"
    refine_stage(capture, gt, tmp_path / "whole", config())
    assert not work_dir_for(tmp_path / "whole", "refine").exists()  # removed once the output is in place
    interrupt_after(monkeypatch, 3)  # after the first iteration of the second level
    with pytest.raises(KeyboardInterrupt):
        refine_stage(capture, gt, tmp_path / "again", config())
    assert not (tmp_path / "again").exists() and work_dir_for(tmp_path / "again", "refine").is_dir()
    monkeypatch.undo()
    lines = []
    with reporting(lines.append, bars=False):
        refine_stage(capture, gt, tmp_path / "again", config())
    assert any("resuming from" in line and "3 of 4 iterations" in line for line in lines), lines
    whole, again = outputs(tmp_path / "whole"), outputs(tmp_path / "again")
    assert whole[0] == again[0]  # summary and trace, every float to the last digit
    assert whole[1] == again[1]
    np.testing.assert_array_equal(whole[2], again[2])


def test_a_refine_interrupted_in_a_level_that_settles_resumes_to_the_uninterrupted_result(capture, tmp_path,
                                                                                         monkeypatch):
    # rel_tol 0.5: each level of 4 stops after its second iteration (saves: 1, 2 at the first level's stop, 3
    # after the second level's first iteration); the resumed level compares its next iteration with the saved one
    gt = capture / "ground_truth"
    options = {"iterations": 4, "rel_tol": 0.5, "min_move": 0.0}
    refine_stage(capture, gt, tmp_path / "whole", config(**options))
    interrupt_after(monkeypatch, 3)
    with pytest.raises(KeyboardInterrupt):
        refine_stage(capture, gt, tmp_path / "again", config(**options))
    monkeypatch.undo()
    refine_stage(capture, gt, tmp_path / "again", config(**options))
    whole, again = outputs(tmp_path / "whole"), outputs(tmp_path / "again")
    assert whole[0]["levels"]["iterations"] == [2, 2]
    assert whole[0] == again[0] and whole[1] == again[1]
    np.testing.assert_array_equal(whole[2], again[2])


def test_a_checkpoint_of_other_options_is_ignored_with_a_line(capture, tmp_path, monkeypatch):
    gt = capture / "ground_truth"
    interrupt_after(monkeypatch, 1)
    with pytest.raises(KeyboardInterrupt):
        refine_stage(capture, gt, tmp_path / "out", config())
    monkeypatch.undo()
    interrupt_after(monkeypatch, 1)  # stopped again: only the lines matter
    lines = []
    with reporting(lines.append, bars=False), pytest.raises(KeyboardInterrupt):
        refine_stage(capture, gt, tmp_path / "out", config(smoothness=0.02))
    assert any("work of other inputs or options: ignored" in line for line in lines), lines
    assert not any("resuming" in line for line in lines)


def test_the_state_is_saved_at_level_ends_between_intervals_and_resumes_under_another_interval(capture, tmp_path,
                                                                                            monkeypatch):
    """With a long interval only each level's last iteration is saved (a host copy per iteration costs more than
    the iteration on a GPU); the interval is not part of the checkpoint's key, so a state saved under one interval
    resumes under another to the uninterrupted result."""
    gt = capture / "ground_truth"
    refine_stage(capture, gt, tmp_path / "whole", config())
    interrupt_after(monkeypatch, 1)
    with pytest.raises(KeyboardInterrupt):
        refine_stage(capture, gt, tmp_path / "again", config(checkpoint_every_s=1e9))
    monkeypatch.undo()
    lines = []
    with reporting(lines.append, bars=False):
        refine_stage(capture, gt, tmp_path / "again", config())
    assert any("resuming from" in line and "2 of 4 iterations" in line for line in lines), lines  # the first level's end
    whole, again = outputs(tmp_path / "whole"), outputs(tmp_path / "again")
    assert whole[0] == again[0] and whole[1] == again[1]
    np.testing.assert_array_equal(whole[2], again[2])
