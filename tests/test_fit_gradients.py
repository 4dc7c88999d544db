"""Fit kernels: fp64 gradient and d^T H d against central finite differences; NaN safety."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from texstream.capture.conventions import look_at_w2c
from texstream.render.layout import ModelLayout
from texstream.fit.stream.config import StreamConfig
from texstream.fit.stream.photo_set import PhotoSet
from texstream.fit.stream.problem import PhotoFrame, StreamProblem
from texstream.fit.stream.texels import TexelSet


SAMPLINGS = ["filtered", "point", "bilinear"]


def plane_problem(device, layout, n_photos=6, grid=5, seed=0, acc="fp64", kind="point", storage=None,
                  sampling="filtered", lookup="texel", taps="plane", unlit=0, unlit_light=None):
    """Texels on the plane z = 0 seen by random cameras under random lights; random photo values
    (the derivative checks need no consistent data). The shading normal bends across each texel
    (a random normal Jacobian) so point and filtered sampling see a different frame at every tap.
    The texel grid maps linearly onto the plane (texel coordinate gradients for ``lookup``
    bilinear: a filtered tap lands ~0.15 texel from its centre, so neighbours weigh in), and so
    do the mesh's UVs, whose tilted vertex normals give traced taps (``taps`` mesh) their own
    frame at every hit. The first ``unlit`` photos' light has intensity 0 (taken with the flash off), at
    ``unlit_light`` when given (a point light's position; else drawn as the lit photos' are)."""
    rng = np.random.default_rng(seed)
    pts = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], float)
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    xs, ys = np.meshgrid((np.arange(grid) + 0.5) / grid * 1.6 - 0.8, (np.arange(grid) + 0.5) / grid * 1.6 - 0.8)
    pos = np.stack([xs, ys, np.zeros_like(xs)], -1)
    e = np.eye(3)
    jac = np.zeros((grid, grid, 3, 3))
    jac[..., :, :2] = rng.normal(scale=0.3, size=(grid, grid, 3, 2))  # d n / d (x, y) on the plane
    coord = np.zeros((grid, grid, 2, 3))
    coord[..., 0, 0] = coord[..., 1, 1] = grid / 1.6  # texel x follows the plane's x, texel y its y
    tex = TexelSet.from_grid(np.ones((grid, grid), bool), pos, np.broadcast_to(e[2], pos.shape),
                             np.broadcast_to(e[0], pos.shape), np.broadcast_to(e[1], pos.shape),
                             np.broadcast_to(e[2], pos.shape), jac, coord)
    frames, imgs = [], []
    for _ in range(n_photos):
        ang, el = rng.uniform(0, 2 * np.pi), rng.uniform(0.4, 1.3)
        eye = 3 * np.array([np.cos(ang) * np.cos(el), np.sin(ang) * np.cos(el), np.sin(el)])
        r, t = look_at_w2c(eye, [0, 0, 0])
        if kind == "point":
            lv = eye + rng.normal(size=3) * 0.7
        else:
            lv = -(eye + rng.normal(size=3)) / np.linalg.norm(eye)
        intensity = np.array([5.0, 4.0, 3.0]) * float(len(frames) >= unlit)
        if len(frames) < unlit and unlit_light is not None:
            lv = np.asarray(unlit_light, float)
        frames.append(PhotoFrame(r, t, 60.0, 60.0, 32.0, 32.0, 64, 64, kind, lv, intensity))
        imgs.append(rng.uniform(0, 1, (64, 64, 3)).astype(np.float32))
    cfg = StreamConfig(accumulate=acc, storage=storage or ("fp64" if acc == "fp64" else "fp32"), shadow_map_size=64,
                       photo_sampling=sampling, model_lookup=lookup, tap_geometry=taps)
    # texel (x, y) = ((X + 0.8) W / 1.6 - 1/2, (Y + 0.8) H / 1.6 - 1/2) = (u W - 1/2, (1 - v) H - 1/2)
    uvs = np.stack([(pts[:, 0] + 0.8) / 1.6, 1.0 - (pts[:, 1] + 0.8) / 1.6], 1)
    # an rng of its own, so the other tests' random streams stay as they were
    tilt = np.random.default_rng(seed + 1000).normal(scale=0.3, size=(4, 3))
    vertex_normals = e[2] + tilt * np.array([1.0, 1.0, 0.0])
    vertex_normals /= np.linalg.norm(vertex_normals, axis=1, keepdims=True)
    photos = PhotoSet(frames, imgs, pts, faces, config=cfg, device=device, mesh_normals=vertex_normals, mesh_uvs=uvs)
    return StreamProblem(tex, photos, layout, cfg, device=device), rng


def random_params(layout, n, rng, n_range=(2.0, 30.0), cz_max=1.3):
    lobes = []
    for _ in range(layout.n_lobes):
        c = [-np.ones(n), rng.uniform(0.7, cz_max if n_range[1] < 100 else 1.0, n)]
        if layout.anisotropic:
            c = [-np.ones(n), rng.uniform(-1.3, -0.7, n), rng.uniform(0.7, 1.3, n)]
        lobes.append({"rho_s": rng.uniform(0.3, 2.0, (n, 3)), "c": np.stack(c, 1), "n": rng.uniform(*n_range, n)})
    return layout.pack(rng.uniform(0.05, 0.3, (n, 3)), lobes)


def evaluate(prob, p, direction=None, full=False):
    f, g = prob.new_scalar(), prob.new_vec()
    st = wp.zeros(prob.n, dtype=wp.vec4d, device=prob.device)
    h = prob.new_scalar()
    prob.evaluate(prob.new_storage(p), f, g, st, direction=None if direction is None else prob.new_storage(direction),
                  dhd=h, full_hessian=full)
    return f.numpy(), g.numpy()[:, :prob.layout.n_params], h.numpy(), st.numpy()


@pytest.mark.parametrize("layout,n_range", [(ModelLayout(), (2.0, 30.0)), (ModelLayout(), (1.0, 1.2)),
                                            (ModelLayout(), (900.0, 1000.0)), (ModelLayout(n_lobes=2, anisotropic=True), (2.0, 30.0))],
                         ids=["iso", "n_near_1", "n_1000", "aniso_2lobes"])
@pytest.mark.parametrize("sampling", SAMPLINGS)
def test_gradient_matches_finite_differences(device, layout, n_range, sampling):
    prob, rng = plane_problem(device, layout, sampling=sampling)
    assert_gradient_matches_finite_differences(prob, layout, random_params(layout, prob.n, rng, n_range))


def assert_full_dhd_matches_second_difference(prob, p, rng, scale=None):
    """The full-Hessian d^T H d along a random direction (columns scaled by ``scale``; default: one isotropic
    lobe's) against second differences of every texel's objective; bound: O(h^2) truncation and second-difference
    rounding."""
    scale = np.array([0.01, 0.01, 0.01, 0.05, 0.05, 0.05, 0.0, 0.02, 0.5]) if scale is None else scale
    d = rng.normal(size=p.shape) * scale
    f0, _, dhd, _ = evaluate(prob, p, direction=d, full=True)
    h = 3e-4
    second = (evaluate(prob, p + h * d)[0] - 2 * f0 + evaluate(prob, p - h * d)[0]) / h ** 2
    bound = 1e-6 * np.abs(second) + 1e-6 * np.abs(second).max() + 1e-7 * np.abs(f0)
    assert np.all(np.abs(dhd - second) <= bound), np.max(np.abs(dhd - second) / bound)


def assert_gradient_matches_finite_differences(prob, layout, p, columns=None):
    """Each free column's gradient (or each of ``columns``) against central differences of every texel's
    objective."""
    f0, g0, _, st = evaluate(prob, p)
    assert st[:, 0].sum() > 0
    for k in (np.flatnonzero(~layout.frozen()) if columns is None else columns):
        h = 1e-6 * max(1.0, np.abs(p[:, k]).max())
        pp, pm = p.copy(), p.copy()
        pp[:, k] += h
        pm[:, k] -= h
        fd = (evaluate(prob, pp)[0] - evaluate(prob, pm)[0]) / (2 * h)
        # 1e-6 relative to each texel's gradient norm: central differences in fp64 carry
        # O(h^2) truncation plus eps*f/h ~ 1e-10 rounding, far below it
        scale = np.linalg.norm(g0, axis=1) + 1e-12
        assert np.all(np.abs(fd - g0[:, k]) <= 1e-6 * scale), (k, np.max(np.abs(fd - g0[:, k]) / scale))


@pytest.mark.parametrize("full", [False, True], ids=["gauss_newton", "full_hessian"])
@pytest.mark.parametrize("sampling", SAMPLINGS)
def test_dhd_matches_second_difference(device, full, sampling):
    layout = ModelLayout()
    prob, rng = plane_problem(device, layout, seed=1, sampling=sampling)
    p = random_params(layout, prob.n, rng)
    d = rng.normal(size=p.shape) * np.array([0.01, 0.01, 0.01, 0.05, 0.05, 0.05, 0.0, 0.02, 0.5])
    f0, g0, dhd, _ = evaluate(prob, p, direction=d, full=full)
    # h = 3e-4 balances the O(h^2) truncation against rounding, which grows as 1 / h^2 and is set
    # by the residual terms (up to ~100x f here, not f itself): at h = 1e-4 rounding alone reaches
    # ~1e-6 f on some texels
    h = 3e-4
    fp, fm = evaluate(prob, p + h * d)[0], evaluate(prob, p - h * d)[0]
    second = (fp - 2 * f0 + fm) / h ** 2
    if full:
        # the full d^T H d is the exact second directional derivative; 1e-6 relative covers the
        # O(h^2) truncation, and 1e-7 f per texel the rounding of the second difference on texels
        # whose curvature is small next to their objective (measured: <= 1.5e-7 f at h = 3e-4)
        bound = 1e-6 * np.abs(second) + 1e-6 * np.abs(second).max() + 1e-7 * np.abs(f0)
        assert np.all(np.abs(dhd - second) <= bound), np.max(np.abs(dhd - second) / bound)
    else:
        # Gauss-Newton drops r * d^T (Hess r) d: it equals sum (J d)^2, checked against the
        # directional derivative of the residual vector by differencing the gradient
        gp = evaluate(prob, p + h * d)[1]
        gm = evaluate(prob, p - h * d)[1]
        hd = ((gp - gm) / (2 * h) * d).sum(1)  # = d^T H d (full), so GN differs by the r-term
        assert np.all(dhd >= 0)
        full_dhd = evaluate(prob, p, direction=d, full=True)[2]
        np.testing.assert_allclose(full_dhd, hd, rtol=1e-5, atol=1e-7 * np.abs(hd).max())


@pytest.mark.parametrize("layout", [ModelLayout(), ModelLayout(n_lobes=2, anisotropic=True)], ids=["iso", "aniso_2lobes"])
@pytest.mark.parametrize("sampling", ["filtered", "bilinear"])
def test_lm_pass_matches_the_gradient_pass(device, layout, sampling):
    """The LM pass's J^T r is the gradient pass's gradient and d^T (J^T J) d its Gauss-Newton
    d^T H d for every d: random directions reach every entry of J^T J, which the LM kernel sums
    over each Jacobian row's structural non-zeros only (off-diagonal and cross-lobe blocks included)."""
    prob, rng = plane_problem(device, layout, seed=3, sampling=sampling)
    p = random_params(layout, prob.n, rng)
    n, npar = prob.n, layout.n_params
    f_lm, g_lm = prob.new_scalar(), prob.new_vec()
    jtj = wp.zeros(n, dtype=prob.mat, device=device)
    prob.evaluate_lm(prob.new_storage(p), f_lm, g_lm, jtj, wp.zeros(n, dtype=wp.vec4d, device=device))
    f0, g0, _, st = evaluate(prob, p)
    assert st[:, 0].sum() > 0
    jj = jtj.numpy().reshape(n, npar, npar)
    # fp64 sums of the same terms, in another order for J^T J: rounding only (1e-10 relative)
    np.testing.assert_allclose(f_lm.numpy(), f0, rtol=1e-12)
    np.testing.assert_allclose(g_lm.numpy().reshape(n, -1)[:, :npar], g0, rtol=1e-12, atol=1e-14 * np.abs(g0).max())
    np.testing.assert_array_equal(jj, jj.transpose(0, 2, 1))
    for _ in range(3):
        d = rng.normal(size=p.shape)
        gn = evaluate(prob, p, direction=d)[2]
        np.testing.assert_allclose(np.einsum("ni,nij,nj->n", d, jj, d), gn, rtol=1e-10, atol=1e-12 * gn.max())


def test_fp32_matches_fp64(device):
    layout = ModelLayout()
    p64, rng = plane_problem(device, layout, acc="fp64", seed=2)
    p32, _ = plane_problem(device, layout, acc="fp32", seed=2)
    p = random_params(layout, p64.n, rng)
    f64, g64 = evaluate(p64, p)[:2]
    f32, g32 = evaluate(p32, p)[:2]
    # float32 accumulation over ~6 photos x 3 channels: a few ulps of the summed terms
    np.testing.assert_allclose(f32, f64, rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(g32, g64, rtol=1e-3, atol=1e-4 * np.abs(g64).max())


def test_kahan_summation_matches_fp64(device):
    """The Kahan-compensated fp32 pass (StreamConfig.kahan, its own compiled kernel) computes the
    same objective, gradient and d^T H d as fp64, within fp32 rounding of the summed terms."""
    layout = ModelLayout()
    p64, rng = plane_problem(device, layout, acc="fp64", seed=2)
    p32, _ = plane_problem(device, layout, acc="fp32", seed=2)
    kahan = StreamProblem(p32.texels, p32.photos, layout, StreamConfig(accumulate="fp32", kahan=True,
                                                                        shadow_map_size=64), device=device)
    p = random_params(layout, p64.n, rng)
    d = rng.normal(size=p.shape)
    f64, g64, h64, _ = evaluate(p64, p, direction=d)
    fk, gk, hk, _ = evaluate(kahan, p, direction=d)
    np.testing.assert_allclose(fk, f64, rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(gk, g64, rtol=1e-3, atol=1e-4 * np.abs(g64).max())
    np.testing.assert_allclose(hk, h64, rtol=1e-3, atol=1e-4 * np.abs(h64).max())


def test_extreme_exponents_and_grazing_lights_stay_finite(device):
    layout = ModelLayout()
    prob, rng = plane_problem(device, layout, seed=3, kind="directional", acc="fp32")
    p = random_params(layout, prob.n, rng, (9000.0, 10000.0))
    f, g, _, _ = evaluate(prob, p)
    assert np.all(np.isfinite(f)) and np.all(np.isfinite(g))
    p[:, 8] = 1.0
    p[:, 7] = 10.0
    f, g, _, _ = evaluate(prob, p)
    assert np.all(np.isfinite(f)) and np.all(np.isfinite(g))


def test_smoothness_gradient_and_block_hessian_match_finite_differences(device):
    """The membrane term of LM (fit/optim/lm.py): the texel's half share summed over texels is the
    global penalty; its gradient and diagonal block Hessian must be the penalty's derivatives."""
    from texstream.fit.kernels import optim_kernels as K
    from texstream.fit.optim.lm import edge_weights
    from texstream.fit.stream.penalties import PenaltyConfig

    layout = ModelLayout()
    prob, rng = plane_problem(device, layout, n_photos=1, grid=6, seed=4)
    cfg = PenaltyConfig(smooth_weight=0.3, smooth_params="all", smooth_exponent_scale=20.0)
    w = cfg.parameter_weights(layout, cfg.smooth_params)
    p = random_params(layout, prob.n, rng)
    ew = wp.array(edge_weights(p[:, :3], prob.texels.neighbors, 0.5), dtype=wp.vec4, device=device)
    n = prob.n

    def penalty(q, scale, derivatives=False):
        qa = prob.new_vec(q)
        f, g = prob.new_scalar(), prob.new_vec()
        h = wp.zeros(n, dtype=prob.mat, device=device)
        wp.launch(K.smooth_local_kernel, dim=n, device=device,
                  inputs=[qa, qa, prob.neighbors, ew, prob.vec(*w), prob.scalar(0.3), prob.scalar(scale),
                          prob.new_scalar(), prob.new_vec(), wp.zeros(n, dtype=prob.mat, device=device),
                          layout.n_params, 1 if derivatives else 0], outputs=[f, g, h])
        return f.numpy(), g.numpy()[:, :layout.n_params], h.numpy()

    f_half, g, hess = penalty(p, 0.5, True)
    total = f_half.sum()
    # the global penalty is quadratic: central differences are exact up to fp64 rounding (1e-8 rel.)
    for i in (0, 7, n - 1):
        for k in np.flatnonzero(~layout.frozen()):
            step = 1e-3
            pp, pm = p.copy(), p.copy()
            pp[i, k] += step
            pm[i, k] -= step
            fp, fm = penalty(pp, 0.5)[0].sum(), penalty(pm, 0.5)[0].sum()
            np.testing.assert_allclose((fp - fm) / (2 * step), g[i, k], rtol=1e-7, atol=1e-10 * abs(total))
            np.testing.assert_allclose((fp - 2 * total + fm) / step ** 2, hess[i, k, k], rtol=1e-5, atol=1e-8)
    assert np.all(np.isfinite(f_half)) and total > 0


@pytest.mark.parametrize("bad", [{"cuda_block_dim": 100}, {"cuda_block_dim": 2048}, {"cuda_max_registers": 8}],
                         ids=["block_not_warp_multiple", "block_too_large", "register_cap_too_small"])
def test_bad_cuda_launch_options_are_config_errors(device, bad):
    from texstream.core.errors import ConfigError

    prob, _ = plane_problem(device, ModelLayout(), n_photos=1, grid=2)
    with pytest.raises(ConfigError):
        StreamProblem(prob.texels, prob.photos, prob.layout, StreamConfig(**bad), device=device)
