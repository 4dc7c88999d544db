"""Tiled fits (fit/tiles.py): tiles of texels fitted over only the photos that see them, on one device or
several worker threads, give the untiled fit's parameters to the last bit; options that couple texels
are refused."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from texstream.core.errors import ConfigError
from texstream.fit.optim.fitter import FitConfig, initial_guess, run_fit
from texstream.fit.optim.linesearch import LineSearchConfig
from texstream.fit.stream.penalties import PenaltyConfig
from texstream.fit.stream.config import StreamConfig
from texstream.fit.stages.stage import build_problem
from texstream.fit.multi.tile_plan import split_texels, texel_range
from texstream.fit.multi.tiles import WARM_UP_TEXELS, plan_tiles, run_tiled_fit

from conftest import DEVICES

ANY = DEVICES[0]
"""the device of the tests that are not device-parametrised: the first there is (the GPU machine's Warp has
no CPU compiler)"""

SMALL = dict(scale=0.02, photos=10, image_size=40, progress=False)
# small shadow maps keep the CPU ray casts to a fraction of a second; one photo group per pass (the CPU's
# automatic choice, forced on CUDA too) sums each texel's photos in order, the same with or without the
# photos a tile leaves out (they add no sample), so the comparisons below are exact
STREAM = dict(shadow_map_size=48, groups=1)


@pytest.fixture(scope="module")
def scene():
    """(mesh, bake, frames, images, masks) of a small ornament rendered in memory."""
    from conftest import SCENE_DEVICE
    from texstream.capture.synthetic.synth import SynthConfig, render_scene

    sc = render_scene("ornament", SynthConfig(device=SCENE_DEVICE, **SMALL))
    return sc.mesh, sc.bake, sc.frames, sc.images, sc.masks


def fit_config(optimizer="lm", model="lafortune", **stream) -> FitConfig:
    # rel_tol 0: a fixed number of iterations, so the untiled and tiled stopping tests (sums over texels in
    # different orders, equal to ~1e-16 relative) cannot part at a threshold
    return FitConfig(model=model, optimizer=optimizer, max_iterations=6, rel_tol=0.0, sync_every=2,
                     stream=StreamConfig(**STREAM, **stream))


def problem(scene, cfg, device):
    mesh, bake, frames, images, masks = scene
    return build_problem(mesh, bake, frames, images, masks, cfg, device)


@pytest.mark.parametrize("optimizer,model", [("lm", "lafortune"), ("cg", "lafortune"), ("lbfgs", "diffuse"),
                                             ("sd", "diffuse"), ("lm", "radiance")])
def test_tiled_fit_equals_the_untiled_fit_to_the_bit(scene, device, optimizer, model, monkeypatch):
    import texstream.fit.multi.tile_plan as tiles

    monkeypatch.setattr(tiles, "ALL_PHOTOS_FRACTION", 2.0)  # every tile streams only the photos that see it
    cfg = fit_config(optimizer, model)
    whole = problem(scene, cfg, device)
    ref = run_fit(whole, cfg)
    tiled_cfg = dataclasses.replace(cfg, stream=dataclasses.replace(cfg.stream, tiles=3))
    res, report = run_tiled_fit(problem(scene, tiled_cfg, device), tiled_cfg)
    assert report["tiles"] == 3 and sum(report["texels_per_tile"]) == whole.n
    assert min(report["photos_streamed_per_tile"]) < whole.photos.n  # some tile streams a strict subset
    np.testing.assert_array_equal(res.params, ref.params)
    np.testing.assert_array_equal(res.samples, ref.samples)
    assert res.robust_loss == ref.robust_loss and res.robust_scale == ref.robust_scale  # radiance: cauchy, auto scale
    assert len(res.trace) == len(ref.trace)
    # the trace's sums over texels are added per tile, then across tiles: another order of float64 additions
    np.testing.assert_allclose([r["objective"] for r in res.trace], [r["objective"] for r in ref.trace], rtol=1e-12)
    assert [r["samples"] for r in res.trace] == [r["samples"] for r in ref.trace]


def test_tiles_on_two_worker_threads_equal_the_untiled_fit(scene, device):
    """Several devices run one thread each; the same device twice checks that path on any machine."""
    cfg = fit_config()
    ref = run_fit(problem(scene, cfg, device), cfg)
    two = dataclasses.replace(cfg, stream=dataclasses.replace(cfg.stream, tiles=4, devices=f"{device},{device}"))
    res, report = run_tiled_fit(problem(scene, two, device), two)
    assert report["devices"] == [device, device] and report["backend"] == "threads"
    np.testing.assert_array_equal(res.params, ref.params)
    # the modules were loaded by a throwaway fit of a few of tile 0's texels, so no tile went first alone; the
    # tiles' fit is the untiled one's all the same (above)
    assert report["warm_up"]["texels"] == WARM_UP_TEXELS


def test_a_fit_with_a_halo_exchange_keeps_tile_0_first_alone(scene, device):
    """With LM's smoothness the tiles' steps go through other calls (the halo exchange's), which the warm-up does
    not make: tile 0 still steps first alone, and no warm-up is run."""
    cfg = dataclasses.replace(fit_config(), penalties=PenaltyConfig(smooth_weight=0.05))
    tcfg = dataclasses.replace(cfg, stream=dataclasses.replace(cfg.stream, tiles=2, devices=f"{device},{device}"))
    _, report = run_tiled_fit(problem(scene, tcfg, device), tcfg)
    assert report["warm_up"]["texels"] == 0


def test_stopping_test_sums_the_tiles(scene, device):
    """With the default tolerance the tiled fit stops at the untiled fit's iteration, with its parameters."""
    cfg = dataclasses.replace(fit_config(), rel_tol=2e-2, max_iterations=30)
    ref = run_fit(problem(scene, cfg, device), cfg)
    tcfg = dataclasses.replace(cfg, stream=dataclasses.replace(cfg.stream, tiles=2))
    res, _ = run_tiled_fit(problem(scene, tcfg, device), tcfg)
    assert len(ref.trace) < 31  # it stopped early
    assert len(res.trace) == len(ref.trace)
    np.testing.assert_array_equal(res.params, ref.params)


def test_each_tile_gets_every_photo_that_samples_it(scene, device, monkeypatch):
    """The tiles' photo lists hold every photo with a sample of their texels: each tile's own initial-guess
    pass (sample counts, per-texel percentiles) equals the untiled one's for its texels."""
    import texstream.fit.multi.tile_plan as tiles

    monkeypatch.setattr(tiles, "ALL_PHOTOS_FRACTION", 2.0)
    cfg = fit_config(tiles=5)
    whole = problem(scene, cfg, device)
    guess, counts = initial_guess(whole, cfg)
    plan = plan_tiles(whole, cfg)
    assert any(p.size < whole.photos.n for p in plan.photos)  # the split does leave photos out
    from texstream.fit.multi.tiles import tile_problem

    for t, (b, e) in enumerate(plan.bounds):
        g_t, c_t = initial_guess(tile_problem(whole, plan, t, cfg), cfg)
        np.testing.assert_array_equal(c_t, counts[b:e])
        np.testing.assert_array_equal(g_t, guess[b:e])


def test_split_and_texel_range():
    assert split_texels(10, 3).tolist() == [[0, 3], [3, 7], [7, 10]]
    assert split_texels(2, 5).tolist() == [[0, 1], [1, 2]]


def test_texel_range_keeps_neighbours_inside(scene):
    cfg = fit_config()
    whole = problem(scene, cfg, ANY)
    part = texel_range(whole.texels, 100, 200)
    nb = part.neighbors
    inside = (whole.texels.neighbors[100:200] >= 100) & (whole.texels.neighbors[100:200] < 200)
    np.testing.assert_array_equal(nb >= 0, inside)
    np.testing.assert_array_equal(nb[inside] + 100, whole.texels.neighbors[100:200][inside])


@pytest.mark.parametrize("devices", ["", "cpu,cpu"])
def test_smoothness_with_halo_exchange_equals_the_untiled_fit(scene, device, devices):
    """LM's smoothness couples neighbours across tile borders: each tile holds its halo, copied from the owning
    tiles after every iteration, and the fit equals the untiled one to the bit (objectives included)."""
    cfg = dataclasses.replace(fit_config(), penalties=PenaltyConfig(smooth_weight=0.05))
    ref = run_fit(problem(scene, cfg, device), cfg)
    devs = devices.replace("cpu", device)
    tcfg = dataclasses.replace(cfg, stream=dataclasses.replace(cfg.stream, tiles=3, devices=devs))
    res, report = run_tiled_fit(problem(scene, tcfg, device), tcfg)
    assert min(report["halo_texels"]) > 0
    np.testing.assert_array_equal(res.params, ref.params)
    np.testing.assert_allclose([r["objective"] for r in res.trace], [r["objective"] for r in ref.trace], rtol=1e-12)


def test_halo_exchange_is_needed(scene, monkeypatch):
    """Without the exchange (halos held at the start) the smooth fit differs: the test above has teeth."""
    import texstream.fit.multi.tiles as tiles

    cfg = dataclasses.replace(fit_config(), penalties=PenaltyConfig(smooth_weight=0.05))
    ref = run_fit(problem(scene, cfg, ANY), cfg)
    monkeypatch.setattr(tiles.HaloExchange, "__call__", lambda self: None)
    tcfg = dataclasses.replace(cfg, stream=dataclasses.replace(cfg.stream, tiles=3))
    res, _ = run_tiled_fit(problem(scene, tcfg, ANY), tcfg)
    assert not np.array_equal(res.params, ref.params)


@pytest.mark.parametrize("change,option", [
    (dict(linesearch=LineSearchConfig(acceptance="global"), optimizer="cg"), "linesearch.acceptance"),
    (dict(penalties=PenaltyConfig(laplacian_weight=0.1), optimizer="cg"), "penalties.laplacian_weight"),
    (dict(stream=StreamConfig(**STREAM, tiles=2, model_lookup="bilinear")), "stream.model_lookup"),
])
def test_options_that_couple_texels_are_refused(scene, change, option):
    cfg = dataclasses.replace(fit_config(tiles=2), **change)
    with pytest.raises(ConfigError, match=option.replace(".", r"\.")):
        run_tiled_fit(problem(scene, cfg, ANY), cfg)


def test_other_devices_need_resident_photos(scene):
    cfg = fit_config(tiles=2, devices=f"{ANY},{ANY}", photo_residency="host", photos_per_window=4)
    with pytest.raises(ConfigError, match="photo_residency device"):
        run_tiled_fit(problem(scene, cfg, ANY), cfg)


def test_unknown_device_is_refused(scene):
    cfg = fit_config(tiles=2, devices=f"{ANY},tpu:0")
    with pytest.raises(ConfigError, match="tpu:0"):
        run_tiled_fit(problem(scene, cfg, ANY), cfg)


@pytest.fixture(scope="module")
def capture_dir(tmp_path_factory):
    """The small ornament written as a capture folder (float EXR photos, masks)."""
    from conftest import SCENE_DEVICE
    from texstream.capture.synthetic.synth import SynthConfig, synthesize

    out = tmp_path_factory.mktemp("ornament") / "capture"
    synthesize("ornament", out, SynthConfig(device=SCENE_DEVICE, preview=False, **SMALL))
    return out


@pytest.mark.parametrize("residency", ["host", "disk"])
def test_tiles_over_streamed_photos_equal_the_untiled_fit(capture_dir, residency):
    """Photos streamed a window per pass (host memory, or decoded from the files): tiles that stream every photo
    share the parent's windows, so the sums and the fit are the untiled one's."""
    from texstream.capture.capture_json import read_capture
    from texstream.fit.stages.stage import load_geometry, photo_files

    cap = read_capture(capture_dir)
    mesh, bake = load_geometry(capture_dir / "ground_truth", 64, "cpu")
    cfg = fit_config(photo_residency=residency, photos_per_window=4)
    ref = run_fit(build_problem(mesh, bake, cap.frames, photo_files(cap, cap.frames), None, cfg, "cpu"), cfg)
    tcfg = dataclasses.replace(cfg, stream=dataclasses.replace(cfg.stream, tiles=2))
    prob = build_problem(mesh, bake, cap.frames, photo_files(cap, cap.frames), None, tcfg, "cpu")
    res, report = run_tiled_fit(prob, tcfg)
    assert report["photos_streamed_per_tile"] == [prob.photos.n] * 2
    np.testing.assert_array_equal(res.params, ref.params)


def test_texstream_fit_in_tiles_records_them(capture_dir, tmp_path, capsys):
    """``texstream fit --stream.tiles 2 --stream.devices cpu,cpu`` fits in tiles and model.json says how."""
    import json

    from texstream.pipelines.cli import main

    cap = capture_dir
    out = tmp_path / "model"
    code = main(["fit", str(cap), "--mesh", str(cap / "ground_truth"), "-o", str(out), "--texture-size", "64",
                 "--renders", "0", "--max-iterations", "2", "--stream.shadow-map-size", "48",
                 "--stream.tiles", "2", "--stream.devices", "cpu,cpu", "--stream.photo-residency", "device"])
    assert code == 0, capsys.readouterr().err
    tiles = json.loads((out / "model.json").read_text())["tiles"]
    assert tiles["tiles"] == 2 and tiles["devices"] == ["cpu", "cpu"] and tiles["backend"] == "threads"


@pytest.mark.parametrize("smooth", [0.0, 0.05])
def test_tiles_on_two_gpus_equal_the_untiled_fit(scene, smooth):
    """cuda:0 and cuda:1, one thread each (photos and maps copied device to device, halos exchanged between
    the GPUs with smoothness): the one-GPU fit's parameters to the bit."""
    import warp as wp

    if wp.get_cuda_device_count() < 2:
        pytest.skip("needs two CUDA devices (run on the two-GPU machine)")
    cfg = dataclasses.replace(fit_config(), penalties=PenaltyConfig(smooth_weight=smooth))
    ref = run_fit(problem(scene, cfg, "cuda:0"), cfg)
    two = dataclasses.replace(cfg, stream=dataclasses.replace(cfg.stream, tiles=3, devices="cuda:0,cuda:1"))
    res, report = run_tiled_fit(problem(scene, two, "cuda:0"), two)
    assert report["devices"] == ["cuda:0", "cuda:1"]
    np.testing.assert_array_equal(res.params, ref.params)


def test_visibility_launched_in_chunks_of_photos_equals_one_launch(scene, monkeypatch):
    import texstream.fit.multi.tile_plan as tiles

    cfg = fit_config(tiles=4)
    whole = problem(scene, cfg, ANY)
    bounds = split_texels(whole.n, 4)
    one = tiles.tile_photo_visibility(whole, bounds)
    monkeypatch.setattr(tiles, "MAX_LAUNCH_THREADS", 3 * whole.n)  # 3 photos a launch
    np.testing.assert_array_equal(tiles.tile_photo_visibility(whole, bounds), one)
    assert one.any(axis=1).all() and not one.all()
