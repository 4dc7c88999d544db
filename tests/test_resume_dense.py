"""Dense stereo, interrupted after some photos' depth maps, resumes from the ones it kept (geometry/mvs.py
``work_dir``) to the uninterrupted points to the last bit; depth maps of other options are ignored with a line.

The interruption is raised in-process from the checkpoint's write, right after the N-th depth map is saved:
the state a SIGKILL anywhere before the next save leaves (work after a save is lost either way), without a
subprocess's start-up. scripts/kill_resume.py kills a real ``texstream run`` with SIGKILL at random times."""

from __future__ import annotations

import numpy as np
import pytest

from texstream.capture.capture_json import read_capture
from texstream.core.progress import reporting
from texstream.geometry.hull import load_masks
from texstream.geometry.mesh_io import load_mesh
from texstream.geometry.mvs import MvsConfig, capture_dense_points

from conftest import SCENE_DEVICE, interrupt_after


@pytest.fixture(scope="module")
def sphere(tmp_path_factory):
    from texstream.capture.synthetic.synth import SynthConfig, synthesize

    root = tmp_path_factory.mktemp("dense_resume") / "cap"
    # 12 photos of 64x64: the fewest with neighbours in the angle range and matches on the blotchy albedo
    synthesize("textured_sphere", root, SynthConfig(photos=12, image_size=64, progress=False, preview=False,
                                                    device=SCENE_DEVICE))
    cap = read_capture(root)
    return cap, load_masks(cap), load_mesh(root / "ground_truth" / "mesh.obj").bbox()


def test_interrupted_dense_stereo_resumes_to_the_same_points(sphere, tmp_path, monkeypatch):
    cap, masks, bounds = sphere
    cfg = MvsConfig(depths=32)
    whole = capture_dense_points(cap, masks, bounds, cfg, SCENE_DEVICE)
    assert len(whole.points) > 100  # the scene gives dense stereo something to match
    work = tmp_path / "work"
    interrupt_after(monkeypatch, 3)
    with pytest.raises(KeyboardInterrupt):
        capture_dense_points(cap, masks, bounds, cfg, SCENE_DEVICE, work_dir=work)
    assert len(list(work.glob("depth_*.npz"))) == 3
    monkeypatch.undo()
    lines = []
    with reporting(lines.append, bars=False):
        again = capture_dense_points(cap, masks, bounds, cfg, SCENE_DEVICE, work_dir=work)
    assert any("resuming dense stereo" in line and "3 of 12 photos" in line for line in lines), lines
    np.testing.assert_array_equal(again.points, whole.points)
    np.testing.assert_array_equal(again.normals, whole.normals)
    for a, b in zip(again.depth_maps, whole.depth_maps):
        np.testing.assert_array_equal(a, b)
    assert [v.get("matched") for v in again.report["views"]] == [v.get("matched") for v in whole.report["views"]]

    lines = []
    interrupt_after(monkeypatch, 1)  # only the first line matters here
    with reporting(lines.append, bars=False), pytest.raises(KeyboardInterrupt):
        capture_dense_points(cap, masks, bounds, MvsConfig(depths=33), SCENE_DEVICE, work_dir=work)
    assert any("work of other inputs or options: ignored" in line for line in lines), lines
    assert not any("resuming" in line for line in lines)
