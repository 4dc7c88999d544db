"""The light and the albedo of the env_diffuse model, from the texels' radiance under one environment light.

The photos' data term of a Lambertian texel t under an SH light L (9, 3) is, per channel c,
sum_i (I_i / e_i - a_tc s_tc)^2 with s_tc = T_t . L_c (T_t its transfer vector, geometry/sh_transfer.py): its
prediction is the same in every photo, so that sum is w_t (R_tc - a_tc s_tc)^2 plus a constant, with R_t the
texel's mean radiance and w_t its sample count: exactly what the streaming radiance fit accumulates per texel
(its robust loss keeps glints out of R_t). So the photos stream once, and this module fits
E(L, a) = sum_t w_t sum_c (R_tc - a_tc T_t . L_c)^2 on those statistics, in float64.

**The ambiguities.** With a free albedo per texel any light fits (a_t = R_t / (T_t . L)). The light is
determined through texels that share an albedo but differ in normal or visibility, so it is fitted with
**shared materials** (a prior: K albedos m_k, each texel labelled with one) and only then each texel's own
albedo given that light, pulled toward its material's (``albedo_prior``; a texel no light reaches takes its
material's). Two ambiguities remain whatever the data, one scale per channel (a_c x g_c with L_c / g_c fit
alike); they are fixed after the fit, as the options say and model.json records (:func:`fix_gauge`): the
colour (``white``: the light's mean colour grey, or the mean albedo grey) and the overall scale (``scale``:
the mean albedo, or the environment's mean radiance, at ``scale_value``).

**Alternation, not a Schur complement.** For fixed labels E is bilinear in (m, L), and each block alone is an
exact linear least squares: the material albedos given L are K x 3 ratios of per-material sums, and the light
given the albedos is one 9 x 9 normal equation per channel (E is quadratic in L: its Gauss-Newton terms are
exact), its terms reduced over all texels: once per labelling into per-material sums
(:func:`material_statistics`), from which every pass assembles them in K x 81 flops. A Gauss-Newton step on
(m, L) with m eliminated by its Schur complement would need damping and a gauge constraint inside the step
(the per-channel scale makes the joint Hessian singular); the alternation needs neither, never raises E, and
is renormalised each pass (L[0, c] = 1, m absorbing it). Its passes cost microseconds, so its slower
convergence in flat valleys (tens of passes) costs nothing beside the photos' stream. Labels start from
k-means on the radiance's chromaticity and are then moved to the material nearest each texel's own albedo
under the fitted light (``relabel_rounds``), where the light's colour no longer shifts the texels' colours.

**Which texels steer the light.** A real material's albedo is not one colour: it drifts over the object (the
ornament's by 5-15%, each material along another axis), and a drift along the light's low-order terms passes
for them. From the second round the light's fit weighs each texel by (a) a Cauchy weight of its own albedo's
misfit to its material's (``robust_log``), (b) zero at a material edge (a texel with a neighbour of another
material, ``edge_neighbours``: the photos blend colours there), (c) its material's factor (v_min / v_k)^p, v_k
that material's mean squared misfit (``material_weight_power``): the materials that hold one albedo fix the
light, those that drift follow it. Then (d) :func:`slope_consensus` moves the light's dipole so that most
materials' albedos hold no slope along x, y, z. On the ornament (benchmarks/env_light_gap.py) the light's error
goes 5.7% (a) -> 4.3% (a-c) -> 2.2% (a-d), 2.1% being what a fit given the true per-texel albedo reaches.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from texstream.fit.models.materials import kmeans
from texstream.render import sh

_Y0 = sh.sh9_basis(np.array([0.0, 0.0, 1.0]))[0]
"""Y_0: an SH light's mean radiance over the sphere is L[0] x Y_0"""


@dataclasses.dataclass
class EnvSolution:
    """What the fit of the light and the albedo found (over the seen texels given to :func:`solve`).

    Attributes:
        light: (9, 3) SH light.
        albedo: (N, 3) per-texel albedo.
        materials: (K, 3) the shared albedos the light was fitted with (gauge-fixed like ``albedo``); (0, 3)
            for a given light.
        labels: (N,) each texel's material (-1: none, a given light).
        gauge: how the ambiguities were fixed (model.json's ``light.gauge``).
        trace: per round and pass count, the shared-albedo objective (model.json's ``light.trace``).
    """

    light: np.ndarray
    albedo: np.ndarray
    materials: np.ndarray
    labels: np.ndarray
    gauge: dict
    trace: list


def objective(light: np.ndarray, albedo: np.ndarray, radiance: np.ndarray, weight: np.ndarray,
              transfer: np.ndarray) -> float:
    """E = sum_t w_t |R_t - a_t * (T_t @ L)|^2 (per-texel albedo ``albedo`` (N, 3): a material's repeated)."""
    r = radiance - albedo * (transfer @ light)
    return float(np.sum(weight[:, None] * r * r))


def light_gradient(light: np.ndarray, albedo: np.ndarray, radiance: np.ndarray, weight: np.ndarray,
                   transfer: np.ndarray) -> np.ndarray:
    """(9, 3) dE / dL: -2 sum_t w_t (R_t - a_t s_t) a_t T_t, per channel."""
    r = radiance - albedo * (transfer @ light)
    return -2.0 * transfer.T @ (weight[:, None] * r * albedo)


def material_statistics(radiance, weight, transfer, labels, k: int) -> tuple[np.ndarray, np.ndarray, float]:
    """(G (k, 9, 9), h (k, 9, 3), sum w R^2): the texels reduced per material, G_k = sum_{t in k} w_t T_t T_t^T,
    h_k = sum_{t in k} w_t T_t R_t^T. For fixed labels E(L, m) = sum w R^2 - 2 sum_kc m_kc L_c.h_kc
    + sum_kc m_kc^2 L_c^T G_k L_c, so the alternation's passes cost K x 81 flops, not N x 81."""
    wt = weight[:, None] * transfer
    g = np.stack([wt[labels == j].T @ transfer[labels == j] for j in range(k)])
    h = np.stack([wt[labels == j].T @ radiance[labels == j] for j in range(k)])
    return g, h, float(np.sum(weight[:, None] * radiance * radiance))


def _fit_shared(stats, k: int, cfg, light0) -> tuple[np.ndarray, np.ndarray, float, int]:
    """(L, m, E, passes): the alternation for fixed labels on the per-material statistics, from ``light0``, L
    renormalised each pass (L[0, c] = 1)."""
    g, h, r2 = stats
    pull = np.ones(sh.SH_COUNT)
    pull[0] = 0.0

    def mats_given(light):
        return materials_given_light(stats, light)

    def energy(light, mats):
        lin = np.einsum("kc,kjc,jc->", mats, h, light)
        quad = np.einsum("kc,jc,kji,ic->", mats ** 2, light, g, light)
        return r2 - 2.0 * lin + quad

    light, prev, passes = light0.copy(), np.inf, 0
    mats = mats_given(light)
    for passes in range(1, cfg.light_passes + 1):
        light = np.zeros_like(light)
        for c in range(3):  # the light's normal equations per channel: A_c = sum_k m_kc^2 G_k, b_c = sum_k m_kc h_kc
            a = np.einsum("k,kji->ji", mats[:, c] ** 2, g)
            scale = max(float(np.trace(a)) / sh.SH_COUNT, 1e-300)
            light[:, c] = np.linalg.lstsq(a + np.diag(cfg.light_ridge * scale * pull), mats[:, c] @ h[:, :, c],
                                          rcond=None)[0]
        dc = np.where(np.abs(light[0]) > 1e-12, light[0], 1.0)
        light = light / dc  # the per-channel gauge, absorbed by the materials' albedos in the next block
        mats = mats_given(light)
        e = energy(light, mats)
        if np.isfinite(prev) and prev - e <= cfg.rel_tol * max(prev, 1e-300):
            break
        prev = e
    return light, mats, energy(light, mats), passes


def materials_given_light(stats, light: np.ndarray) -> np.ndarray:
    """(K, 3) the material albedos minimising E for the light ``light`` (:func:`material_statistics`'s
    ``stats``): per material and channel m = L.h / L^T G L; nonnegative."""
    g, h, _ = stats
    num = np.einsum("kjc,jc->kc", h, light)
    den = np.einsum("jc,kji,ic->kc", light, g, light)
    return np.maximum(np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0), 0.0)


def slope_consensus(light, radiance, weight, transfer, positions, labels, irls: int = 20) -> np.ndarray:
    """(9, 3) ``light`` with its band-1 terms (the dipole) moved so that most materials' albedos hold no slope.

    A material whose albedo drifts along an axis makes the light's fit tilt the dipole along it (the fit then
    trusts the most uniform material, which may drift too: the ornament's white by 5% along x, 3.4% of the light
    moved). Each material's own albedos under the light, log, regressed on position give its slopes b_k (3,) per
    channel; a dipole change d moves them by -J_k d (linearised: d log a_t = -T_t[1:4] . d / s_t, regressed alike).
    The d that zeroes the slopes of most materials (least absolute deviations over the materials' slopes,
    iteratively reweighted) is kept: a drift is taken to be one material's, not most materials'. With fewer than
    3 materials of 20+ texels (``weight`` > 0) there is no majority: the light is returned as it is."""
    light = np.array(light, np.float64)
    centred = positions - positions.mean(axis=0)
    positions = centred / max(float(np.sqrt(np.mean(np.sum(centred ** 2, axis=1)))), 1e-300)  # slopes per radius
    shading = transfer @ light
    own = albedo_given_light(light, radiance, weight, transfer)
    for c in range(3):
        slopes, jacobians = [], []
        for k in range(int(labels.max()) + 1):
            m = (labels == k) & (weight > 0) & (own[:, c] > 1e-6) & (shading[:, c] > 1e-9)
            if m.sum() < 20:
                continue
            w = weight[m]
            x = positions[m] - np.average(positions[m], axis=0, weights=w)
            design = np.c_[np.ones(len(x)), x]
            wd = design * w[:, None]
            normal = wd.T @ design
            rhs = np.c_[np.log(own[m, c]), transfer[m, 1:4] / shading[m, c][:, None]]
            coef = np.linalg.lstsq(normal, wd.T @ rhs, rcond=None)[0][1:]  # (3 axes, 1 + 3)
            slopes.append(coef[:, 0])
            jacobians.append(coef[:, 1:])
        if len(slopes) < 3:
            return light
        b, jac = np.concatenate(slopes), np.concatenate(jacobians)
        rw, d = np.ones(len(b)), np.zeros(3)
        for _ in range(irls):
            d = np.linalg.lstsq(jac * rw[:, None], b * rw, rcond=None)[0]
            rw = 1.0 / np.sqrt(np.maximum(np.abs(b - jac @ d), 1e-4))
        light[1:4, c] += d
    return light


def albedo_given_light(light, radiance, weight, transfer, prior_albedo=None, prior: float = 0.0) -> np.ndarray:
    """(N, 3) each texel's albedo minimising w_t (R_t - a_t s_t)^2 + p (a_t - prior_t)^2, p = ``prior`` x the
    mean of w s^2 over the texels (per channel); nonnegative."""
    s = transfer @ light
    ws2 = weight[:, None] * s * s
    num = weight[:, None] * s * radiance
    if prior_albedo is not None and prior > 0:
        p = prior * np.mean(ws2, axis=0)[None, :]
        return np.maximum((num + p * prior_albedo) / (ws2 + p), 0.0)
    return np.maximum(np.where(ws2 > 0, num / np.where(ws2 > 0, ws2, 1.0), 0.0), 0.0)


def _chromaticity(radiance: np.ndarray) -> np.ndarray:
    """log colour minus its mean over the channels: what k-means first groups texels by (shading-free when the
    light is grey)."""
    lr = np.log(np.maximum(radiance, 1e-6 * max(float(radiance.max()), 1e-30)))
    return lr - lr.mean(axis=1, keepdims=True)


def _fit_materials(radiance, weight, transfer, neighbours, k: int, cfg, trace: list):
    """(L, m, labels, E) with ``k`` materials: labels from chromaticity, then, round after round, relabelled under
    the fitted light and reweighted (:func:`_robust_weight`, the material edges left out, :func:`_material_weight`);
    E is the plain (unweighted) objective. ``neighbours``: (N, n) each texel's nearest texels, or None."""
    labels, _ = kmeans(_chromaticity(radiance), k)
    k = int(labels.max()) + 1
    light0 = np.zeros((sh.SH_COUNT, 3))
    light0[0] = 1.0
    fit_weight = weight
    for round_ in range(cfg.relabel_rounds):
        stats = material_statistics(radiance, fit_weight, transfer, labels, k)
        light, mats, e, passes = _fit_shared(stats, k, cfg, light0)
        # stationarity of the light at the shared albedos, relative (dE/dL over E / |L|: 0 at a minimum)
        grad = light_gradient(light, mats[labels], radiance, fit_weight, transfer)
        trace.append({"materials": k, "round": round_, "passes": passes, "objective": float(e),
                      "light_gradient_rel": float(np.abs(grad).max() * np.abs(light).max() / max(e, 1e-300))})
        own = albedo_given_light(light, radiance, weight, transfer)
        d = np.log(own[:, None, :] + 1e-3) - np.log(mats[None, :, :] + 1e-3)
        new = _merged(mats, cfg.merge_log_distance)[np.argmin((d * d).sum(-1), axis=1)]
        present = np.unique(new)
        new = np.searchsorted(present, new)  # materials nobody chose are dropped
        if np.array_equal(new, labels) and round_ > 0:
            break
        fit_weight = _robust_weight(weight, own, mats[present][new], cfg.robust_log)
        if neighbours is not None:  # the texels the photos blend across material edges
            fit_weight = fit_weight * (new[neighbours] == new[:, None]).all(axis=1)
        fit_weight = fit_weight * _material_weight(fit_weight, own, mats[present], new, cfg.material_weight_power)
        labels, k, light0 = new, len(present), light
    return light, mats, labels, objective(light, mats[labels], radiance, weight, transfer)


def _robust_weight(weight, own: np.ndarray, material: np.ndarray, scale: float) -> np.ndarray:
    """(N,) the texels' weights in the next round's light fit: Cauchy in the largest log-ratio q of a texel's own
    albedo (under the current light) to its material's, w / (1 + (q / scale)^2). Texels the photos blend across
    material edges, or of an albedo no material holds, then steer the light less than the texels that fit their
    material (on the ornament they moved it by 8%). ``scale`` 0: the weights as they are."""
    if scale <= 0:
        return weight
    q = np.max(np.abs(np.log(own + 1e-3) - np.log(material + 1e-3)), axis=1)
    return weight / (1.0 + (q / scale) ** 2)


def _material_weight(weight, own: np.ndarray, mats: np.ndarray, labels: np.ndarray, power: float) -> np.ndarray:
    """(N,) each texel's factor in the next round's light fit by how well its material fits one albedo:
    (v_min / v_k)^power, v_k the material's weighted mean squared log-ratio of its texels' own albedos (under the
    current light) to its albedo. A material whose albedo drifts across the object (a gradient, wear) lets that
    drift pass for the light's low-order terms, the ambiguity the shared albedo is there to remove; the materials
    that hold one albedo then steer the light (power 1: each material's residual as its noise variance, the
    maximum-likelihood weighting; larger powers trust the most uniform material more). 0: factors 1."""
    if power <= 0:
        return np.ones(len(labels))
    q = np.log(own + 1e-3) - np.log(mats[labels] + 1e-3)
    total = np.bincount(labels, weight, len(mats))
    var = np.bincount(labels, (q * q).mean(axis=1) * weight, len(mats)) / np.maximum(total, 1e-300)
    var = np.where(total > 0, np.maximum(var, 1e-12), np.inf)  # a material of edge texels only: no say
    best = float(var[np.isfinite(var)].min()) if np.isfinite(var).any() else 1.0
    return (best / var)[labels] ** power


def _merged(mats: np.ndarray, distance: float) -> np.ndarray:
    """(K,) each material's representative: materials whose albedos differ by less than ``distance`` in every
    channel's log are one (a split along the shading would let their albedo ratio absorb the light's
    variation, the ambiguity the materials are there to remove)."""
    logm = np.log(np.maximum(mats, 1e-6))
    rep = np.arange(len(mats))
    for i in range(len(mats)):
        for j in range(i):
            if rep[j] == j and np.max(np.abs(logm[i] - logm[j])) < distance:
                rep[i] = j
                break
    return rep


def fix_gauge(light: np.ndarray, albedo: np.ndarray, materials: np.ndarray, cfg) -> tuple:
    """(light, albedo, materials, gauge): the per-channel scale the photos cannot tell, fixed as ``cfg`` says
    (module docstring); E is unchanged."""
    mean_a = albedo.mean(axis=0) if len(albedo) else np.ones(3)
    if cfg.white == "light":
        g = light[0] / max(float(light[0].mean()), 1e-300)  # L_c / g_c: L[0] the same in every channel
    else:
        g = mean_a.mean() / np.maximum(mean_a, 1e-300)  # a_c x g_c: the mean albedo the same in every channel
    g = np.where(np.abs(g) > 1e-300, g, 1.0)
    light, albedo, materials = light / g, albedo * g, materials * g
    if cfg.scale == "mean_albedo":
        sigma = cfg.scale_value / max(float(albedo.mean()), 1e-300)
    else:
        sigma = float(light[0].mean()) * _Y0 / cfg.scale_value
    light, albedo, materials = light / sigma, albedo * sigma, materials * sigma
    gauge = {"colour": cfg.white, "scale": cfg.scale, "scale_value": cfg.scale_value,
             "mean_albedo": [float(v) for v in albedo.mean(axis=0)] if len(albedo) else None,
             "light_mean_radiance": [float(v) for v in light[0] * _Y0],
             "why": "one light of unknown colour and strength: a_c x g and L_c / g render alike, so "
                    + ("the environment's mean colour is grey" if cfg.white == "light" else
                       "the seen texels' mean albedo is grey") + " and "
                    + ("their mean albedo" if cfg.scale == "mean_albedo" else "the environment's mean radiance")
                    + f" is {cfg.scale_value:g}"}
    return light, albedo, materials, gauge


def nearest_texels(positions: np.ndarray, count: int) -> np.ndarray | None:
    """(N, count) each texel's ``count`` nearest other texels on the surface (by position), or None (count 0)."""
    if count <= 0 or len(positions) <= count:
        return None
    from scipy.spatial import cKDTree

    return cKDTree(positions).query(positions, count + 1)[1][:, 1:]


def solve(radiance: np.ndarray, weight: np.ndarray, transfer: np.ndarray, cfg, fixed_light=None,
          positions: np.ndarray | None = None) -> EnvSolution:
    """The light (estimated, or ``fixed_light`` (9, 3)) and every texel's albedo, from seen texels' radiance
    (N, 3), weights (N,) (sample counts) and transfer vectors (N, 9); ``cfg``: optim/env_config.py;
    ``positions`` (N, 3): where the texels are, for the material edges (None: no texel is taken for an edge)."""
    radiance, weight, transfer = (np.asarray(x, np.float64) for x in (radiance, weight, transfer))
    if fixed_light is not None:
        light = np.asarray(fixed_light, np.float64)
        albedo = albedo_given_light(light, radiance, weight, transfer)
        return EnvSolution(light, albedo, np.zeros((0, 3)), -np.ones(len(radiance), int),
                           {"fixed": "the light was given (--env.light): no ambiguity to fix"}, [])
    trace, best = [], None
    ks = [cfg.materials] if cfg.materials > 0 else list(range(1, cfg.max_materials + 1))
    neighbours = None if positions is None else nearest_texels(np.asarray(positions, np.float64), cfg.edge_neighbours)
    for k in ks:
        found = _fit_materials(radiance, weight, transfer, neighbours, k, cfg, trace)
        if best is not None and (len(found[1]) <= len(best[1]) or found[3] > (1.0 - cfg.material_gain) * best[3]):
            break  # one more material was merged into another, or hardly helps: keep the fewer
        best = found
    light, mats, labels, _ = best
    if neighbours is not None and cfg.slope_consensus:
        interior = (labels[neighbours] == labels[:, None]).all(axis=1)
        light = slope_consensus(light, radiance, weight * interior, transfer, np.asarray(positions, np.float64),
                                labels)
        mats = materials_given_light(material_statistics(radiance, weight, transfer, labels, len(mats)), light)
    albedo = albedo_given_light(light, radiance, weight, transfer, mats[labels], cfg.albedo_prior)
    light, albedo, mats, gauge = fix_gauge(light, albedo, mats, cfg)
    gauge["materials"] = int(len(mats))
    return EnvSolution(light, albedo, mats, labels, gauge, trace)
