"""The view-dependent radiance model (ModelLayout kind "view_radiance", fit/models.py).

Per texel L_c(v) = L_c + sum_k a_k,c phi_k(v), phi = (v_x, v_y, v_x^2, v_x v_y, v_y^2) of the local
view direction, with a ridge prior on the a_k (StreamProblem.set_view_prior). Checked here: the
parameter table and its maps, fp64 derivatives (with the prior) against finite differences for every
photo sampling, the LM pass against the gradient pass, the renderer's evaluation, and a synthetic
recovery: photos rendered from a known view-dependent radiance are fitted back (so the fit and the
renderer agree on the tangent frame the view terms live in), and the view-dependent model predicts
held-out views that the view-independent one cannot.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import warp as wp

from texstream.capture.synthetic.param_maps import VIEW_TERM_NAMES
from texstream.capture.synthetic.synth import SynthConfig, render_scene
from texstream.fit.optim.fitter import FitConfig, run_fit
from texstream.render.layout import VIEW_TERMS, ModelLayout
from texstream.fit.stream.photo_set import PhotoSet
from texstream.fit.stream.problem import PhotoFrame, StreamProblem
from texstream.fit.stream.texels import TexelSet, surface_derivatives
from texstream.render.renderer import Renderer

from conftest import SCENE_DEVICE
from test_fit_gradients import SAMPLINGS, assert_gradient_matches_finite_differences, evaluate, plane_problem

VIEW = ModelLayout(kind="view_radiance")
RADIANCE = ModelLayout(kind="radiance")


def view_params(n, rng):
    p = np.zeros((n, VIEW.n_params))
    p[:, 0:3] = rng.uniform(0.2, 2.0, (n, 3))
    p[:, 3:] = rng.normal(scale=0.3, size=(n, 15))
    return p


def test_layout_table_json_and_param_maps(tmp_path):
    assert (VIEW.n_lobes, VIEW.view_terms, VIEW.n_params) == (0, 5, 18)
    assert VIEW.is_radiance and VIEW_TERM_NAMES == VIEW_TERMS  # capture/ keeps its own copy of the names
    assert VIEW.names[:4] == ["view_radiance.L.r", "view_radiance.L.g", "view_radiance.L.b", "view_radiance.view.vx.r"]
    assert VIEW.index("view.vyy.b") == VIEW.view_offset(4) + 2 == 17
    assert ModelLayout.from_json(VIEW.to_json()) == VIEW
    np.testing.assert_array_equal(VIEW.lower()[3:], -1000.0)
    from texstream.capture.synthetic.param_maps import read_param_maps, write_param_maps

    grid = np.random.default_rng(0).normal(size=(6, 5, 18)).astype(np.float32)
    files = write_param_maps(tmp_path, grid, VIEW)
    assert files == {"radiance": "radiance.exr", **{f"view_{k}": f"view_{k}.exr" for k in VIEW_TERMS}}
    np.testing.assert_array_equal(read_param_maps(tmp_path, VIEW), grid)  # 32-bit float EXR: exact


@pytest.mark.parametrize("prior", [0.0, 0.7])
@pytest.mark.parametrize("sampling", SAMPLINGS)
def test_gradient_matches_finite_differences(device, sampling, prior):
    prob, rng = plane_problem(device, VIEW, sampling=sampling, kind="none")
    prob.set_view_prior(prior)
    # test_fit_gradients' check: 1e-6 of each texel's gradient norm (fp64 central differences)
    assert_gradient_matches_finite_differences(prob, VIEW, view_params(prob.n, rng))


def test_dhd_and_lm_pass_match_the_gradient_pass(device):
    """The model is linear in its parameters, so f is quadratic: d^T H d is the exact second difference
    (Gauss-Newton drops nothing), and the LM pass's f, J^T r and d^T (J^T J) d equal the gradient pass's
    f, g and d^T H d, the prior included in both."""
    prob, rng = plane_problem(device, VIEW, seed=3, kind="none")
    prob.set_view_prior(0.7)
    p = view_params(prob.n, rng)
    d = rng.normal(size=p.shape) * 0.05
    f0, g0, dhd, st = evaluate(prob, p, direction=d)
    assert st[:, 0].sum() > 0
    h = 1e-2  # f is quadratic along d: the second difference is exact up to rounding, eps f / h^2 ~ 1e-12 f
    second = (evaluate(prob, p + h * d)[0] - 2 * f0 + evaluate(prob, p - h * d)[0]) / h ** 2
    np.testing.assert_allclose(dhd, second, rtol=1e-8, atol=1e-10 * np.abs(second).max())
    n = prob.n
    f_lm, g_lm = prob.new_scalar(), prob.new_vec()
    jtj = wp.zeros(n, dtype=prob.mat, device=device)
    prob.evaluate_lm(prob.new_storage(p), f_lm, g_lm, jtj, wp.zeros(n, dtype=wp.vec4d, device=device))
    jj = jtj.numpy().reshape(n, 18, 18)
    # fp64 sums of the same terms in another order: rounding only
    np.testing.assert_allclose(f_lm.numpy(), f0, rtol=1e-12)
    np.testing.assert_allclose(g_lm.numpy().reshape(n, -1), g0, rtol=1e-11, atol=1e-13 * np.abs(g0).max())
    np.testing.assert_allclose(np.einsum("ni,nij,nj->n", d, jj, d), dhd, rtol=1e-10)


def test_prior_pulls_only_the_view_terms(device):
    """set_view_prior adds lam / 2 |a|^2 with lam = weight x the mean squared exposure: the objective
    grows by exactly that and L's gradient is untouched."""
    prob, rng = plane_problem(device, VIEW, seed=5, kind="none")
    p = view_params(prob.n, rng)
    f0, g0, _, _ = evaluate(prob, p)
    prob.set_view_prior(2.0)
    f1, g1, _, _ = evaluate(prob, p)
    lam = 2.0 * np.mean(np.square(prob.photos.exposures))
    np.testing.assert_allclose(f1 - f0, 0.5 * lam * (p[:, 3:] ** 2).sum(1), rtol=1e-10)
    np.testing.assert_array_equal(g1[:, :3], g0[:, :3])
    np.testing.assert_allclose(g1[:, 3:] - g0[:, 3:], lam * p[:, 3:], rtol=1e-10, atol=1e-14)


# ------------------------------------------------------------------------------- synthetic recovery


def view_truth(bake, rng):
    """A smooth view-dependent radiance on the flat sample: L 0.3-0.8 from the checker, and view terms
    whose polynomial stays within [0.05, 1.6] for every view within 70 degrees of the normal."""
    base = 0.3 + 0.5 * rng.uniform(size=3)
    grid = np.zeros((*bake.covered.shape, 18))
    grid[..., 0:3] = base + 0.2 * np.sin(3.0 * bake.position[..., 0:1])
    grid[..., 3:6] = 0.25  # vx
    grid[..., 6:9] = -0.15  # vy
    grid[..., 9:12] = 0.2  # vxx
    grid[..., 12:15] = 0.1  # vxy
    grid[..., 15:18] = -0.1  # vyy
    return grid


@pytest.fixture(scope="module")
def view_scene():
    """The flat sample's cameras (render_scene) seeing a known view-dependent radiance, rendered by the
    Renderer into light-less frames with exposures from 0.5 to 2; every 4th frame is held out."""
    sc = render_scene("flat_sample", SynthConfig(scale=0.3, photos=24, image_size=48, progress=False,
                                                 device=SCENE_DEVICE))
    rng = np.random.default_rng(11)
    truth = view_truth(sc.bake, rng)
    exposures = np.linspace(0.5, 2.0, len(sc.frames))
    rng.shuffle(exposures)
    frames = [dataclasses.replace(f, light=None, exposure=float(e)) for f, e in zip(sc.frames, exposures)]
    rend = Renderer(sc.mesh, sc.bake.fill_padding(truth.astype(np.float32)), VIEW, SCENE_DEVICE)
    images = [rend.render_frame(f).radiance * np.float32(f.exposure) for f in frames]
    return dict(scene=sc, frames=frames, images=images, truth=truth)


def fit_view_scene(data, device, model, prior=0.0, **stop):
    sc = data["scene"]
    mesh, bake = sc.mesh, sc.bake
    fit_idx = [k for k in range(len(data["frames"])) if k % 4 != 3]
    cfg = FitConfig(model=model, optimizer="lm", max_iterations=10, view_prior=prior, robust_loss="none", **stop)
    normals = mesh.vertex_normals()
    fn, jac = surface_derivatives(mesh.vertices, mesh.faces, normals, bake.face, bake.bary)
    texels = TexelSet.from_grid(bake.covered, bake.position, bake.normal, bake.tangent, bake.bitangent, fn, jac)
    frames = [PhotoFrame.from_capture_frame(data["frames"][k]) for k in fit_idx]
    photos = PhotoSet(frames, [data["images"][k] for k in fit_idx], mesh.vertices, mesh.faces,
                      masks=[sc.masks[k] for k in fit_idx], config=cfg.stream, device=device,
                      mesh_normals=normals, mesh_uvs=mesh.uvs)
    prob = StreamProblem(texels, photos, cfg.layout(frames), cfg.stream, device=device)
    res = run_fit(prob, cfg)
    grid = np.zeros((*bake.covered.shape, res.layout.n_params), np.float32)
    grid.reshape(-1, res.layout.n_params)[texels.grid_index] = res.params
    return res, texels, bake.fill_padding(grid)


def heldout_mse(data, grid, layout):
    rend = Renderer(data["scene"].mesh, grid, layout, SCENE_DEVICE)
    err, n = 0.0, 0
    for k, f in enumerate(data["frames"]):
        if k % 4 != 3:
            continue
        r = rend.render_frame(f)
        m = r.mask & data["scene"].masks[k]
        err += float(((r.radiance * np.float32(f.exposure) - data["images"][k])[m] ** 2).sum())
        n += int(m.sum()) * 3
    return err / n


def test_fit_recovers_a_view_dependent_radiance(view_scene, device):
    res, texels, _ = fit_view_scene(view_scene, device, "view_radiance")
    truth = view_scene["truth"].reshape(-1, 18)[texels.grid_index]
    well = res.samples >= 12  # a 6-parameter polynomial per channel needs views from many directions
    assert well.sum() > 300
    # noise-free photos of exactly this model (rendered in float32, resampled by the photos' bilinear
    # filter): L within 1%, each coefficient within 0.03 of its 0.1-0.25 magnitude on the median texel
    assert np.median(np.abs(res.params[well, :3] - truth[well, :3]) / truth[well, :3]) < 0.01
    assert np.all(np.median(np.abs(res.params[well, 3:] - truth[well, 3:]), axis=0) < 0.03)
    # held-out views: the view-dependent fit (default prior) predicts them; the view-independent one
    # cannot. Measured 0.24 of the flat model's MSE (+6.2 dB) on the CPU; the rest sits on texels seen by
    # 3-5 photos, whose polynomial the prior holds near flat. 0.4 (+4 dB) leaves room for other devices
    _, _, prior_grid = fit_view_scene(view_scene, device, "view_radiance", prior=FitConfig().view_prior)
    _, _, flat = fit_view_scene(view_scene, device, "radiance")
    mse_view, mse_flat = heldout_mse(view_scene, prior_grid, VIEW), heldout_mse(view_scene, flat, RADIANCE)
    assert mse_view < 0.4 * mse_flat, (mse_view, mse_flat)


def test_prior_keeps_a_texel_seen_from_one_direction_view_independent(device):
    """One photo: the data cannot tell L from the view terms along that direction; the prior picks the
    smallest view terms, so L carries the radiance (with no prior the system is singular and LM's
    damping alone decides)."""
    prob, rng = plane_problem(device, VIEW, seed=7, kind="none", n_photos=1)
    prob.set_view_prior(1.0)
    cfg = FitConfig(model="view_radiance", optimizer="lm", max_iterations=15, view_prior=1.0, robust_loss="none")
    res = run_fit(prob, cfg)
    seen = res.samples > 0
    assert seen.sum() >= 5
    assert np.all(np.isfinite(res.params))
    # each channel: minimise (L + a.phi - y)^2 / 2 + |a|^2 / 2 -> a = phi (y - L) ... with L free, the
    # optimum has a = 0 and L = y; LM reaches it to its stopping tolerance
    assert np.max(np.abs(res.params[seen, 3:])) < 1e-3


def test_the_radiance_models_stop_once_their_objective_settles(view_scene, device):
    """The radiance models' stopping rule (fit/models/radiance/fit.py): the view-dependent radiance is linear
    least squares per texel, which LM solves in its first iteration or two (its damping starts at lm_lambda0), so
    under the rule its fit stops at the second or third (measured: the third here, the second on the temple)
    instead of running to the cap, with the parameters of the capped fit. A rule the caller gives is kept."""
    from texstream.fit.models.radiance.fit import SETTLED_REL_TOL, SETTLED_SYNC_EVERY, settled_config
    from texstream.fit.stages.stage import FitStageConfig

    settled = settled_config(FitStageConfig(fit=FitConfig(model="view_radiance"))).fit
    assert (settled.rel_tol, settled.sync_every) == (SETTLED_REL_TOL, SETTLED_SYNC_EVERY)
    given = FitStageConfig(fit=FitConfig(model="view_radiance", rel_tol=1e-9))
    assert settled_config(given) is given

    capped, _, capped_grid = fit_view_scene(view_scene, device, "view_radiance")
    stopped, _, stopped_grid = fit_view_scene(view_scene, device, "view_radiance", rel_tol=settled.rel_tol,
                                              sync_every=settled.sync_every)
    assert capped.trace[-1]["iteration"] == 10 and stopped.trace[-1]["iteration"] <= 3
    # texels seen from many directions are solved: the later iterations move them by float32 round-off of
    # their values (0.1-0.8); the 0.1% seen by a few photos, whose view terms the damping still holds back,
    # moved by up to 0.007 (measured), which the held-out views must not see
    well = capped.samples >= 12
    np.testing.assert_allclose(stopped.params[well], capped.params[well], rtol=0, atol=1e-4)
    mse_stopped, mse_capped = heldout_mse(view_scene, stopped_grid, VIEW), heldout_mse(view_scene, capped_grid, VIEW)
    assert mse_stopped <= 1.01 * mse_capped, (mse_stopped, mse_capped)
