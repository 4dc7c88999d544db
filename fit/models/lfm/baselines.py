"""The methods light field mapping by streaming replaces (Chen et al. 2002): resample each vertex
light field into a matrix (ring texel slots x the discrete view directions of the view map), then
PCA (truncated SVD of the matrix after the per-texel mean is subtracted) or NMF (Lee-Seung
multiplicative updates after the per-texel minimum is subtracted).

Same model, map sizes, diffuse term and error metric as the streaming fit (fit/models/lfm/problem.py): the result
is an :class:`LFMParams` rendered and scored the same way. The resampling: every photo's sample of a
texel is placed at that photo's view direction in the vertex's frame, and each discrete direction
(view-map texel centre, :func:`view_directions`) takes the sample of the photo nearest to it in
angle among the photos that see the texel (a Voronoi resampling of the view hemisphere; Chen et
al. interpolate over a Delaunay triangulation of the views, equal at the photos' own directions).
Unlike streaming, this needs every sample in memory at once: (photos x texels x 3) float64.

Host numpy, batched over vertices (rings padded to the largest); imports only numpy and warp.
"""

from __future__ import annotations

import time

import numpy as np

from texstream.fit.models.lfm.problem import LFMParams, LFMProblem, view_directions, view_mask


def gather_samples(problem: LFMProblem) -> tuple[np.ndarray, np.ndarray]:
    """All samples: (P, N, 3) photo values and (P, N) exposures (0 = unseen), one streaming pass."""
    P, N = problem.samples.n_photos, problem.N
    Y = np.zeros((P, N, 3))
    E = np.zeros((P, N))
    for p in range(P):
        problem.samples.load(p, problem.obs_y, problem.obs_e)
        Y[p] = problem.obs_y.numpy()
        E[p] = problem.obs_e.numpy()
    return Y, E


def resample_chunks(problem: LFMProblem, Y: np.ndarray, E: np.ndarray, diffuse: np.ndarray,
                    budget: int = 2_000_000):
    """Yield the vertex light-field matrices in chunks of vertices of similar ring size (sorted),
    padded to the chunk's largest ring: (vertex ids (v,), values (v, r, M, 3) L_j(s) (y / e - d(s))
    at the discrete views, 0 in padding rows, unseen texels and view texels outside the mask;
    slot of each row (v, r), -1 for padding). ``budget``: padded matrix entries per chunk."""
    g = problem.geom
    M = problem.M
    counts = np.diff(g.ring_start)
    dirs = view_directions(problem.R, problem.cfg.view_map)                       # (M, 3) local
    mask = view_mask(problem.R, problem.cfg.view_map).astype(bool)
    centers = problem.samples.centers                                             # (P, 3)
    seen = E > 0                                                                  # (P, N)
    radiance = np.where(seen[..., None], Y / np.where(seen, E, 1.0)[..., None], 0.0)
    order = np.argsort(counts, kind="stable")
    b = 0
    while b < order.size:
        r = max(int(counts[order[b]]), 1)
        e = b + 1
        while e < order.size and (e - b + 1) * max(int(counts[order[e]]), 1) * M <= budget:
            e += 1
        vs = order[b:e]
        b = e
        r = max(int(counts[vs].max()), 1)
        col = np.arange(r)[None, :]
        valid = col < counts[vs][:, None]
        sl = -np.ones((vs.size, r), np.int64)
        sl[valid] = g.ring_slots[(g.ring_start[vs][:, None] + col)[valid]]
        w = centers[None, :, :] - g.vpos[vs][:, None, :]                        # (v, P, 3)
        w /= np.linalg.norm(w, axis=2, keepdims=True)
        frame = np.stack([g.vtan[vs], g.vbit[vs], g.vnrm[vs]], 1)                 # (v, 3, 3)
        local = np.einsum("vpk,vjk->vpj", w, frame)
        cos = np.einsum("mj,vpj->vpm", dirs, local)                               # (v, P, M)
        tex = np.maximum(sl, 0) // 3
        # per (vertex, view direction) the photos nearest first (ties: the lower index); each entry takes
        # the first of them that sees its texel. Most entries resolve at the first ranks, so the loop
        # touches only the unresolved ones instead of every photo for every entry.
        rank = np.argsort(-cos, axis=1, kind="stable")                            # (v, P, M)
        any_vis = seen[:, tex].any(axis=0) & (sl >= 0)                            # (v, r)
        val = np.zeros((vs.size, r, M, 3))
        vi, ri, mi = np.nonzero(np.broadcast_to(any_vis[:, :, None], (vs.size, r, M)))
        k = 0
        while vi.size:
            p = rank[vi, k, mi]
            t = tex[vi, ri]
            hit = seen[p, t]
            val[vi[hit], ri[hit], mi[hit]] = radiance[p[hit], t[hit]]
            vi, ri, mi = vi[~hit], ri[~hit], mi[~hit]
            k += 1
        hat = g.slot_hat[np.maximum(sl, 0)]
        block = hat[:, :, None, None] * (val - diffuse[tex][:, :, None, :])
        block *= (any_vis[:, :, None] & mask[None, None, :])[..., None]
        yield vs, block, sl


def _factor(problem: LFMProblem, method: str, iterations: int):
    """Resample and factorize chunk by chunk; returns (LFMParams, info)."""
    t0 = time.perf_counter()
    problem.compute_diffuse("mean" if method == "pca" else "min")
    diffuse = problem.diffuse.numpy()
    Y, E = gather_samples(problem)
    t_resample = time.perf_counter() - t0
    K, M = problem.K, problem.M
    m = view_mask(problem.R, problem.cfg.view_map).astype(np.float64)
    G = np.zeros((problem.S, K, 3))
    H = np.zeros((problem.V, K, M, 3))
    matrix_bytes = 0
    t_factor = 0.0
    t1 = time.perf_counter()
    for vs, F, sl in resample_chunks(problem, Y, E, diffuse):
        t2 = time.perf_counter()
        t_resample += t2 - t1
        matrix_bytes += int((sl >= 0).sum()) * M * 3 * 8
        Fc = np.moveaxis(F, 3, 1)                                                 # (v, 3, r, M)
        if method == "pca":
            W, Hm = _truncated_svd(Fc, K)
        else:
            W, Hm = _nmf(np.maximum(Fc, 0.0), K, m, problem.R, iterations)
        ok = sl >= 0
        G[sl[ok]] = np.moveaxis(W, 1, 3)[ok]
        H[vs] = np.moveaxis(Hm, 1, 3) * m[None, None, :, None]
        t1 = time.perf_counter()
        t_factor += t1 - t2
    params = LFMParams(diffuse, G, H)
    return params, {"resample_s": t_resample, "factor_s": t_factor, "total_s": t_resample + t_factor,
                    "samples_bytes": int(Y.nbytes + E.nbytes), "matrix_bytes": matrix_bytes}


def _truncated_svd(Fc: np.ndarray, K: int) -> tuple[np.ndarray, np.ndarray]:
    """Rank-K truncated SVD of each (r, M) matrix of (v, 3, r, M) through the smaller of its two Gram
    matrices: M x M (F^T F: its top K eigenvectors are the view maps, unit norm, and F V_k = U_k S_k
    the surface maps) for rings longer than the view map has texels, else r x r (F F^T: U_k, then
    the view maps U_k^T F / S_k). A batched eigh of small symmetric matrices instead of the thin SVD
    of the tall ones. The Gram matrix squares the condition number: singular values below ~1e-8 of
    the largest lose their digits, far below any term K keeps."""
    Ft = np.swapaxes(Fc, -1, -2)
    r, M = Fc.shape[-2:]
    k = min(K, r, M)
    W = np.zeros(Fc.shape[:3] + (K,))
    Hm = np.zeros(Fc.shape[:2] + (K, M))
    if r > M:
        _, vecs = np.linalg.eigh(Ft @ Fc)                                 # ascending eigenvalues
        top = vecs[..., ::-1][..., :k]                                    # (v, 3, M, k)
        W[..., :k] = Fc @ top
        Hm[:, :, :k] = np.swapaxes(top, -1, -2)
    else:
        vals, vecs = np.linalg.eigh(Fc @ Ft)
        top = vecs[..., ::-1][..., :k]                                    # (v, 3, r, k)
        sv = np.sqrt(np.maximum(vals[..., ::-1][..., :k], 0.0))           # (v, 3, k)
        proj = np.swapaxes(top, -1, -2) @ Fc                              # (v, 3, k, M) = S_k V_k^T
        ok = sv > 0
        Hm[:, :, :k] = np.where(ok[..., None], proj / np.where(ok, sv, 1.0)[..., None], 0.0)
        W[..., :k] = top * sv[..., None, :]
    return W, Hm


def _nmf(Fc: np.ndarray, K: int, m: np.ndarray, res: int, iterations: int):
    """Lee-Seung multiplicative updates on (v, 3, r, M) non-negative matrices; (W, H) factors."""
    V, C, R, M = Fc.shape
    scale = np.sqrt(np.maximum(Fc.mean(axis=(2, 3), keepdims=True), 1e-12) / K)
    c = (np.arange(res) + 0.5) / res * 2.0 - 1.0
    u, v = np.meshgrid(c, c)
    basis = np.stack([np.ones_like(u), 1 + 0.5 * u, 1 + 0.5 * v, 1.5 - 0.5 * (u * u + v * v)]).reshape(4, -1)[:K]
    Hm = np.broadcast_to(basis * m, (V, C, K, M)) * scale
    W = np.ones((V, C, R, K)) * scale * (Fc.sum(axis=3, keepdims=True) > 0)
    eps = 1e-12
    for _ in range(int(iterations)):   # batched matrix products (K x K Gram matrices), not r x M ones
        Wt = np.swapaxes(W, -1, -2)
        Hm = Hm * ((Wt @ Fc) / ((Wt @ W) @ Hm + eps))
        Ht = np.swapaxes(Hm, -1, -2)
        W = W * ((Fc @ Ht) / (W @ (Hm @ Ht) + eps))
    return W, Hm


def fit_pca(problem: LFMProblem) -> tuple[LFMParams, dict]:
    """Chen et al.'s PCA: per vertex and channel the rank-K truncated SVD of the resampled matrix
    (the per-texel mean subtracted: d = mean). Returns the parameters and timings (resampling,
    factorization) and memory (all samples; the resampled matrices, unpadded)."""
    return _factor(problem, "pca", 0)


def fit_nmf(problem: LFMProblem, iterations: int = 200) -> tuple[LFMParams, dict]:
    """Chen et al.'s NMF: per vertex and channel, Lee-Seung multiplicative updates (Frobenius) of a
    rank-K non-negative factorization of the resampled matrix (the per-texel minimum subtracted)."""
    return _factor(problem, "nmf", iterations)
