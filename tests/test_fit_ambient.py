"""The ambient radiance term (render/layout.py ``ModelLayout.ambient``): the passes' derivatives against finite
differences in float64, and fits of synthetic flash captures with and without the room's light."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from texstream.render.layout import ModelLayout

from test_fit_gradients import (SAMPLINGS, assert_full_dhd_matches_second_difference,
                                assert_gradient_matches_finite_differences, evaluate, plane_problem, random_params)


def ambient_params(layout: ModelLayout, n: int, rng) -> np.ndarray:
    """Random lobes (test_fit_gradients) and a random ambient radiance of the size of the flash's share."""
    p = random_params(layout, n, rng)
    p[:, layout.ambient_offset:] = rng.uniform(0.05, 0.5, (n, 3))
    return p


LAYOUTS = [ModelLayout(ambient=True), ModelLayout(kind="diffuse", ambient=True),
           ModelLayout(n_lobes=2, anisotropic=True, ambient=True)]
LAYOUT_IDS = ["lafortune", "diffuse", "aniso_2lobes"]


def test_layout_declares_the_ambient_columns():
    """Three columns after the lobes, lower bound 0; a light-free kind has none (its radiance is all the light)."""
    lay = ModelLayout(ambient=True)
    assert lay.n_params == ModelLayout().n_params + 3 and lay.ambient_offset == lay.n_params - 3
    assert lay.names[-3:] == ["lafortune.ambient.r", "lafortune.ambient.g", "lafortune.ambient.b"]
    assert np.all(lay.lower()[-3:] == 0.0) and np.all(lay.defaults()[-3:] == 0.0)
    assert ModelLayout.from_json(lay.to_json()) == lay
    assert "ambient" not in ModelLayout().to_json()  # manifests without the term are as before
    assert not ModelLayout(kind="radiance", ambient=True).ambient


@pytest.mark.parametrize("layout", LAYOUTS, ids=LAYOUT_IDS)
@pytest.mark.parametrize("sampling", SAMPLINGS)
def test_ambient_gradient_matches_finite_differences(device, layout, sampling):
    """Every free column's gradient, the ambient's included, against central differences (fp64)."""
    prob, rng = plane_problem(device, layout, sampling=sampling)
    assert_gradient_matches_finite_differences(prob, layout, ambient_params(layout, prob.n, rng))


@pytest.mark.parametrize("lookup,taps", [("bilinear", "plane"), ("texel", "mesh")], ids=["lookup", "traced"])
def test_ambient_gradient_with_the_lookup_and_traced_taps(device, lookup, taps):
    """The renderer's lookup (the neighbours' held ambient in the offset) and traced taps: gradient and the full
    d^T H d against differences."""
    layout = ModelLayout(ambient=True)
    prob, rng = plane_problem(device, layout, lookup=lookup, taps=taps)
    p = ambient_params(layout, prob.n, rng)
    prob.refresh_lookup(prob.new_storage(p))  # neighbours held at other values than the texel's own
    assert_gradient_matches_finite_differences(prob, layout, p)
    d = rng.normal(size=p.shape) * np.r_[[0.01] * 3, [0.05] * 3, 0.0, 0.02, 0.5, [0.05] * 3]
    f0, _, dhd, _ = evaluate(prob, p, direction=d, full=True)
    h = 3e-4
    second = (evaluate(prob, p + h * d)[0] - 2 * f0 + evaluate(prob, p - h * d)[0]) / h ** 2
    # as test_fit_gradients' full d^T H d: O(h^2) truncation and second-difference rounding
    bound = 1e-6 * np.abs(second) + 1e-6 * np.abs(second).max() + 1e-7 * np.abs(f0)
    assert np.all(np.abs(dhd - second) <= bound), np.max(np.abs(dhd - second) / bound)


@pytest.mark.parametrize("sampling", ["filtered", "point"])
def test_ambient_full_dhd_matches_second_difference(device, sampling):
    layout = ModelLayout(ambient=True)
    prob, rng = plane_problem(device, layout, seed=1, sampling=sampling)
    p = ambient_params(layout, prob.n, rng)
    d = rng.normal(size=p.shape) * np.r_[[0.01] * 3, [0.05] * 3, 0.0, 0.02, 0.5, [0.05] * 3]
    f0, _, dhd, _ = evaluate(prob, p, direction=d, full=True)
    h = 3e-4
    second = (evaluate(prob, p + h * d)[0] - 2 * f0 + evaluate(prob, p - h * d)[0]) / h ** 2
    bound = 1e-6 * np.abs(second) + 1e-6 * np.abs(second).max() + 1e-7 * np.abs(f0)
    assert np.all(np.abs(dhd - second) <= bound), np.max(np.abs(dhd - second) / bound)


@pytest.mark.parametrize("layout", LAYOUTS[:1] + LAYOUTS[2:], ids=["lafortune", "aniso_2lobes"])
def test_ambient_lm_pass_matches_the_gradient_pass(device, layout):
    """J^T r of the LM pass is the gradient and d^T J^T J d the Gauss-Newton d^T H d: the ambient's row entries
    (one per channel) reach J^T J."""
    prob, rng = plane_problem(device, layout, seed=3)
    p = ambient_params(layout, prob.n, rng)
    n, npar = prob.n, layout.n_params
    f_lm, g_lm = prob.new_scalar(), prob.new_vec()
    jtj = wp.zeros(n, dtype=prob.mat, device=device)
    prob.evaluate_lm(prob.new_storage(p), f_lm, g_lm, jtj, wp.zeros(n, dtype=wp.vec4d, device=device))
    f0, g0, _, _ = evaluate(prob, p)
    jj = jtj.numpy().reshape(n, npar, npar)
    # fp64 sums of the same terms in another order: rounding only
    np.testing.assert_allclose(f_lm.numpy(), f0, rtol=1e-12)
    np.testing.assert_allclose(g_lm.numpy().reshape(n, -1)[:, :npar], g0, rtol=1e-12, atol=1e-14 * np.abs(g0).max())
    for _ in range(3):
        d = rng.normal(size=p.shape)
        gn = evaluate(prob, p, direction=d)[2]
        np.testing.assert_allclose(np.einsum("ni,nij,nj->n", d, jj, d), gn, rtol=1e-10, atol=1e-12 * gn.max())
