"""The room light (render/layout.py ``ModelLayout.room``, fit/models/per_texel/room_light.py): the kernels'
derivatives in its columns and the light's normal equations against float64 finite differences, and the room light
at zero giving the flash-only fit bit for bit. The recovery of a known room light and albedo is test_fit_ambient's
``test_auto_keeps_the_room_light_on_a_lit_room_and_recovers_it`` (auto chooses it there)."""

from __future__ import annotations

import numpy as np
import pytest

from texstream.fit.models.per_texel.room_light import light_step, texel_blocks, with_room
from texstream.render.layout import ModelLayout

from test_fit_gradients import assert_gradient_matches_finite_differences, evaluate, plane_problem, random_params

def room_params(layout: ModelLayout, n: int, rng) -> np.ndarray:
    """Random lobes (test_fit_gradients) and a random room irradiance factor of the size of the flash's share."""
    p = np.zeros((n, layout.n_params))
    p[:, :layout.room_offset] = random_params(layout, n, rng)[:, :layout.room_offset]
    p[:, layout.room_offset:] = rng.uniform(0.5, 3.0, (n, 3))
    return p


def test_layout_declares_the_room_columns():
    """Three frozen columns last, drawn by the renderer as the ambient radiance rho_d S they make."""
    lay = ModelLayout(room=True)
    assert lay.n_params == ModelLayout().n_params + 3 and lay.room_offset == lay.n_params - 3
    assert lay.names[-3:] == ["lafortune.room.r", "lafortune.room.g", "lafortune.room.b"]
    assert lay.frozen()[-3:].all() and lay.extra_term == 2 and lay.ambient_offset == -1
    assert ModelLayout.from_json(lay.to_json()) == lay and "room" not in ModelLayout().to_json()
    p = np.arange(lay.n_params, dtype=float)[None] + 1
    drawn_layout, drawn = lay.rendered(p)
    assert drawn_layout.ambient and not drawn_layout.room
    np.testing.assert_array_equal(drawn[0, -3:], p[0, 0:3] * p[0, -3:])


@pytest.mark.parametrize("layout,lookup", [(ModelLayout(room=True), "bilinear"),
                                           (ModelLayout(kind="diffuse", room=True), "texel")],
                         ids=["lafortune_lookup", "diffuse"])
def test_room_gradient_matches_finite_differences(device, layout, lookup):
    """Every column's gradient, the frozen room columns' included (what the light's step reduces), against central
    differences in float64; with the renderer's lookup the neighbours' rho_d S is held (their share in the
    offset), so each texel's objective is its own."""
    prob, rng = plane_problem(device, layout, seed=5, lookup=lookup)
    p = room_params(layout, prob.n, rng)
    prob.refresh_lookup(prob.new_storage(p))
    assert_gradient_matches_finite_differences(prob, layout, p, [0, 1, 2, *range(layout.room_offset, layout.n_params)])


def test_light_normal_equations_match_finite_differences(device):
    """The light's gradient (the normal equations' right side, sum_t pi T_t J^T r_t) and its Gauss-Newton step
    against float64 differences of the summed objective E(L) at fixed per-texel parameters: E is quadratic in L
    (S linear in L, the prediction linear in S), so the step from any L lands on the minimum, where central
    differences of E vanish. The diffuse kind: no lobe for the Schur complement to move, so the step is the
    light-only one exactly (its parameters are then re-fitted, which moves E below this minimum)."""
    layout = ModelLayout(kind="diffuse", room=True)
    prob, rng = plane_problem(device, layout, seed=7, grid=6)
    transfer = np.c_[np.full(prob.n, 0.28), rng.normal(scale=0.1, size=(prob.n, 8))]  # S > 0 at the lights below
    light = np.abs(rng.normal(size=(9, 3))) * np.r_[1.0, np.full(8, 0.05)][:, None]
    p = with_room(room_params(layout, prob.n, rng), layout, transfer, light)
    assert np.all(p[:, -3:] > 0)

    def energy(lt):
        return float(np.sum(evaluate(prob, with_room(p, layout, transfer, lt))[0]))

    g, jtj, _ = texel_blocks(prob, p)
    grad = np.einsum("nk,nc->kc", np.pi * transfer, g[:, layout.room_offset:])
    h = 1e-5
    for k, c in [(0, 0), (1, 1), (4, 2), (8, 0)]:
        d = np.zeros_like(light)
        d[k, c] = h
        fd = (energy(light + d) - energy(light - d)) / (2 * h)
        assert abs(fd - grad[k, c]) <= 1e-6 * np.abs(grad).max(), (k, c, fd, grad[k, c])
    # the diffuse texel's own rho_d is eliminated too: hold it by zeroing its coupling, the step is then exact
    jtj_held = jtj.copy()
    jtj_held[:, 0:3, layout.room_offset:] = jtj_held[:, layout.room_offset:, 0:3] = 0.0
    g_held = g.copy()
    g_held[:, 0:3] = 0.0
    new = light + light_step(layout, g_held, jtj_held, transfer, light)
    for k, c in [(0, 0), (2, 1), (8, 2)]:
        d = np.zeros_like(light)
        d[k, c] = 1e-4
        slope = (energy(new + d) - energy(new - d)) / 2e-4
        assert abs(slope) <= 1e-5 * np.abs(grad).max(), (k, c, slope)


def test_zero_room_light_is_the_flash_only_fit_bit_for_bit(device):
    """With S = 0 the room kernels compute m = rho_d (1 + 0 a) + lobes and dm/drho_d = 1 + 0 a: the flash-only
    layout's objective and gradient to the last bit; the off layout compiles the kernels it always did."""
    room, off = ModelLayout(room=True), ModelLayout()
    prob_room, rng = plane_problem(device, room, seed=9)
    prob_off, _ = plane_problem(device, off, seed=9)
    p = random_params(off, prob_off.n, rng)
    f_off, g_off, _, _ = evaluate(prob_off, p)
    f_room, g_room, _, _ = evaluate(prob_room, np.c_[p, np.zeros((prob_off.n, 3))])
    np.testing.assert_array_equal(f_room, f_off)
    np.testing.assert_array_equal(g_room[:, :off.n_params], g_off)
    assert off.extra_term == 0 and off.names == ModelLayout(ambient=False, room=False).names
