"""Tiles as Ray actors (fit/tiles_ray.py) on a local Ray cluster of two CPU workers: each actor reads its
photos from the capture folder and builds its own maps, and the fit equals the one-process fit to the bit."""

from __future__ import annotations

import dataclasses
import os

import numpy as np
import pytest
import ray

from texstream.core.errors import ConfigError
from texstream.fit.optim.fitter import FitConfig, run_fit
from texstream.fit.stream.penalties import PenaltyConfig
from texstream.fit.stream.config import StreamConfig
from texstream.fit.stages.stage import build_problem, photo_files
from texstream.fit.multi.tiles import run_tiled_fit

SMALL = dict(scale=0.02, photos=10, image_size=40, progress=False)


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    """(capture, mesh, bake) of the small ornament written as a capture folder (float EXR photos, masks)."""
    from conftest import SCENE_DEVICE
    from texstream.capture.capture_json import read_capture
    from texstream.capture.synthetic.synth import SynthConfig, synthesize
    from texstream.fit.stages.stage import load_geometry

    out = tmp_path_factory.mktemp("ornament") / "capture"
    synthesize("ornament", out, SynthConfig(device=SCENE_DEVICE, preview=False, **SMALL))
    cap = read_capture(out)
    mesh, bake = load_geometry(out / "ground_truth", 64, "cpu")
    return cap, mesh, bake


@pytest.fixture(scope="module")
def local_cluster():
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield
    ray.shutdown()


def problem(capture, cfg):
    cap, mesh, bake = capture
    return build_problem(mesh, bake, cap.frames, photo_files(cap, cap.frames), None, cfg, "cpu")


@pytest.mark.parametrize("smooth", [0.0, 0.05])
def test_ray_tiles_equal_the_one_process_fit(capture, local_cluster, smooth, monkeypatch):
    """With LM's smoothness the actors' halos go through the object store after every iteration."""
    import texstream.fit.multi.tile_plan as tiles

    monkeypatch.setattr(tiles, "ALL_PHOTOS_FRACTION", 2.0)  # each actor reads only the photos that see its tile
    # one photo group and a fixed iteration count: the conditions of the exact comparison (test_fit_tiles.py)
    cfg = FitConfig(optimizer="lm", max_iterations=4, rel_tol=0.0, sync_every=2,
                    penalties=PenaltyConfig(smooth_weight=smooth), stream=StreamConfig(shadow_map_size=48, groups=1))
    ref = run_fit(problem(capture, cfg), cfg)
    # three tiles on two CPUs: the actors share them (every actor must be placed for the lockstep)
    rcfg = dataclasses.replace(cfg, stream=dataclasses.replace(cfg.stream, tiles=3, tile_backend="ray"))
    res, report = run_tiled_fit(problem(capture, rcfg), rcfg)
    assert report["backend"] == "ray" and report["tiles"] == 3
    np.testing.assert_array_equal(res.params, ref.params)
    np.testing.assert_array_equal(res.samples, ref.samples)


def test_ray_needs_the_photos_as_files(capture, local_cluster):
    cap, mesh, bake = capture
    from texstream.fit.stages.stage import load_photos

    images, masks = load_photos(cap, cap.frames)
    cfg = FitConfig(max_iterations=1, stream=StreamConfig(shadow_map_size=48, tiles=2, tile_backend="ray"))
    prob = build_problem(mesh, bake, cap.frames, images, masks, cfg, "cpu")
    with pytest.raises(ConfigError, match="capture's files"):
        run_tiled_fit(prob, cfg)


def test_a_photo_a_worker_cannot_read_fails_naming_it(capture, local_cluster, tmp_path):
    """A photo that turned unreadable on the shared storage after the driver's set-up: the actor's InputError
    comes back as itself (one line naming the file), not as Ray's traceback."""
    import shutil

    from texstream.capture.capture_json import read_capture
    from texstream.core.errors import InputError

    cap, mesh, bake = capture
    copy = tmp_path / "capture"
    shutil.copytree(cap.root, copy)
    cap2 = read_capture(copy)
    cfg = FitConfig(max_iterations=1, stream=StreamConfig(shadow_map_size=48, tiles=2, tile_backend="ray"))
    prob = build_problem(mesh, bake, cap2.frames, photo_files(cap2, cap2.frames), None, cfg, "cpu")
    bad = cap2.image_path(cap2.frames[3])
    bad.write_bytes(bad.read_bytes()[:100])
    with pytest.raises(InputError, match=bad.name):
        run_tiled_fit(prob, cfg)
