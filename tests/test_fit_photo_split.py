"""Photos split over devices (fit/photo_split.py): each device streams a run of the photos over every texel
and the first adds their sums. The split fit equals one device's fit with one photo group per device
part to the last bit, and the one-group fit to float64 rounding; the initial guess is exact."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from texstream.core.errors import ConfigError
from texstream.fit.optim.fitter import FitConfig, initial_guess, run_fit
from texstream.fit.stream.penalties import PenaltyConfig
from texstream.fit.common import setup
from texstream.fit.multi.photo_split import DevicePhotos, check_split_devices, split_bounds
from texstream.fit.stream.config import StreamConfig
from texstream.fit.stages.stage import build_problem

from conftest import DEVICES

SMALL = dict(scale=0.02, photos=10, image_size=40, progress=False)
STREAM = dict(shadow_map_size=48)  # small shadow maps: the CPU's ray casts take a fraction of a second


@pytest.fixture(scope="module")
def scene():
    """(mesh, bake, frames, images, masks) of a small ornament rendered in memory."""
    from conftest import SCENE_DEVICE
    from texstream.capture.synthetic.synth import SynthConfig, render_scene

    sc = render_scene("ornament", SynthConfig(device=SCENE_DEVICE, **SMALL))
    return sc.mesh, sc.bake, sc.frames, sc.images, sc.masks


def fit_config(optimizer="lm", model="lafortune", smooth=0.0, **stream) -> FitConfig:
    # rel_tol 0: a fixed number of iterations, so that stopping tests on objectives equal to rounding
    # cannot part at a threshold
    return FitConfig(model=model, optimizer=optimizer, max_iterations=6, rel_tol=0.0, sync_every=2,
                     penalties=PenaltyConfig(smooth_weight=smooth), stream=StreamConfig(**STREAM, **stream))


def split(cfg: FitConfig, devices: str) -> FitConfig:
    return dataclasses.replace(cfg, stream=dataclasses.replace(cfg.stream, devices=devices, device_split="photos"))


def problem(scene, cfg, device):
    mesh, bake, frames, images, masks = scene
    return build_problem(mesh, bake, frames, images, masks, cfg, device)


def test_split_bounds():
    assert split_bounds(10, 2) == [(0, 5), (5, 10)]
    assert split_bounds(10, 3) == [(0, 4), (4, 8), (8, 10)]
    assert split_bounds(2, 3) == [(0, 1), (1, 2)]  # no device without photos


@pytest.mark.parametrize("optimizer,model,smooth,lookup", [("lm", "lafortune", 0.0, "texel"),
                                                           ("lm", "lafortune", 0.05, "texel"),
                                                           ("lm", "lafortune", 0.0, "bilinear"),
                                                           ("cg", "lafortune", 0.0, "texel"),
                                                           ("lbfgs", "diffuse", 0.0, "texel"),
                                                           ("lm", "radiance", 0.0, "texel")])
def test_split_fit_equals_the_one_device_fit_with_a_group_per_part(scene, device, optimizer, model, smooth, lookup):
    """Two parts on one device (the path of two devices, the copies within one) with one group each sum
    every texel in the order of one device with two groups: the same parameters to the last bit (with the
    renderer's lookup too, whose held neighbours each part refreshes)."""
    one = fit_config(optimizer, model, smooth, groups=2, model_lookup=lookup)
    ref = run_fit(problem(scene, one, device), one)
    two = split(fit_config(optimizer, model, smooth, groups=1, model_lookup=lookup), f"{device},{device}")
    pr = problem(scene, two, device)
    assert isinstance(pr.photos, DevicePhotos) and [p.n for p in pr.photos.parts] == [5, 5]
    assert len(pr.peers) == 1 and pr.rows == 2
    res = run_fit(pr, two)
    np.testing.assert_array_equal(res.params, ref.params)
    np.testing.assert_array_equal(res.samples, ref.samples)
    assert res.robust_scale == ref.robust_scale  # radiance: the Cauchy loss's automatic scale from the pass
    assert [r["objective"] for r in res.trace] == [r["objective"] for r in ref.trace]


def test_the_copies_between_devices_on_one_device(scene, device, monkeypatch):
    """The path that copies parameters to another device and partial sums back (mirrors, offsets, the
    synchronisations), taken on one device by telling the problem its peer is elsewhere: still the
    two-group fit to the last bit (the two-GPU test runs it between devices)."""
    from texstream.fit.stream.problem import StreamProblem

    monkeypatch.setattr(StreamProblem, "_same_device", lambda self, peer: False)
    one = fit_config(smooth=0.05, groups=2, model_lookup="bilinear")
    ref = run_fit(problem(scene, one, device), one)
    two = split(fit_config(smooth=0.05, groups=1, model_lookup="bilinear"), f"{device},{device}")
    pr = problem(scene, two, device)
    res = run_fit(pr, two)
    assert set(pr.peers[0]._mirrors) == {"params", "active", "lookup_params"}  # copies were made
    np.testing.assert_array_equal(res.params, ref.params)
    np.testing.assert_array_equal(initial_guess(pr, two)[0], initial_guess(problem(scene, one, device), one)[0])


def test_split_fit_matches_the_one_group_fit(scene, device):
    """Against one device with one group the sums associate differently. In float64 sums (what ``auto``
    picks above 1,000 photos) that is ~1e-16 relative per sum, carried through 6 LM iterations; the
    parameters are stored in float32, so a rounding difference can move a value by an ulp of float32:
    1e-5 relative leaves that room and nothing more."""
    cfg = fit_config(groups=1, accumulate="fp64")
    ref = run_fit(problem(scene, cfg, device), cfg)
    res = run_fit(problem(scene, split(cfg, f"{device},{device}"), device), split(cfg, f"{device},{device}"))
    np.testing.assert_allclose(res.params, ref.params, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose([r["objective"] for r in res.trace], [r["objective"] for r in ref.trace], rtol=1e-9)


def test_split_initial_guess_is_exact(scene, device):
    """The low percentile merges exactly from each part's 4 smallest samples, for every rank, over 3 parts."""
    for rank in (0, 1, 3):
        cfg = dataclasses.replace(fit_config(), init_rank=rank)
        guess, counts = initial_guess(problem(scene, cfg, device), cfg)
        three = split(cfg, ",".join([device] * 3))
        pr = problem(scene, three, device)
        assert len(pr.peers) == 2
        g3, c3 = initial_guess(pr, three)
        np.testing.assert_array_equal(c3, counts)
        np.testing.assert_array_equal(g3, guess)


def test_split_photos_subset_and_refusals(scene, device):
    cfg = split(fit_config(), f"{device},{device}")
    pr = problem(scene, cfg, device)
    sub = pr.photos.subset([0, 2, 6, 9])
    assert [p.n for p in sub.parts] == [2, 2] and sub.n == 4 and sub.bounds == [(0, 2), (2, 4)]
    assert sub.frames == [pr.photos.frames[k] for k in (0, 2, 6, 9)]
    rest = pr.photos.subset([7, 8])  # the second part's photos only: on the same device, one part
    assert [p.n for p in rest.parts] == [2] and rest.frames == pr.photos.frames[7:9]
    with pytest.raises(ConfigError, match="no tiles"):
        from texstream.fit.multi.tiles import tiled

        tiled(split(fit_config(tiles=2), f"{device},{device}"))
    with pytest.raises(ConfigError, match="stays on the devices|stay on the devices"):
        problem(scene, split(fit_config(photo_residency="host"), f"{device},{device}"), device)


def test_split_photos_need_the_fit_device_first_and_one_device_kind(scene, device, monkeypatch):
    """The device list's refusals, on any machine: the list is checked by name before any device is used
    (the set-up is then told that the machine has the devices listed, which it checks first)."""
    with pytest.raises(ConfigError, match="starts with cuda:1, not the fit's device cuda:0"):
        check_split_devices(["cuda:1", "cuda:0"], "cuda:0")
    with pytest.raises(ConfigError, match="mixes the CPU and CUDA devices"):
        check_split_devices(["cpu", "cuda:0"], "cpu")
    check_split_devices(["cuda:0", "cuda:1"], "cuda:0")
    check_split_devices(["cpu", "cpu"], "cpu")
    other = "cuda:0" if device == "cpu" else "cpu"
    monkeypatch.setattr(setup, "parse_devices", lambda devices, default: [d.strip() for d in devices.split(",")])
    with pytest.raises(ConfigError, match=f"starts with {other}, not the fit's device {device}"):
        problem(scene, split(fit_config(), f"{other},{device}"), device)


@pytest.mark.skipif(sum(d.startswith("cuda") for d in DEVICES) < 1, reason="needs CUDA")
def test_split_over_two_gpus_equals_one_gpu_with_two_groups():
    import warp as wp

    if wp.get_cuda_device_count() < 2:
        pytest.skip("needs two GPUs")
    from texstream.capture.synthetic.synth import SynthConfig, render_scene

    sc = render_scene("ornament", SynthConfig(device="cuda:0", **SMALL))
    scene = (sc.mesh, sc.bake, sc.frames, sc.images, sc.masks)
    for smooth, lookup in ((0.0, "texel"), (0.05, "texel"), (0.0, "bilinear")):
        one = fit_config(smooth=smooth, groups=2, model_lookup=lookup)
        ref = run_fit(problem(scene, one, "cuda:0"), one)
        two = split(fit_config(smooth=smooth, groups=1, model_lookup=lookup), "cuda:0,cuda:1")
        pr = problem(scene, two, "cuda:0")
        assert pr.peers[0].device == "cuda:1"
        np.testing.assert_array_equal(run_fit(pr, two).params, ref.params)


def test_fit_stage_with_split_photos(tmp_path):
    """The whole stage (shared materials judged on a validation split of the photos, the traced polish,
    held-out photos) with the photos split over two parts: the model of the unsplit stage, to float
    rounding of the sums' order (the photos are few: float32 sums; a texel's step accepted or not near a
    tie can differ, so the maps are compared by their fit, 0.01 dB)."""
    import json

    from conftest import SCENE_DEVICE, tiny_sphere_capture
    from texstream.fit.stages.stage import FitStageConfig, fit_stage

    capture = tiny_sphere_capture(tmp_path, photos=12)
    gt = capture / "ground_truth"
    base = FitStageConfig(device=SCENE_DEVICE, renders=1, holdout_every=4,
                          fit=FitConfig(max_iterations=8, stream=StreamConfig(shadow_map_size=48)))
    splitcfg = dataclasses.replace(base, fit=split(base.fit, f"{SCENE_DEVICE},{SCENE_DEVICE}"))
    fit_stage(capture, gt, tmp_path / "one", base, progress=False)
    fit_stage(capture, gt, tmp_path / "two", splitcfg, progress=False)
    one, two = (json.loads((tmp_path / name / "model.json").read_text()) for name in ("one", "two"))
    assert two["photos"]["residency_reason"].startswith("split over ")
    assert two["photos"]["fitted"] == one["photos"]["fitted"]
    for got, want in ((two["final"]["psnr_db"], one["final"]["psnr_db"]),
                      (two["heldout"]["pooled_psnr_db"], one["heldout"]["pooled_psnr_db"]),
                      (two["heldout"]["worst_psnr_db"], one["heldout"]["worst_psnr_db"])):
        assert abs(got - want) < 0.01, (got, want)


def test_split_serves_the_options_tiles_refuse(scene, device):
    """Every texel is stepped on the first device, so what couples texels works with the photos split: CG
    with the Laplacian penalty and the global line search, to the two-group fit's bits."""
    from texstream.fit.optim.linesearch import LineSearchConfig

    def cfg(groups, **extra):
        c = fit_config("cg", groups=groups, **extra)
        return dataclasses.replace(c, penalties=PenaltyConfig(laplacian_weight=1e-3),
                                   linesearch=LineSearchConfig(acceptance="global"))

    ref = run_fit(problem(scene, cfg(2), device), cfg(2))
    two = split(cfg(1), f"{device},{device}")
    np.testing.assert_array_equal(run_fit(problem(scene, two, device), two).params, ref.params)


def test_parts_build_their_meshes_one_at_a_time(scene, device, monkeypatch):
    """Warp's BVH build sorts in a buffer shared by a device's builds, held without a lock: two parts set
    up at once on threads of their own once corrupted each other's BVH on a GPU (a hung set-up, illegal
    memory accesses). Their builds must not overlap: here each build takes 50 ms (a sleep, so that two
    threads would overlap if nothing serialised them), and none may start before the other has finished."""
    import threading
    import time

    import warp as wp

    real, lock = wp.Mesh, threading.Lock()
    running, most = [0], [0]

    def slow_mesh(**kwargs):
        with lock:
            running[0] += 1
            most[0] = max(most[0], running[0])
        time.sleep(0.05)
        try:
            return real(**kwargs)
        finally:
            with lock:
                running[0] -= 1

    monkeypatch.setattr(wp, "Mesh", slow_mesh)
    pr = problem(scene, split(fit_config(), f"{device},{device},{device}"), device)
    assert len(pr.photos.parts) == 3
    assert most[0] == 1
