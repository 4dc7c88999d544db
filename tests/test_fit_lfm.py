"""Light field mapping fitted by image streaming (fit/lfm.py, fit/kernels/lfm.py; issue 18).

Tiny meshes with samples given as tables (no photos): the gradients and curvature against finite
differences, the index-table gathers against a dense numpy reference, and the recovery of a surface
light field that is exactly rank K at the view-map resolution.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from texstream.fit.models.lfm.problem import LFMConfig, LFMGeometry, LFMProblem, TableSamples, fit_lfm


def grid_mesh(n: int = 3, bump: float = 0.15):
    """An (n+1) x (n+1) vertex grid over [0, 1]^2, z a bump (flat for bump = 0), two faces per cell."""
    xs = np.linspace(0.0, 1.0, n + 1)
    x, y = np.meshgrid(xs, xs)
    z = bump * np.sin(2.0 * x) * np.cos(1.5 * y)
    pts = np.stack([x.ravel(), y.ravel(), z.ravel()], 1)
    faces = []
    for j in range(n):
        for i in range(n):
            a = j * (n + 1) + i
            faces += [(a, a + 1, a + n + 2), (a, a + n + 2, a + n + 1)]
    faces = np.array(faces, np.int64)
    nrm = np.zeros_like(pts)
    fn = np.cross(pts[faces[:, 1]] - pts[faces[:, 0]], pts[faces[:, 2]] - pts[faces[:, 0]])
    for c in range(3):
        np.add.at(nrm, faces[:, c], fn)
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    return pts, faces, nrm


def texels_on(pts, faces, per_face: int, rng):
    """Random texels: ``per_face`` per face, random barycentrics."""
    face = np.repeat(np.arange(len(faces)), per_face)
    b = rng.dirichlet(np.ones(3), size=face.size)
    pos = np.einsum("nj,njk->nk", b, pts[faces[face]])
    return face, b, pos


def tiny_problem(device, cfg: LFMConfig, seed: int = 0, photos: int = 6, unseen: float = 0.2, threads: int = 1):
    rng = np.random.default_rng(seed)
    pts, faces, nrm = grid_mesh()
    face, bary, pos = texels_on(pts, faces, 3, rng)
    geom = LFMGeometry.build(pts, faces, nrm, face, bary, pos)
    centers = np.stack([rng.uniform(-1, 2, photos), rng.uniform(-1, 2, photos), rng.uniform(1.5, 3, photos)], 1)
    y = rng.uniform(0.1, 1.0, (photos, face.size, 3))
    e = rng.uniform(0.5, 1.5, (photos, 1)) * (rng.uniform(size=(photos, face.size)) > unseen)
    pr = LFMProblem(geom, TableSamples(y, e, centers, device), cfg, device, threads)
    pr.compute_diffuse()
    return pr, rng


def random_params(pr, rng):
    G = rng.normal(size=(pr.S, pr.K, 3)) * 0.3
    H = rng.normal(size=(pr.V, pr.K, pr.M, 3)) * (pr.mask_np[None, None, :, None])
    return G, H


def total_objective(pr, G, H) -> float:
    f = pr.new_patch()
    pr.evaluate(pr.new_G(G), pr.new_H(H), f)
    return float(f.numpy().sum())


@pytest.mark.parametrize("lookup,mapping", [("bilinear", "disk"), ("nearest", "hemioct")])
def test_gradient_and_curvature_match_finite_differences(device, lookup, mapping):
    cfg = LFMConfig(terms=2, view_res=6, lookup=lookup, view_map=mapping, laplacian=0.7)
    pr, rng = tiny_problem(device, cfg)
    G, H = random_params(pr, rng)
    f = pr.new_patch()
    gG, gH = pr.new_G(), pr.new_H()
    pr.evaluate(pr.new_G(G), pr.new_H(H), f, gG, gH)
    gG, gH = gG.numpy().reshape(G.shape), gH.numpy().reshape(H.shape)
    step = 1e-2
    # the model is linear in each single surface- or view-map entry, so the objective is quadratic in it
    # and central differences have no truncation error; what is left is rounding, ~1e-16 x E (~5e3)
    # / step = 5e-11 against derivatives of O(0.1): 1e-8 relative
    checked = 0
    for _ in range(12):
        s, k, c = rng.integers(pr.S), rng.integers(pr.K), rng.integers(3)
        Gp, Gm = G.copy(), G.copy()
        Gp[s, k, c] += step
        Gm[s, k, c] -= step
        fd = (total_objective(pr, Gp, H) - total_objective(pr, Gm, H)) / (2 * step)
        assert fd == pytest.approx(gG[s, k, c], rel=1e-8, abs=1e-9)
        checked += abs(fd) > 1e-6
    touched = np.flatnonzero(np.abs(gH).sum(axis=3).reshape(-1) > 0)  # (vertex, term, texel) some sample reads
    for _ in range(12):
        v, k, q = np.unravel_index(int(rng.choice(touched)), gH.shape[:3])
        c = rng.integers(3)
        Hp, Hm = H.copy(), H.copy()
        Hp[v, k, q, c] += step
        Hm[v, k, q, c] -= step
        fd = (total_objective(pr, G, Hp) - total_objective(pr, G, Hm)) / (2 * step)
        assert fd == pytest.approx(gH[v, k, q, c], rel=1e-8, abs=1e-9)
        checked += abs(fd) > 1e-6
    assert checked >= 12, "most checked entries should have a non-trivial derivative"
    # d^T H d: the derivative of g(x + a d).d at a = 0, per patch (patches share no parameter)
    DG = rng.normal(size=G.shape)
    DH = rng.normal(size=H.shape) * pr.mask_np[None, None, :, None]
    dhd, gn = pr.new_patch(), pr.new_patch()
    pr.evaluate(pr.new_G(G), pr.new_H(H), pr.new_patch(), DG=pr.new_G(DG), DH=pr.new_H(DH), dhd=dhd, gn=gn)

    def slope(a):
        f, gG2, gH2 = pr.new_patch(), pr.new_G(), pr.new_H()
        pr.evaluate(pr.new_G(G + a * DG), pr.new_H(H + a * DH), f, gG2, gH2)
        d = pr.new_patch()
        pr.patch_dot(gG2, pr.new_G(DG), gH2, pr.new_H(DH), d)
        return d.numpy()
    # g(x + a d).d is a cubic in a, so the five-point stencil (exact to degree 4) has no truncation
    # error at a = 0.1; rounding ~1e-16 x |g.d| (~1e3) / 0.1: 1e-8 relative
    a = 0.1
    fd = (8 * (slope(a) - slope(-a)) - (slope(2 * a) - slope(-2 * a))) / (12 * a)
    np.testing.assert_allclose(dhd.numpy(), fd, rtol=1e-8, atol=1e-8)
    assert np.all(gn.numpy() >= 0)


def dense_reference(pr, samples, G, H):
    """Objective per patch and gradient by plain loops over photos, texels and slots (numpy)."""
    from texstream.fit.models.lfm.problem import view_mask  # noqa: F401  (the mask is the problem's)

    geom = pr.geom
    f = np.zeros((pr.V, 3))
    gG = np.zeros_like(G)
    gH = np.zeros_like(H)
    d = pr.diffuse.numpy()
    y_all = samples.y.numpy().reshape(samples.n_photos, pr.N, 3)
    e_all = samples.e.numpy().reshape(samples.n_photos, pr.N)
    for p in range(samples.n_photos):
        pr._taps(p)
        idx, wt = pr.tap_idx.numpy(), pr.tap_w.numpy()
        for s in range(pr.N):
            e = e_all[p, s]
            if e <= 0:
                continue
            for j in range(3):
                slot = 3 * s + j
                v = geom.slot_vertex[slot]
                h = np.einsum("t,ktc->kc", wt[v], H[v][:, idx[v]])
                r = geom.slot_hat[slot] * (y_all[p, s] - e * d[s]) - e * (G[slot] * h).sum(0)
                f[v] += 0.5 * r * r
                gG[slot] -= e * r * h
                for t in range(4):
                    gH[v, :, idx[v][t]] -= wt[v][t] * e * r * G[slot]
    lam = pr.lam
    R = pr.R
    m = pr.mask_np
    for v in range(pr.V):
        for k in range(pr.K):
            for q in range(R * R):
                for q2 in ((q + 1) if q % R + 1 < R else -1, q + R if q + R < R * R else -1):
                    if q2 < 0 or not m[q] or not m[q2]:
                        continue
                    diff = H[v, k, q] - H[v, k, q2]
                    f[v] += 0.5 * lam * diff * diff
                    gH[v, k, q] += lam * diff
                    gH[v, k, q2] -= lam * diff
    return f, gG, gH


def test_gathers_equal_dense_reference(device):
    cfg = LFMConfig(terms=2, view_res=5, lookup="bilinear", laplacian=0.3)
    pr, rng = tiny_problem(device, cfg, seed=3, photos=4)
    G, H = random_params(pr, rng)
    f = pr.new_patch()
    gG, gH = pr.new_G(), pr.new_H()
    pr.evaluate(pr.new_G(G), pr.new_H(H), f, gG, gH)
    rf, rgG, rgH = dense_reference(pr, pr.samples, G, H)
    # the same sums in another order (fp64): agreement to rounding, 1e-12 relative
    np.testing.assert_allclose(f.numpy(), rf, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(gG.numpy().reshape(G.shape), rgG, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(gH.numpy().reshape(H.shape), rgH, rtol=1e-12, atol=1e-12)
    # every slot sits in exactly one ring, and its vertex is the welded corner of its owner face
    assert np.array_equal(np.sort(pr.geom.ring_slots), np.arange(pr.S))


def test_photo_batches_give_identical_sums(device):
    """The batched passes add every photo in order whatever the batch size: one photo per batch, a
    partial last batch (3 + 3 + 1) and all 7 at once give bit-identical objective, gradients and
    curvature; so do the slot pass and the gather split over 3 CPU threads (each texel and vertex summed by
    one of them), the Gauss-Newton diagonal too."""
    outs = []
    for batch, threads in ((1, 1), (3, 1), (7, 1), (3, 3)):
        cfg = LFMConfig(terms=2, view_res=5, lookup="bilinear", laplacian=0.3, photo_batch=batch,
                        precondition="jacobi")  # jacobi: the diagonal's scratch
        pr, rng = tiny_problem(device, cfg, seed=5, photos=7, threads=threads)
        assert pr.B == batch
        G, H = random_params(pr, rng)
        DG, DH = random_params(pr, rng)
        f, dhd, gn = pr.new_patch(), pr.new_patch(), pr.new_patch()
        gG, gH = pr.new_G(), pr.new_H()
        pr.evaluate(pr.new_G(G), pr.new_H(H), f, gG, gH)
        f2 = pr.new_patch()
        pr.evaluate(pr.new_G(G), pr.new_H(H), f2, DG=pr.new_G(DG), DH=pr.new_H(DH), dhd=dhd, gn=gn)
        f3, xG, xH = pr.new_patch(), pr.new_G(), pr.new_H()
        pr.evaluate(pr.new_G(G), pr.new_H(H), f3, pr.new_G(), pr.new_H(), diag_G=xG, diag_H=xH)
        outs.append([a.numpy() for a in (f, gG, gH, f2, dhd, gn, f3, xG, xH)])
    for other in outs[1:]:
        for a, b in zip(outs[0], other):
            assert np.array_equal(a, b)


def rank_k_case(device, K: int, cfg: LFMConfig, seed: int = 1):
    """A flat patch seen by far cameras whose directions sit on distinct view-map texel centres: every
    vertex sees one photo along the same direction (nearest lookup, identical frames), and the light
    field d0(s) + sum_k a_k(s) b_k(view texel) is exactly rank K at the map resolution."""
    from texstream.fit.models.lfm.problem import view_directions

    rng = np.random.default_rng(seed)
    pts, faces, nrm = grid_mesh(3, bump=0.0)
    face, bary, pos = texels_on(pts, faces, 4, rng)
    geom = LFMGeometry.build(pts, faces, nrm, face, bary, pos)
    dirs = view_directions(cfg.view_res, cfg.view_map)
    inside = np.flatnonzero(dirs[:, 2] > 0.3)
    pick = rng.choice(inside, size=min(30, inside.size), replace=False)
    t, b = geom.vtan[0], geom.vbit[0]
    n = geom.vnrm[0]
    world = dirs[pick] @ np.stack([t, b, n])            # local -> world rows
    centers = np.array([0.5, 0.5, 0.0]) + 1e7 * world
    a = rng.uniform(0.2, 1.0, (face.size, K, 3))
    bmap = rng.uniform(0.0, 1.0, (K, dirs.shape[0], 3))
    d0 = rng.uniform(0.1, 0.5, (face.size, 3))
    f = d0[None] + np.einsum("skc,kpc->psc", a, bmap[:, pick])
    e = np.tile(rng.uniform(0.6, 1.4, (len(pick), 1)), (1, face.size))
    pr = LFMProblem(geom, TableSamples(f * e[..., None], e, centers, device), cfg, device)
    return pr


@pytest.mark.parametrize("K", [1, 2])
def test_exact_rank_k_light_field_is_recovered(device, K):
    cfg = LFMConfig(terms=K, view_res=8, lookup="nearest", laplacian=0.0, iterations=150, rel_tol=0.0,
                    sync_every=10)
    pr = rank_k_case(device, K, cfg)
    res = fit_lfm(pr)
    err = pr.model_error(pr.new_G(res.params.G), pr.new_H(res.params.H))
    # the bar: an exactly representable light field is recovered to < 1e-4 relative (RMS over
    # every sample, the full model: d plus the three vertex light fields)
    assert err["relative_rms"] < 1e-4, err
    objs = [t["objective"] for t in res.trace]
    # per-patch acceptance never raises E; the gauge balancing re-evaluates E, equal up to rounding
    # (1e-12 relative, plus 1e-24 of the start once E is down to round-off itself)
    assert all(b <= a * (1 + 1e-12) + 1e-24 * objs[0] for a, b in zip(objs, objs[1:]))


def test_jacobi_cg_recovers_exact_rank_k(device):
    cfg = LFMConfig(terms=2, view_res=8, lookup="nearest", laplacian=0.0, iterations=150, rel_tol=0.0,
                    sync_every=10, precondition="jacobi")
    pr = rank_k_case(device, 2, cfg)
    res = fit_lfm(pr)
    err = pr.model_error(pr.new_G(res.params.G), pr.new_H(res.params.H))
    # the same bar as plain CG (an exactly representable field, < 1e-4 relative RMS)
    assert err["relative_rms"] < 1e-4, err


def test_jacobi_diagonal_equals_dense_reference(device):
    """The Gauss-Newton diagonal of the data term (surface maps: sum (e h_k)^2; view maps: sum over
    samples of (w_t e g_k)^2 at each tap) from the batched passes equals plain loops (numpy)."""
    cfg = LFMConfig(terms=2, view_res=5, lookup="bilinear", laplacian=0.3, precondition="jacobi", photo_batch=3)
    pr, rng = tiny_problem(device, cfg, seed=4, photos=7)
    G, H = random_params(pr, rng)
    f, gG, gH, xG, xH = pr.new_patch(), pr.new_G(), pr.new_H(), pr.new_G(), pr.new_H()
    pr.evaluate(pr.new_G(G), pr.new_H(H), f, gG, gH, diag_G=xG, diag_H=xH)
    rG, rH = np.zeros_like(G), np.zeros_like(H)
    e_all = pr.samples.e.numpy().reshape(pr.samples.n_photos, pr.N)
    for p in range(pr.samples.n_photos):
        pr._taps(p)
        idx, wt = pr.tap_idx.numpy(), pr.tap_w.numpy()
        for s in range(pr.N):
            e = e_all[p, s]
            if e <= 0:
                continue
            for j in range(3):
                slot = 3 * s + j
                v = pr.geom.slot_vertex[slot]
                h = np.einsum("t,ktc->kc", wt[v], H[v][:, idx[v]])
                rG[slot] += (e * h) ** 2
                for t in range(4):
                    rH[v, :, idx[v][t]] += (wt[v][t] * e * G[slot]) ** 2
    # the same sums in another order (fp64): 1e-12 relative
    np.testing.assert_allclose(xG.numpy().reshape(G.shape), rG, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(xH.numpy().reshape(H.shape), rH, rtol=1e-12, atol=1e-14)


def test_cg_hessian_beats_steepest_descent(device):
    """The dissertation's comparison (Fig. 7.2): CG with the Hessian step (and the default gauge
    balancing) reaches in 25 iterations at least the error of 250 iterations of the dissertation's
    steepest descent (backtracking step, no gauge balancing). Steepest descent *with* the balancing is
    far stronger than the dissertation's (docs/lfm.md), so this compares the methods as published."""
    base = dict(terms=2, view_res=8, lookup="nearest", laplacian=0.0, rel_tol=0.0, sync_every=5)
    cg = fit_lfm(rank_k_case(device, 2, LFMConfig(**base, iterations=25)))
    sd = fit_lfm(rank_k_case(device, 2, LFMConfig(**base, iterations=250, optimizer="sd", step="backtrack",
                                                        balance_every=0)))
    assert cg.trace[-1]["objective"] <= sd.trace[-1]["objective"], (cg.trace[-1], sd.trace[-1])
    assert math.isfinite(cg.trace[-1]["objective"])


def test_pca_and_nmf_baselines(device):
    """Chen et al.'s methods on the exactly rank-K light field: PCA recovers it (the nearest-view
    resampling copies a seen direction's column into the unseen ones, so the matrices stay rank K),
    NMF approximates it (non-negative after the minimum, but rank K + 1 then: approximate only)."""
    from texstream.fit.models.lfm.baselines import fit_nmf, fit_pca

    cfg = LFMConfig(terms=2, view_res=8, lookup="nearest", laplacian=0.0)
    pr = rank_k_case(device, 2, cfg)
    params, info = fit_pca(pr)
    err = pr.model_error(pr.new_G(params.G), pr.new_H(params.H))
    assert err["relative_rms"] < 1e-8, err   # an SVD of exact data: round-off only
    assert info["matrix_bytes"] > 0 and info["samples_bytes"] == pr.samples.n_photos * pr.N * 4 * 8
    params, _ = fit_nmf(pr, iterations=300)
    nmf = pr.model_error(pr.new_G(params.G), pr.new_H(params.H))
    zero = pr.model_error(pr.new_G(), pr.new_H())  # the minimum alone
    # NMF of a rank-K + 1 matrix with K terms: a fraction of the minimum-only error is left
    assert nmf["relative_rms"] < 0.5 * zero["relative_rms"], (nmf, zero)


def patch_vector(pr, G, H, v, c):
    """Patch (v, c)'s parameters as one vector: its ring slots' surface-map entries, its view maps."""
    g = pr.geom
    slots = g.ring_slots[g.ring_start[v]:g.ring_start[v + 1]]
    return np.concatenate([G[slots, :, c].reshape(-1), H[v, :, :, c].reshape(-1)])


def test_lbfgs_two_loop_equals_dense_reference(device):
    """The batched L-BFGS state (ring buffers, per patch and channel counts, rejected and
    curvature-failing pairs skipped) gives per patch the direction of a plain numpy two-loop
    recursion over that patch's own accepted pairs."""
    from texstream.fit.models.lfm.problem import PatchLBFGS

    cfg = LFMConfig(terms=2, view_res=5, lookup="bilinear", laplacian=0.3)
    pr, rng = tiny_problem(device, cfg, seed=5, photos=4)
    memory = 3
    lb = PatchLBFGS(pr, memory)
    G, H = random_params(pr, rng)
    mask = pr.mask_np[None, None, :, None]

    def grad(G, H):
        f, gG, gH = pr.new_patch(), pr.new_G(), pr.new_H()
        pr.evaluate(pr.new_G(G), pr.new_H(H), f, gG, gH)
        return gG.numpy().reshape(G.shape), gH.numpy().reshape(H.shape)

    gG, gH = grad(G, H)
    lb.reset(pr.new_G(gG), pr.new_H(gH))
    pairs = {(v, c): [] for v in range(pr.V) for c in range(3)}
    gamma = {}
    for v in range(pr.V):
        for c in range(3):
            n = np.linalg.norm(patch_vector(pr, gG, gH, v, c))
            gamma[v, c] = 1.0 / n if n > 0 else 0.0
    for it in range(6):   # more pushes than the memory: the ring wraps
        TG = G + 0.05 * rng.normal(size=G.shape)
        TH = H + 0.05 * rng.normal(size=H.shape) * mask
        tgG, tgH = grad(TG, TH)
        acc = (rng.uniform(size=(pr.V, 3)) < 0.75).astype(np.float64)
        alpha = np.ones((pr.V, 3))   # every channel took a step (no restart)
        lb.push(pr.new_G(G), pr.new_G(TG), pr.new_G(gG), pr.new_G(tgG), pr.new_H(H), pr.new_H(TH), pr.new_H(gH),
                pr.new_H(tgH), wp_vec3(pr, acc), wp_vec3(pr, alpha))
        for v in range(pr.V):
            for c in range(3):
                if not acc[v, c]:
                    continue
                s = patch_vector(pr, TG, TH, v, c) - patch_vector(pr, G, H, v, c)
                y = patch_vector(pr, tgG, tgH, v, c) - patch_vector(pr, gG, gH, v, c)
                if s @ y > 0 and y @ y > 0:
                    pairs[v, c] = (pairs[v, c] + [(s, y)])[-memory:]
                    gamma[v, c] = (s @ y) / (y @ y)
        # adopt the accepted trials per patch
        sv = pr.geom.slot_vertex
        G = np.where(acc[sv][:, None, :] > 0, TG, G)
        gG = np.where(acc[sv][:, None, :] > 0, tgG, gG)
        H = np.where(acc[:, None, None, :] > 0, TH, H)
        gH = np.where(acc[:, None, None, :] > 0, tgH, gH)
    DG, DH = pr.new_G(), pr.new_H()
    lb.direction(pr.new_G(gG), pr.new_H(gH), DG, DH)
    DG, DH = DG.numpy().reshape(G.shape), DH.numpy().reshape(H.shape)
    used = 0
    for v in range(pr.V):
        for c in range(3):
            q = patch_vector(pr, gG, gH, v, c) * np.concatenate(
                [np.ones(len(patch_vector(pr, gG, gH, v, c)) - pr.K * pr.M), np.tile(pr.mask_np, pr.K)])
            a = []
            for s, y in reversed(pairs[v, c]):
                a.append((s @ q) / (s @ y))
                q = q - a[-1] * y
            r = gamma[v, c] * q * np.concatenate([np.ones(len(q) - pr.K * pr.M), np.tile(pr.mask_np, pr.K)])
            for (s, y), ai in zip(pairs[v, c], reversed(a)):
                r = r + (ai - (y @ r) / (s @ y)) * s
            used += len(pairs[v, c]) == memory
            # the same sums in another order (fp64): rounding only, 1e-9 relative to the direction's size
            np.testing.assert_allclose(patch_vector(pr, DG, DH, v, c), -r, rtol=1e-9,
                                       atol=1e-9 * max(np.abs(r).max(), 1e-300))
    assert used > 0, "some patch should have a full (wrapped) history"


def wp_vec3(pr, a):
    import warp as wp

    return wp.array(np.ascontiguousarray(a, np.float64), dtype=wp.vec3d, device=pr.device)


@pytest.mark.parametrize("step,bar", [("hessian", 1e-4), ("backtrack", 1e-3)])
def test_lbfgs_recovers_exact_rank_k(device, step, bar):
    """L-BFGS per patch with the Hessian step reaches the issue's < 1e-4 relative error on the exactly
    rank-2 light field in 150 iterations (measured 1.9e-10); with the unit quasi-Newton step and
    backtracking (no curvature pass, half the passes) it is slower: measured 3.1e-4 after 150 and
    5.7e-5 after 300, so 1e-3 here. Per-patch acceptance keeps the objective from rising."""
    cfg = LFMConfig(terms=2, view_res=8, lookup="nearest", laplacian=0.0, iterations=150, rel_tol=0.0,
                    sync_every=10, optimizer="lbfgs", step=step)
    pr = rank_k_case(device, 2, cfg)
    res = fit_lfm(pr)
    err = pr.model_error(pr.new_G(res.params.G), pr.new_H(res.params.H))
    assert err["relative_rms"] < bar, err
    objs = [t["objective"] for t in res.trace]
    # as in the CG test: acceptance never raises E; the gauge balancing re-evaluates it (rounding)
    assert all(b <= a * (1 + 1e-12) + 1e-24 * objs[0] for a, b in zip(objs, objs[1:]))


@pytest.mark.parametrize("rows", [5, 90])
def test_gram_truncated_svd_equals_numpy_svd(rows):
    """PCA's rank-K factorization through the smaller Gram matrix (r x r for short rings, M x M for
    long ones) gives numpy's thin-SVD rank-K approximation."""
    from texstream.fit.models.lfm.baselines import _truncated_svd

    rng = np.random.default_rng(7)
    F = rng.normal(size=(4, 3, rows, 16))
    W, Hm = _truncated_svd(F, 2)
    U, S, Vt = np.linalg.svd(F, full_matrices=False)
    ref = np.einsum("vcrk,vck,vckm->vcrm", U[..., :2], S[..., :2], Vt[..., :2, :])
    # eigh of the Gram matrix squares the condition number; with well separated singular values
    # (random Gaussian matrices) the rank-2 product agrees to ~1e-13 of its O(1) entries: 1e-10 here
    np.testing.assert_allclose(np.einsum("vcrk,vckm->vcrm", W, Hm), ref, atol=1e-10)
    np.testing.assert_allclose(np.linalg.norm(Hm, axis=-1), 1.0, rtol=1e-12)   # unit view maps, as PCA's


@pytest.mark.parametrize("optimizer,precondition", [("cg", "none"), ("lbfgs", "none"), ("cg", "jacobi")])
def test_objective_never_rises_with_the_laplacian(device, optimizer, precondition):
    """With the view-map Laplacian the objective is not invariant under the g h gauge (h / c costs
    1 / c^2 of the Laplacian), so the gauge balancing only shrinks view maps: with per-patch acceptance
    the objective read at every iteration never rises (an equalising balance raised it by ~40% each
    time on the star, undoing ten iterations)."""
    cfg = LFMConfig(terms=2, view_res=6, laplacian=2.0, iterations=40, rel_tol=0.0, sync_every=1, balance_every=4,
                    optimizer=optimizer, precondition=precondition)
    pr, _ = tiny_problem(device, cfg, seed=11, photos=8)
    res = fit_lfm(pr)
    objs = [t["objective"] for t in res.trace]
    # rounding only: the balancing re-evaluates E in another summation order (1e-12 relative)
    assert all(b <= a * (1 + 1e-12) for a, b in zip(objs, objs[1:])), objs
    assert objs[-1] < 0.5 * objs[0]


def test_the_automatic_photo_batch_holds_the_photos_its_scratch_budget_allows(device):
    """``photo_batch`` 0: as many photos a batch as their per-photo scratch (slot residuals and gathered view
    terms, 24 bytes each) fits in the device's budget (problem.py ``CPU_BATCH_BYTES`` on the CPU), at most 64: the
    tiny problem's 7 photos in one batch; the same sums whatever the batch (above)."""
    from texstream.fit.models.lfm.problem import CPU_BATCH_BYTES

    import warp as wp

    pr, _ = tiny_problem(device, LFMConfig(terms=1, view_res=4), photos=7)
    budget = (1 << 30) if wp.get_device(device).is_cuda else CPU_BATCH_BYTES
    per_photo = pr.S * 24 + pr.V * pr.K * 24
    assert budget // per_photo >= 7 and pr.B == 7


def test_a_fit_on_cpu_threads_gives_one_thread_s_parameters(device):
    """The slot pass and the gather split their texels and vertices over the CPU threads, each summed as one launch
    sums it: a fit on 3 threads ends at the parameters and objective of a fit on one, to the bit."""
    cfg = LFMConfig(terms=2, view_res=5, iterations=6, rel_tol=0.0, laplacian=0.3)
    fits = [fit_lfm(tiny_problem(device, cfg, seed=2, photos=5, threads=threads)[0]) for threads in (1, 3)]
    assert np.array_equal(fits[0].params.G, fits[1].params.G) and np.array_equal(fits[0].params.H, fits[1].params.H)
    assert [r["objective"] for r in fits[0].trace] == [r["objective"] for r in fits[1].trace]
