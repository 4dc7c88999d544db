"""Shared fixtures: devices (cpu always, cuda when present), data folder, tolerance reasons."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def _devices() -> list:
    import warp as wp

    wp.config.quiet = True
    wp.init()
    # the GPU machine's warp ships without the CPU compiler: there only CUDA is tested
    devs = ["cpu"] if wp.is_cpu_available() else []
    if wp.get_cuda_device_count() > 0:
        devs.append("cuda:0")
    return devs


DEVICES = _devices()
# where module fixtures render their synthetic scenes (numpy results, shared by every device)
SCENE_DEVICE = DEVICES[0]


@pytest.fixture(params=DEVICES)
def device(request) -> str:
    """Every device-parametrised test runs on the CPU, and on CUDA when a GPU is present."""
    return request.param


def cuda_device_or_skip() -> str:
    if "cuda:0" not in DEVICES:
        pytest.skip("no CUDA device on this machine (CI has none; run on the GPU machine)")
    return "cuda:0"


@pytest.fixture(scope="session")
def data_dir() -> Path:
    """Third-party data (../shared/data by default, or $TEXSTREAM_DATA)."""
    return Path(os.environ.get("TEXSTREAM_DATA", ROOT.parent / "shared" / "data")).resolve()


def need_data(data_dir: Path, sub: str) -> Path:
    p = data_dir / sub
    if not p.exists():
        pytest.skip(f"{p} absent: set TEXSTREAM_DATA to the folder holding {sub}/ (see ../shared/data/README.md)")
    return p


def pose_errors(got, truth):
    """Per registered frame of capture ``got``: camera centre error as a fraction of ``truth``'s camera
    ring diameter, and rotation error in degrees."""
    import numpy as np

    gt = {f.name: f for f in truth.frames}
    c = np.stack([f.center for f in truth.frames])
    diameter = 2 * np.mean(np.linalg.norm(c - c.mean(0), axis=1))
    cen, rot = [], []
    for f in got.frames:
        g = gt[f.name]
        cen.append(np.linalg.norm(f.center - g.center) / diameter)
        d = f.R @ g.R.T
        rot.append(np.degrees(np.arccos(np.clip((np.trace(d) - 1) / 2, -1, 1))))
    return np.array(cen), np.array(rot)


def tiny_sphere_capture(root: Path, photos: int, image_size: int = 40) -> Path:
    """A small synthetic sphere capture (``root/cap``, with its ground-truth atlas) for stage tests."""
    from texstream.capture.synthetic.synth import SynthConfig, synthesize

    synthesize("sphere", root / "cap", SynthConfig(scale=0.05, photos=photos, image_size=image_size, progress=False,
                                                   preview=False, device=SCENE_DEVICE))
    return root / "cap"


def interrupt_after(monkeypatch, saves: int) -> None:
    """Stop a stage with KeyboardInterrupt right after its ``saves``-th checkpoint write: the state a SIGKILL
    anywhere before the next write leaves (what it did after the last save is lost either way)."""
    from texstream.core.checkpoint import StageCheckpoint

    real, calls = StageCheckpoint.write_arrays, []

    def write_then_stop(self, name, **arrays):
        real(self, name, **arrays)
        calls.append(name)
        if len(calls) == saves:
            raise KeyboardInterrupt

    monkeypatch.setattr(StageCheckpoint, "write_arrays", write_then_stop)
