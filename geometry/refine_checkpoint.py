"""The photometric refinement's checkpoint: after an iteration of the levels (at most every ``checkpoint_every_s``
seconds, and at each level's end), what the next one reads.

An iteration of :meth:`~texstream.geometry.refine.PhotometricRefinement.run` recomputes the colours, the depth
maps and every scratch array from the state kept here (poses with their damping, the welded vertices'
displacements, bases, directions and positions with theirs, the counts of kept steps, the trace so far and
the starting residual), so a rerun resumes after the last finished iteration and ends with the same result,
to the bit, as an uninterrupted run on the same device: the BVH is refitted from the same topology and points,
and every kernel reads the same inputs. The shading normals and the intensity iterations after the levels (known
lights) are not checkpointed: a kill during them resumes after the last level's iteration.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from texstream.capture.capture_json import Capture
from texstream.core.checkpoint import StageCheckpoint, files_signature, inputs_key, work_dir_for
from texstream.core.config import config_to_dict
from texstream.render.camera import ImageInfo, struct_array

STATE_FILE = "levels.npz"
START_FILE = "start.json"
DECISION_FILE = "finer_levels.json"
_ARRAYS = ("disp", "base", "direction", "welded_points", "pose_damping", "pose_accepted", "disp_damping",
           "disp_accepted")


def refine_checkpoint(capture: Capture, geometry: Path, out: Path, cfg, device: str, log=None) -> StageCheckpoint:
    """The refine stage's work folder beside ``out``, keyed by the photos, masks, capture.json, mesh and bake
    it reads (paths, sizes, modification times), its options and the device (another device's arithmetic
    gives other bits); its lines go to ``log`` when given (``texstream refine`` prints), else the phase lines."""
    files = [capture.root / "capture.json", geometry / "mesh.obj", geometry / "bake.npz"]
    for f in capture.frames:
        files.append(capture.image_path(f))
        mask = capture.mask_path(f)
        if mask is not None:
            files.append(mask)
    options = config_to_dict(cfg)
    options.pop("checkpoint_every_s", None)  # when the state is saved, not what it is: a checkpoint resumes either way
    options.pop("threads", None)  # the same bits on any number
    key = inputs_key("refine", files_signature(files), options, device)
    return StageCheckpoint(work_dir_for(out, "refine"), key, "refine",
                           None if log is None else (lambda message: log(f"  refine: {message}")))


def save_state(job, ck: StageCheckpoint, step: int, history) -> None:
    """The state after ``step`` iterations of the levels (``history``: the device trace rows)."""
    ck.write_arrays(STATE_FILE, step=np.array(step), level=np.array(job.level), infos=job.infos.numpy(),
                    history=history.numpy()[:step],
                    **{name: getattr(job, name).numpy() for name in _ARRAYS})


def save_start(ck: StageCheckpoint, start: dict) -> None:
    ck.write_json(START_FILE, start)


def save_decision(ck: StageCheckpoint, finer: dict) -> None:
    """Whether the finer levels run, and why (refine_levels.coarse_moved), taken once after the coarse level."""
    ck.write_json(DECISION_FILE, finer)


def read_decision(ck: StageCheckpoint) -> dict:
    return ck.read_json(DECISION_FILE)


def restore_state(job, ck: StageCheckpoint, history) -> tuple[int, dict] | None:
    """Open the work folder (once the inputs passed their checks: a refused input leaves none); (iterations
    done, starting residual) of a saved state, put back into ``job`` and ``history``; None when there is none
    (a fresh work folder, or one killed before its first iteration finished)."""
    if not ck.open():
        return None
    start = ck.read_json(START_FILE)
    state = ck.read_arrays(STATE_FILE)
    if start is None or state is None:
        return None
    step = int(state["step"])
    for name in _ARRAYS:
        getattr(job, name).assign(state[name])
    job.infos = struct_array(state["infos"], ImageInfo, job.device)
    job.level = int(state["level"])  # the cameras' pyramid level (job.set_level rescales them from it)
    if step:
        rows = history.numpy()
        rows[:step] = state["history"]
        history.assign(rows)
    return step, start
