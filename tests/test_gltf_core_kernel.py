"""The glTF core-material fit's Warp kernel (fit/models/lafortune/gltf_core_kernel.py) against the moment-based numpy
search it replaced, kept here as the reference: the same grids, the same closed forms, float64 in both, so the maps
agree to round-off wherever the best grid point is not a near tie (the summation order differs).
"""

from __future__ import annotations

import numpy as np
import pytest

from texstream.fit.models.lafortune import gltf_core
from texstream.render.layout import ModelLayout


# ---- the numpy reference (the export's code before the kernel) ----

def _wsum(wu: np.ndarray, y: np.ndarray) -> np.ndarray:
    """sum over samples of wu * y: ``wu`` (S,) shared by the texels or (T, S), ``y`` (T, S, 3) -> (T, 3)."""
    return np.einsum("s,tsc->tc" if wu.ndim == 1 else "ts,tsc->tc", wu, y)


def _best_for_roughness(y, w, dv, x5, metal, yy):
    """For one roughness per texel (``dv``, ``x5``: (S,) when every texel has the same roughness, else (T, S);
    ``w`` likewise): the best metallic on the grid ``metal`` (K,) and its base colour and squared error, from
    weighted moments (module doc); ``yy`` (T, 3) the weighted sum of y^2. Returns (err (T,), m (T,), b (T, 3))."""
    a = dv * (1 - x5)
    p, q = 1.0 / np.pi, a - 1.0 / np.pi
    s, t = dv * x5 + gltf_core.DIELECTRIC_F0 * a, -gltf_core.DIELECTRIC_F0 * a  # g0 = s + m t, g1 = p + m q

    def mom(u, v):  # (T,), or (1,) for directions and weights shared by the texels
        return np.atleast_1d((w * u * v).sum(axis=-1))

    pp, pq, qq = p * p * np.atleast_1d(w.sum(axis=-1)), p * mom(q, 1.0), mom(q, q)
    ps, pt, qs, qt = p * mom(s, 1.0), p * mom(t, 1.0), mom(q, s), mom(q, t)
    ss, st, tt = mom(s, s), mom(s, t), mom(t, t)
    py, qy, sy, ty = p * _wsum(w, y), _wsum(w * q, y), _wsum(w * s, y), _wsum(w * t, y)
    m = metal[None, :, None]  # (1, K, 1)
    g2 = (pp[:, None] + 2 * metal[None] * pq[:, None] + metal[None] ** 2 * qq[:, None])[..., None]
    gy = (py[:, None] + m * qy[:, None] - (ps[:, None, None] + m * (qs + pt)[:, None, None]
                                           + m * m * qt[:, None, None]))
    r2 = (yy[:, None] - 2 * (sy[:, None] + m * ty[:, None]) + ss[:, None, None] + 2 * m * st[:, None, None]
          + m * m * tt[:, None, None])
    b = np.clip(gy / np.maximum(g2, 1e-300), 0.0, 1.0)
    err = (r2 - 2 * b * gy + b * b * g2).sum(axis=2)  # (T, K)
    k = np.argmin(err, axis=1)
    rows = np.arange(len(k))
    return err[rows, k], metal[k], b[rows, k]


def _fit_chunk(y, w, light, view) -> tuple[np.ndarray, ...]:
    """Core (b, m, r) and the extension's F0_d for a chunk of texels (module doc). The coarse roughness grid
    gives every texel the same roughness, so its GGX terms and moments are computed once for the chunk (the
    directions and weights are every texel's): only the refinement works per texel."""
    metal = np.linspace(0.0, 1.0, gltf_core.METALLIC_STEPS)
    best_err = np.full(len(y), np.inf)
    best_m, best_r, best_b = np.zeros(len(y)), np.ones(len(y)), np.zeros((len(y), 3))
    yy = _wsum(w[0], y * y)

    def consider(rough, dv, x5, wt):
        nonlocal best_err, best_m, best_r, best_b
        err, m, b = _best_for_roughness(y, wt, dv, x5, metal, yy)
        better = err < best_err
        best_err = np.where(better, err, best_err)
        best_m, best_r = np.where(better, m, best_m), np.where(better, rough, best_r)
        best_b = np.where(better[:, None], b, best_b)

    for r in np.geomspace(gltf_core.ROUGHNESS_MIN, 1.0, gltf_core.ROUGHNESS_STEPS):
        dv, x5 = gltf_core.ggx_terms(light[0], view[0], r * r)
        consider(np.full(len(y), r), dv, x5, w[0])
    coarse = best_r.copy()
    for f in gltf_core.ROUGHNESS_REFINE:
        rough = np.clip(coarse * f, gltf_core.ROUGHNESS_MIN, 1.0)
        dv, x5 = gltf_core.ggx_terms(light, view, (rough ** 2)[:, None])
        consider(rough, dv, x5, w)
    dv, x5 = gltf_core.ggx_terms(light, view, (best_r ** 2)[:, None])
    kk = ((1 - best_m)[:, None] * dv * (1 - x5))[..., None]  # d f / d F0_d
    g = gltf_core.core_brdf(best_b, best_m, best_r, light, view) - gltf_core.DIELECTRIC_F0 * kk
    num, den = np.einsum("ts,tsc->tc", w, kk * (y - g)), np.einsum("ts,tsc->tc", w, kk * kk)
    f0d = np.where(den > 0, np.clip(num / np.where(den > 0, den, 1.0), 0.0, 1.0), gltf_core.DIELECTRIC_F0)
    return best_b, best_m, best_r, f0d




def reference_fit(rows, layout, samples):
    light, view = (np.broadcast_to(a, (len(rows),) + a.shape[1:]) for a in (samples.light, samples.view))
    wt = np.broadcast_to(samples.weight / samples.weight.sum(), (len(rows), samples.weight.shape[1]))
    y = gltf_core.lafortune_brdf(rows, layout, light, view)
    return _fit_chunk(y, wt, light, view)


def test_reference_recovers_a_core_material_exactly():
    """A texel whose target is itself a core material (b, m, r on the fit's grids): the moments give it back,
    and the extension's F0 is 0.04 (the core material is already exact). This validates the reference the kernel
    is held to below."""
    flash = gltf_core.flash_samples()
    rough = np.geomspace(gltf_core.ROUGHNESS_MIN, 1.0, gltf_core.ROUGHNESS_STEPS)[[6, 14]]
    b = np.array([[0.6, 0.3, 0.1], [0.2, 0.2, 0.25]])
    m = np.array([0.3, 0.07])
    light, view = (np.broadcast_to(a, (2,) + a.shape[1:]) for a in (flash.light, flash.view))
    w = np.broadcast_to(flash.weight, (2, flash.weight.shape[1]))
    y = gltf_core.core_brdf(b, m, rough, light, view)
    got_b, got_m, got_r, f0d = _fit_chunk(y, w / w.sum(1, keepdims=True), light, view)
    np.testing.assert_allclose(got_m, m, atol=1e-9)
    np.testing.assert_allclose(got_r, rough, rtol=1e-9)
    np.testing.assert_allclose(got_b, b, atol=1e-9)
    np.testing.assert_allclose(f0d, 0.04, atol=1e-7)


def random_grid(rng, layout, n):
    """n texels of plausible Lafortune parameters: albedo 0..0.3 (rho_d), lobes of exponent 5..200."""
    g = np.zeros((n, layout.n_params))
    g[:, 0:3] = rng.uniform(0.0, 0.3, (n, 3))
    for j in range(layout.n_lobes):
        o = layout.lobe_offset(j)
        g[:, o:o + 3] = rng.uniform(0.0, 1.0, (n, 1)) * rng.uniform(0.5, 1.5, (n, 3))
        g[:, o + 3:o + layout.lobe_stride - 1] = -1.0
        g[:, o + layout.lobe_stride - 2] = 1.0
        if layout.anisotropic:
            g[:, o + 4] = rng.uniform(-1.2, -0.8, n)
        g[:, o + layout.lobe_stride - 1] = np.exp(rng.uniform(np.log(5.0), np.log(200.0), n))
    return g


@pytest.mark.parametrize("lobes,aniso", [(0, False), (1, False), (2, True)])
def test_kernel_matches_the_numpy_reference(device, lobes, aniso):
    """200 random texels: the kernel's maps equal the reference's to 1e-9 (float64 round-off of sums over ~190
    samples) on all but near ties of the grid search, where both choices score the same to 1e-12 relative."""
    layout = ModelLayout(n_lobes=lobes, anisotropic=aniso)
    rows = random_grid(np.random.default_rng(lobes), layout, 200)
    samples = gltf_core.flash_samples()
    ref_b, ref_m, ref_r, ref_f = reference_fit(rows, layout, samples)
    old = (np.full((200, 1, 3), 0.1), np.full((200, 1, 3), 0.04), np.full((200, 1), 0.5))
    got = gltf_core.fit_core_material(rows.reshape(200, 1, -1), layout, samples, None, old, device=device)
    same = (np.abs(got.metallic[:, 0] - ref_m) < 1e-9) & (np.abs(got.roughness[:, 0] - ref_r) < 1e-9)
    assert same.mean() >= 0.99
    np.testing.assert_allclose(got.base_color[same, 0], ref_b[same], atol=1e-9)
    np.testing.assert_allclose(got.specular_f0[same, 0], ref_f[same], atol=1e-9)
    assert 0.0 <= got.fit["relative_rms_core"] < 1.0
    assert got.fit["relative_rms_with_specular_extension"] <= got.fit["relative_rms_core"] + 1e-12


def test_texel_chunks_on_worker_threads_give_the_same_maps_to_the_bit(monkeypatch):
    """On the CPU the chunks of texels run on one thread per core (each CPU launch runs on its caller's thread):
    chunks of 16 texels over 2 threads against 1, every map equal to the bit (each texel's arithmetic is its
    own)."""
    from texstream.fit.models.lafortune import gltf_core_kernel

    layout = ModelLayout(n_lobes=1)
    rows = random_grid(np.random.default_rng(7), layout, 100)
    samples = gltf_core.flash_samples()
    old = (np.full((100, 1, 3), 0.1), np.full((100, 1, 3), 0.04), np.full((100, 1), 0.5))
    monkeypatch.setattr(gltf_core_kernel, "TEXEL_CHUNK", 16)
    maps = {}
    for threads in (1, 2):
        monkeypatch.setattr(gltf_core_kernel, "usable_cpus", lambda t=threads: t)
        got = gltf_core.fit_core_material(rows.reshape(100, 1, -1), layout, samples, None, old, device="cpu")
        maps[threads] = (got.base_color, got.metallic, got.roughness, got.specular_f0)
    for one, two in zip(maps[1], maps[2]):
        np.testing.assert_array_equal(one, two)
