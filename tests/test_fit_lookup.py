"""The renderer's texture lookup in the fit (``StreamConfig.model_lookup`` "bilinear").

A filtered sample's taps land around the texel's centre, where the renderer blends the BRDFs of
the four texels around each tap (render/kernels.py). With the lookup the fit's model does the
same, its neighbours held at the values of the last refresh, so each texel's objective stays its
own: derivatives are checked per texel against finite differences in fp64 with the neighbours
held at other values than the texel's parameters; the synthetic ornament checks that the truth
then explains its own noise-free photos far better than the seed's per-texel model does.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import warp as wp

from texstream.capture.synthetic.synth import SynthConfig, render_scene
from texstream.fit.optim.fitter import FitConfig, run_fit
from texstream.render.layout import ModelLayout
from texstream.fit.optim.base import FitState
from texstream.fit.stream.config import StreamConfig
from texstream.fit.stream.problem import StreamProblem
from texstream.fit.stages.stage import build_problem
from texstream.core.errors import ConfigError

from conftest import SCENE_DEVICE
from test_fit_gradients import (assert_full_dhd_matches_second_difference, assert_gradient_matches_finite_differences,
                                evaluate, plane_problem, random_params)


def held_problem(device, layout, seed, taps="plane"):
    """A plane problem with the lookup on, parameters p and neighbours held at other values."""
    prob, rng = plane_problem(device, layout, seed=seed, lookup="bilinear", taps=taps)
    p = random_params(layout, prob.n, rng)
    held = random_params(layout, prob.n, rng)
    prob.refresh_lookup(prob.new_storage(held))
    return prob, rng, p, held


TAPS = ["plane", "mesh"]
LAYOUTS = [ModelLayout(), ModelLayout(n_lobes=2, anisotropic=True)]


@pytest.mark.parametrize("taps", TAPS)
@pytest.mark.parametrize("layout", LAYOUTS, ids=["iso", "aniso_2lobes"])
def test_lookup_gradient_matches_finite_differences(device, layout, taps):
    prob, rng, p, _ = held_problem(device, layout, seed=5, taps=taps)
    # the texels' own parameters vary, the held neighbours do not: per-texel derivatives
    assert_gradient_matches_finite_differences(prob, layout, p)


@pytest.mark.parametrize("layout", LAYOUTS, ids=["iso", "aniso_2lobes"])
def test_traced_taps_gradient_matches_finite_differences(device, layout):
    """Traced taps with the texel's own BRDF at every tap (no lookup): the anisotropic lobes read
    the hit's tangent frame (the face's UV tangent), not the texel's."""
    prob, rng = plane_problem(device, layout, seed=9, taps="mesh")
    assert_gradient_matches_finite_differences(prob, layout, random_params(layout, prob.n, rng))


@pytest.mark.parametrize("taps", TAPS)
def test_lookup_dhd_matches_second_difference(device, taps):
    layout = ModelLayout()
    prob, rng, p, _ = held_problem(device, layout, seed=6, taps=taps)
    assert_full_dhd_matches_second_difference(prob, p, rng)


@pytest.mark.parametrize("taps", TAPS)
def test_lookup_lm_pass_matches_the_gradient_pass(device, taps):
    layout = ModelLayout()
    prob, _, p, _ = held_problem(device, layout, seed=7, taps=taps)
    n = prob.n
    f_lm, g_lm = prob.new_scalar(), prob.new_vec()
    jtj = wp.zeros(n, dtype=prob.mat, device=device)
    prob.evaluate_lm(prob.new_storage(p), f_lm, g_lm, jtj, wp.zeros(n, dtype=wp.vec4d, device=device))
    f0, g0, _, _ = evaluate(prob, p)
    # the same fp64 terms summed in the same order: rounding only
    np.testing.assert_allclose(f_lm.numpy(), f0, rtol=1e-12)
    np.testing.assert_allclose(g_lm.numpy()[:, :layout.n_params], g0, rtol=1e-12, atol=1e-14 * np.abs(g0).max())


def test_lookup_reads_the_held_neighbours(device):
    """The held values enter the objective (the lookup is live), the texel mode ignores them, and
    holding the neighbours at the texels' own parameters differs from the texel mode only by the
    blend of different neighbours (so both agree on a uniform texture)."""
    layout = ModelLayout()
    prob, rng, p, held = held_problem(device, layout, seed=8)
    f_held = evaluate(prob, p)[0]
    prob.refresh_lookup(prob.new_storage(p))
    f_self = evaluate(prob, p)[0]
    assert np.all(np.abs(f_held - f_self) > 1e-9 * np.abs(f_self))
    uniform = np.tile(p[:1], (prob.n, 1))
    prob.refresh_lookup(prob.new_storage(uniform))
    texel, _ = plane_problem(device, layout, seed=8)
    # a uniform texture blends one BRDF with itself: the two modes see the same model, up to the
    # neighbours' share, which is evaluated in float32 as the renderer does (measured 5e-8 relative)
    np.testing.assert_allclose(evaluate(prob, uniform)[0], evaluate(texel, uniform)[0], rtol=1e-6)
    # the partition of unity holds at the grid's border too (clamped lookups): no sample lost or gained
    assert evaluate(prob, uniform)[3][:, 0].sum() == pytest.approx(evaluate(texel, uniform)[3][:, 0].sum())


def test_lookup_config_errors(device):
    layout = ModelLayout()
    with pytest.raises(ConfigError, match="model_lookup bilinear needs filtered"):
        plane_problem(device, layout, sampling="point", lookup="bilinear")
    with pytest.raises(ConfigError, match="model_lookup 'nearest' unknown"):
        plane_problem(device, layout, lookup="nearest")
    with pytest.raises(ConfigError, match="lookup_refresh_every"):
        prob, rng = plane_problem(device, layout, lookup="bilinear")
        run_fit(prob, FitConfig(lookup_refresh_every=-1, max_iterations=1))
    # no atlas (a single-view fit's image grid): nothing to look up
    prob, _ = plane_problem(device, layout)
    bare = dataclasses.replace(prob.texels, coordinate_gradients=None, grid_source=None)
    with pytest.raises(ConfigError, match="needs an atlas"):
        StreamProblem(bare, prob.photos, layout, StreamConfig(model_lookup="bilinear"), device=device)
    # traced taps: filtered sampling and a mesh with normals and UVs
    with pytest.raises(ConfigError, match="tap_geometry 'ray' unknown"):
        plane_problem(device, layout, taps="ray")
    with pytest.raises(ConfigError, match="tap_geometry mesh needs filtered"):
        plane_problem(device, layout, sampling="point", taps="mesh")
    prob.photos.mesh_uvs = None
    with pytest.raises(ConfigError, match="needs a mesh with normals and UVs"):
        StreamProblem(prob.texels, prob.photos, layout, StreamConfig(tap_geometry="mesh"), device=device)


ORNAMENT = dict(scale=0.01, photos=200, image_size=128, progress=False, device=SCENE_DEVICE)


@pytest.fixture(scope="module")
def ornament():
    scene = render_scene("ornament", SynthConfig(**ORNAMENT))
    scene.photos_on = {}  # device -> PhotoSet: the depth and shadow maps are built once per device
    return scene


def ornament_problem(scene, cfg: FitConfig, device: str):
    prob = build_problem(scene.mesh, scene.bake, scene.frames, scene.images, scene.masks, cfg, device,
                         scene.photos_on.get(device))
    scene.photos_on[device] = prob.photos
    return prob


def truth_objective(scene, lookup: str, device: str, taps: str = "plane") -> float:
    cfg = FitConfig(stream=StreamConfig(model_lookup=lookup, tap_geometry=taps))
    prob = ornament_problem(scene, cfg, device)
    gt = scene.params.reshape(-1, scene.params.shape[-1])[prob.texels.grid_index]
    st = FitState.create(prob, gt, np.ones(gt.shape[1], bool))
    prob.refresh_lookup(st.storage)
    prob.evaluate(st.storage, st.f, st.g, st.stats)
    return float(st.f.numpy().astype(np.float64).sum())


def test_truth_explains_its_photos_with_the_lookup(ornament, device):
    """Noise-free ornament photos, three materials in bands: with the seed's per-texel model the
    true parameters leave residuals at every material edge (the renderer blended two BRDFs there);
    with the lookup they nearly fit their photos, and with traced taps exactly. Measured (CPU,
    200 photos of 128x128): 0.83 -> 0.038 (plane taps: tap normals and texel coordinates extended
    linearly beyond the texel's face on the ornament's coarse cap) -> 7e-9 (traced taps: float32
    rounding of the photos and of the renderer's and the fit's arithmetic)."""
    texel = truth_objective(ornament, "texel", device)
    blended = truth_objective(ornament, "bilinear", device)
    assert blended < 0.1 * texel, (blended, texel)
    # float32 photos carry ~1e-7 relative rounding per pixel, 1e-14 in a squared residual: 1e-6 of
    # the texel model's objective leaves two decades above the measured 1e-8
    traced = truth_objective(ornament, "bilinear", device, taps="mesh")
    assert traced < 1e-6 * texel, (traced, texel)


def test_lookup_fit_decreases_and_stays_finite(ornament, device):
    """A short LM fit with the lookup: finite parameters, an objective that falls across refreshes."""
    cfg = FitConfig(optimizer="lm", max_iterations=6, sync_every=1000, stream=StreamConfig(model_lookup="bilinear"))
    prob = ornament_problem(ornament, cfg, device)
    res = run_fit(prob, cfg)
    obj = [r["objective"] for r in res.trace]
    assert obj[-1] < 0.5 * obj[0], obj
    assert np.all(np.isfinite(res.params))
    # LM's start and one pass per step, plus a refresh pass from the second iteration on
    # (lookup_refresh_every 0 -> every iteration for lm)
    assert res.passes == 1 + 6 + 5
