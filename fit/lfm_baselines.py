"""The methods light field mapping by streaming replaces (Chen et al. 2002): resample each vertex
light field into a matrix (ring texel slots x the discrete view directions of the view map), then
PCA (truncated SVD of the matrix after the per-texel mean is subtracted) or NMF (Lee-Seung
multiplicative updates after the per-texel minimum is subtracted).

Same model, map sizes, diffuse term and error metric as the streaming fit (fit/lfm.py): the result
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

from .lfm import LFMParams, LFMProblem, view_directions, view_mask


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


def resample(problem: LFMProblem, Y: np.ndarray, E: np.ndarray, diffuse: np.ndarray, chunk: int = 32):
    """Per vertex light-field matrices, padded: (V, Rmax, M, 3) values L_j(s) (y / e - d(s)) at the
    discrete views (0 in padding rows, unseen texels and view texels outside the mask), and the
    (V, Rmax) slot of each row (-1 for padding)."""
    g = problem.geom
    V, M = problem.V, problem.M
    counts = np.diff(g.ring_start)
    rmax = int(counts.max()) if counts.size else 0
    rows = -np.ones((V, rmax), np.int64)
    col = np.arange(rmax)[None, :]
    valid = col < counts[:, None]
    rows[valid] = g.ring_slots[(g.ring_start[:-1][:, None] + col)[valid]]
    dirs = view_directions(problem.R, problem.cfg.view_map)                       # (M, 3) local
    mask = view_mask(problem.R, problem.cfg.view_map).astype(bool)
    centers = problem.samples.centers                                             # (P, 3)
    seen = E > 0                                                                  # (P, N)
    radiance = np.where(seen[..., None], Y / np.where(seen, E, 1.0)[..., None], 0.0)
    F = np.zeros((V, rmax, M, 3))
    for b in range(0, V, chunk):
        vs = np.arange(b, min(b + chunk, V))
        w = centers[None, :, :] - g.vpos[vs][:, None, :]                        # (v, P, 3)
        w /= np.linalg.norm(w, axis=2, keepdims=True)
        frame = np.stack([g.vtan[vs], g.vbit[vs], g.vnrm[vs]], 1)                 # (v, 3, 3)
        local = np.einsum("vpk,vjk->vpj", w, frame)
        cos = np.einsum("mj,vpj->vmp", dirs, local)                               # (v, M, P)
        sl = rows[vs]                                                             # (v, r)
        tex = np.maximum(sl, 0) // 3
        vis = seen[:, tex].transpose(1, 2, 0) & (sl >= 0)[..., None]              # (v, r, P)
        score = np.where(vis[:, :, None, :], cos[:, None, :, :], -np.inf)         # (v, r, M, P)
        best = score.argmax(axis=3)                                               # (v, r, M)
        any_vis = vis.any(axis=2)                                                 # (v, r)
        val = radiance[best, tex[:, :, None]]                                     # (v, r, M, 3)
        hat = g.slot_hat[np.maximum(sl, 0)]
        block = hat[:, :, None, None] * (val - diffuse[tex][:, :, None, :])
        block *= (any_vis[:, :, None] & mask[None, None, :])[..., None]
        F[vs] = block
    return F, rows


def _to_params(problem: LFMProblem, diffuse, rows, W, Hm) -> LFMParams:
    """Padded factors W (V, Rmax, K, 3) and Hm (V, K, M, 3) into the model's slot / view-map arrays."""
    G = np.zeros((problem.S, problem.K, 3))
    ok = rows >= 0
    G[rows[ok]] = W[ok]
    return LFMParams(diffuse.copy(), G, Hm * view_mask(problem.R, problem.cfg.view_map)[None, None, :, None])


def fit_pca(problem: LFMProblem) -> tuple[LFMParams, dict]:
    """Chen et al.'s PCA: per vertex and channel the rank-K truncated SVD of the resampled matrix
    (mean per texel subtracted: ``problem`` must use diffuse "mean"). Returns the parameters and
    timings (resampling, factorization) and the matrices' memory."""
    t0 = time.perf_counter()
    problem.compute_diffuse("mean")
    diffuse = problem.diffuse.numpy()
    Y, E = gather_samples(problem)
    F, rows = resample(problem, Y, E, diffuse)
    t1 = time.perf_counter()
    K = problem.K
    Fc = np.moveaxis(F, 3, 1)                                                     # (V, 3, r, M)
    U, S, Vt = np.linalg.svd(Fc, full_matrices=False)
    k = min(K, S.shape[-1])
    W = np.zeros(Fc.shape[:3] + (K,))
    W[..., :k] = U[..., :k] * S[..., None, :k]
    Hm = np.zeros(Fc.shape[:2] + (K, Fc.shape[3]))
    Hm[:, :, :k] = Vt[:, :, :k]
    params = _to_params(problem, diffuse, rows, np.moveaxis(W, 1, 3), np.moveaxis(Hm, 1, 3))
    t2 = time.perf_counter()
    return params, {"resample_s": t1 - t0, "factor_s": t2 - t1, "total_s": t2 - t0,
                    "samples_bytes": int(Y.nbytes + E.nbytes), "matrix_bytes": int(F.nbytes)}


def fit_nmf(problem: LFMProblem, iterations: int = 200) -> tuple[LFMParams, dict]:
    """Chen et al.'s NMF: per vertex and channel, Lee-Seung multiplicative updates (Frobenius) of a
    rank-K non-negative factorization of the resampled matrix (minimum per texel subtracted)."""
    t0 = time.perf_counter()
    problem.compute_diffuse("min")
    diffuse = problem.diffuse.numpy()
    Y, E = gather_samples(problem)
    F, rows = resample(problem, Y, E, diffuse)
    F = np.maximum(F, 0.0)
    t1 = time.perf_counter()
    K = problem.K
    Fc = np.moveaxis(F, 3, 1)                                                     # (V, 3, r, M)
    V, C, R, M = Fc.shape
    m = view_mask(problem.R, problem.cfg.view_map).astype(np.float64)
    scale = np.sqrt(np.maximum(Fc.mean(axis=(2, 3), keepdims=True), 1e-12) / K)
    c = (np.arange(problem.R) + 0.5) / problem.R * 2.0 - 1.0
    u, v = np.meshgrid(c, c)
    basis = np.stack([np.ones_like(u), 1 + 0.5 * u, 1 + 0.5 * v, 1.5 - 0.5 * (u * u + v * v)]).reshape(4, -1)[:K]
    Hm = np.broadcast_to(basis * m, (V, C, K, M)) * scale
    W = np.ones((V, C, R, K)) * scale * (np.abs(Fc).sum(axis=3, keepdims=True) > 0)
    eps = 1e-12
    for _ in range(int(iterations)):
        Hm = Hm * (np.einsum("vcrk,vcrm->vckm", W, Fc) / (np.einsum("vcrk,vcrj,vcjm->vckm", W, W, Hm) + eps))
        W = W * (np.einsum("vcrm,vckm->vcrk", Fc, Hm) / (np.einsum("vcrj,vcjm,vckm->vcrk", W, Hm, Hm) + eps))
    params = _to_params(problem, diffuse, rows, np.moveaxis(W, 1, 3), np.moveaxis(Hm, 1, 3))
    t2 = time.perf_counter()
    return params, {"resample_s": t1 - t0, "factor_s": t2 - t1, "total_s": t2 - t0,
                    "samples_bytes": int(Y.nbytes + E.nbytes), "matrix_bytes": int(F.nbytes)}
