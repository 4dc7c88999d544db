"""Shared materials: texels of one material share what their photos saw (issue 17).

A per-texel Lafortune fit pins a narrow lobe down only where some photo caught its peak; a texel
whose highlight fell between the cameras guesses its lobe (or, after the lobe-support test, renders
none), and a new view that looks at that highlight shows it wrong. Real objects are made of few
materials (Lensch et al. 2003: clustered basis BRDFs), so such a texel should take the lobe its
material shows elsewhere. texstream builds this as a **prior** in the streaming fit:

1. **Uncertainty per texel** (:func:`texel_uncertainty`): from the data term's J^T J at the per-texel
   fit, the covariance sigma^2 (J^T J)^-1 over the texel's free columns, with sigma^2 the mean squared
   residual per channel sample of that fit. It gives the relative standard deviations of rho_s (worst
   channel) and n and the standard deviation of c_z (written as ``uncertainty.exr``). A texel's lobe is
   *constrained* when both relative deviations are below ``MaterialConfig.constrained_rel_std``.
2. **Materials** (:func:`find_materials`): k-means on the seen texels' log diffuse albedo. rho_d is
   pinned by every photo of a texel, lobe or not, so every texel gets a material, also one whose lobe
   no photo constrained. A material's lobe is the median of its constrained texels' lobes (rho_s and n
   in log space), its spread their robust standard deviation; a material whose constrained lobes are
   too few (``min_lobe_share``), or whose lobe the photos of most of its unconstrained texels contradict
   (``max_contradicted``, below), has none (white plaster).
3. **Prior** (:func:`material_prior`): 1/2 sum_k w_ik (p_ik - c_ik)^2 on each texel's lobe columns,
   centred on its material's lobe (``StreamProblem.set_material_prior``, in every pass). A constrained
   texel gets w_k = ``prior_samples`` sigma^2 / s_k^2 (s_k the material's spread): the Bayesian balance of
   its photos (J^T J / sigma^2) against the spread of its material, so it keeps a lobe of its own where
   the photos say so (materials vary across an object). An unconstrained texel *borrows*: its weights
   are ``borrow_weight`` times its own J^T J diagonal (or the constrained weight, the larger), so it takes
   its material's lobe instead of a guess, moved only a tenth of the way toward what its own photos weakly
   say (a narrow highlight the plane taps blurred below the constrained test still counts a little).
   Where the texel's photos contradict its material's lobe (:func:`contradiction_test`: they looked
   where its highlight would be and saw none), its centre is no lobe. The "shared" variant makes every texel borrow.
4. **Fit**: Levenberg-Marquardt from the per-texel parameters (borrowing texels start at their centre).

Why a prior rather than basis lobes fitted jointly (the issue's first option): the prior keeps every
solve per texel (LM's Cholesky per texel, no reduction over the texels of a material inside the loop),
lets constrained texels keep their own lobes (the synthetic ornament's materials vary by up to 25% in
n), and is one more term of the passes, like the view-dependent radiance's ridge prior.

The choice between the per-texel model and the materials (and their number K) is made on a
validation split of the fitted photos (stage.py ``fit_materials``), so the held-out photos stay unseen
by every decision. numpy only (no Warp here: the passes are the problem's).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from texstream.core.config import option
from texstream.core.errors import ConfigError

from texstream.render.layout import ModelLayout

MATERIAL_MODES = ("off", "auto", "on")
VARIANTS = ("mixed", "shared")


@dataclasses.dataclass
class MaterialConfig:
    """Shared materials (fit/models/materials.py): what is tried and how it is judged."""

    mode: str = option("auto", "shared materials for the Lafortune model: off (per-texel lobes only), auto (also fit "
                               "the materials and keep whichever predicts a validation split of the fitted photos "
                               "best: per-texel, mixed or shared, and the number of materials) or on (the best "
                               "materials model even where per-texel lobes validate better)", choices=MATERIAL_MODES)
    max_materials: int = option(3, "largest number of materials K tried (each K = 1..this is fitted and judged)",
                                min=1, max=16)
    variants: str = option("mixed", "which materials models are tried: mixed (constrained texels keep their own "
                                     "lobes, the others borrow their material's), shared (every texel takes its "
                                     "material's lobe) or both (comma-separated: mixed,shared)")
    validation_every: int = option(8, "every k-th fitted photo is held back as a validation photo for the choice "
                                      "(the fit's own held-out photos stay out of every decision); with fewer than "
                                      "2k fitted photos the period shortens to keep two validation photos (at least "
                                      "6 fitted photos: every n//2-th)", min=2)
    constrained_rel_std: float = option(0.1, "a texel's lobe is constrained by its photos when the relative standard "
                                             "deviations of its rho_s and n (sigma^2 (J^T J)^-1) are below this",
                                        min=0.0)
    min_lobe_share: float = option(0.005, "a material has a lobe when at least this share of its texels (and 3) "
                                          "have a constrained one; else its texels borrow no lobe", min=0.0, max=1.0)
    max_contradicted: float = option(0.5, "a material has no lobe when its lobe contradicts the photos (see "
                                          "contradiction) of more than this share of its unconstrained texels: the "
                                          "photos looked where its highlight would be and saw none (a matte material "
                                          "whose few constrained lobes are edge texels blending a glossy neighbour)",
                                     min=0.0, max=1.0)
    prior_samples: float = option(1.0, "strength of the pull of a constrained texel's lobe towards its material's, "
                                       "in samples' worth of squared residual per squared material spread (1: the "
                                       "Bayesian balance)", min=0.0)
    borrow_weight: float = option(10.0, "an unconstrained texel's pull towards its material's lobe, as a multiple of "
                                        "its own J^T J diagonal (10: its photos move it about a tenth of the way from "
                                        "the material's lobe to their own estimate; a texel they say nothing about "
                                        "takes the material's lobe, as the weight is at least a constrained texel's)",
                                  min=0.0)
    spread_floor: float = option(0.02, "smallest material spread of rho_s and n, relative (and of c_z, absolute): "
                                       "keeps the pull finite for materials of identical texels", min=1e-6)
    contradiction: float = option(0.5, "a texel borrows no lobe where its photos contradict its material's lobe: "
                                       "the error the lobe adds on the fitted photos over the lobe's own energy there "
                                       "is above this (1: nothing where the lobe predicts a highlight, -1: exactly "
                                       "the lobe) and the lobe would show above the fit's residual",
                                  min=-1.0, max=1.0)
    iterations: int = option(20, "Levenberg-Marquardt iterations of a materials fit (it starts from the per-texel "
                                 "fit)", min=1)
    choice_rel_tol: float = option(1e-4, "the choice's fits on the validation split stop when their objective falls "
                                         "by less than this, relative, over 2 iterations: each materials candidate "
                                         "(it is only scored; the one chosen is fitted again to every fitted photo "
                                         "by the fit's own rule) and the split's per-texel fit, the candidates' "
                                         "start and evidence (on the full ornament 65 of the choice's 95 passes by "
                                         "the fit's own rule). Where the per-texel model then scores within "
                                         "choice_refit_margin_db of the best, its fit is continued by the fit's own "
                                         "rule (fit.rel_tol every fit.sync_every iterations) and scored again. 0: "
                                         "every fit of the choice by the fit's own rule",
                                   min=0.0)
    choice_refit_margin_db: float = option(1.0, "choice_rel_tol: the split's per-texel fit is continued by the fit's "
                                                "own rule, and scored again, where its validation pooled PSNR is at "
                                                "most this below the best candidate's: a fit stopped early is another "
                                                "model than the per-texel fit it stands for (it validated 9.6 dB "
                                                "higher on a small ornament, 2.5 dB higher on the 440-photo one, but "
                                                "0.5 dB lower on the dense ornament: 49.40 dB on the CPU against "
                                                "49.91 dB by the fit's own rule on an H200, 2.6 dB below the "
                                                "materials chosen)",
                                           min=0.0, max=60.0)
    fit_from_validation: bool = option(True, "the choice runs before the fit of every fitted photo, and that fit "
                                             "starts from the validation split's per-texel fit (7/8 of the same "
                                             "photos: it then needs fewer iterations; texels no fitted photo of the "
                                             "split saw start from the fit's own guess); the choice is the same "
                                             "either way. Not with tiles or a resumed checkpoint")
    start_fit_rel_tol: float = option(1e-4, "fit_from_validation, a materials model chosen: the fit of every fitted "
                                            "photo is only the start of the materials' fit (which refits every "
                                            "parameter to every fitted photo by the fit's own rule), so it stops when "
                                            "its objective falls by less than this, relative, over 2 iterations (on "
                                            "the full ornament it starts from the split's fit and falls 2e-4 over its "
                                            "last 75 of 85 iterations under the fit's own rule). 0: the fit's own "
                                            "rule; per-texel chosen, or a fit resumed from its checkpoint (the choice "
                                            "then runs after it): the fit's own rule (that fit is the model)",
                                      min=0.0)

    def variant_list(self) -> tuple:
        out = tuple(v.strip() for v in str(self.variants).split(",") if v.strip())
        bad = [v for v in out if v not in VARIANTS]
        if not out or bad:
            raise ConfigError(f"materials variants {self.variants!r} unknown",
                              fix="use mixed, shared or mixed,shared")
        return out


def lobe_columns(layout: ModelLayout) -> np.ndarray:
    """(P,) bool: the free lobe columns (rho_s, c_z where fitted, n; not the frozen gauge)."""
    cols = np.zeros(layout.n_params, bool)
    for j in range(layout.n_lobes):
        o = layout.lobe_offset(j)
        cols[o:o + layout.lobe_stride] = True
    return cols & ~layout.frozen()


def residual_variance(stats: np.ndarray) -> float:
    """Mean squared radiance-space residual per channel sample from the passes' (N, 4) trace stats
    (samples, sum r^2, sum |r|, sum |y|)."""
    st = np.asarray(stats, np.float64).sum(axis=0)
    return float(st[1] / max(3.0 * st[0], 1.0))


def texel_uncertainty(jtj: np.ndarray, params: np.ndarray, layout: ModelLayout, sigma2: float) -> np.ndarray:
    """(N, 3) per texel: relative standard deviation of rho_s (worst channel and lobe), of n (worst lobe),
    and the standard deviation of c_z (0 where held), from the covariance sigma^2 (J^T J)^-1 over the
    texel's free columns, over the lobes the texel has: a lobe that is off (rho_s = 0 in every channel: at its
    bound, or dropped) renders nothing and is left out. inf where a column is not constrained at all (a zero
    J^T J diagonal: no photo sees the lobe, or the texel has no lobe on, which leaves n without effect).

    Why a lobe that is off is left out: a texel whose second lobe the fit put at zero has one lobe, which its
    photos may pin down; counted, the off lobe's infinite deviation made the texel unconstrained. Why a lobe
    that is on counts even when loose (rather than judging a texel by its best-constrained lobe): on a two-lobe
    sphere (a broad sheen and a sharp highlight, 128 photos) texels then kept loose second lobes of their own
    and the two-lobe model fell from 49.3 to 29.5 dB held out; counted, they borrow their material's lobes.

    The inverse is taken in the Jacobi-scaled basis with eigenvalues floored at 1e-12 of the largest,
    so a nearly singular block (a lobe seen in one photo) gives a large, finite deviation.
    """
    lay = layout
    p = np.asarray(params, np.float64)
    n = p.shape[0]
    if lay.n_lobes == 0:
        return np.zeros((n, 3))
    free = np.flatnonzero(~lay.frozen())
    h = np.asarray(jtj, np.float64)[:, free[:, None], free]
    d = np.einsum("nii->ni", h)
    dead = ~(d > 1e-300)
    s = np.where(dead, 1.0, np.sqrt(np.where(dead, 1.0, d)))
    hs = h / (s[:, :, None] * s[:, None, :])
    if dead.any():  # a column no sample constrains: the identity's row and column (its variance is inf below)
        hs = np.where(dead[:, :, None] | dead[:, None, :], np.eye(len(free))[None], hs)
    var_s = scaled_inverse_diagonal(hs)
    var = sigma2 * var_s / (s * s)
    var[dead] = np.inf
    full = np.full((n, lay.n_params), 0.0)
    full[:, free] = var
    per_lobe = np.empty((lay.n_lobes, n, 3))
    for j in range(lay.n_lobes):
        o = lay.lobe_offset(j)
        rho = p[:, o:o + 3]
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            rel_rho = np.where(rho > 0, np.sqrt(full[:, o:o + 3]) / np.maximum(rho, 1e-300), np.inf).max(axis=1)
            nn = p[:, o + lay.lobe_stride - 1]
            rel_n = np.sqrt(full[:, o + lay.lobe_stride - 1]) / np.maximum(nn, 1e-300)
        rel_n = np.where(np.isfinite(rel_rho), rel_n, np.inf)  # no lobe: n has no meaning
        per_lobe[j] = np.stack([rel_rho, rel_n, np.sqrt(full[:, o + lay.lobe_stride - 2])], axis=1)
    per_lobe = np.nan_to_num(per_lobe, nan=np.inf, posinf=np.inf)
    on = np.stack([np.any(p[:, lay.lobe_offset(j):lay.lobe_offset(j) + 3] != 0, axis=1) for j in range(lay.n_lobes)])
    out = np.where(on[:, :, None], per_lobe, -np.inf).max(axis=0)
    no_lobe = ~on.any(axis=0)
    out[no_lobe] = per_lobe[:, no_lobe].max(axis=0)  # no lobe on: inf, as for a texel without any
    return out


UNCERTAINTY_CHUNK = 4096
"""texels per Cholesky batch of :func:`scaled_inverse_diagonal` (a batch with a block that is not positive
definite is taken by eigenvalues)"""


def scaled_inverse_diagonal(hs: np.ndarray) -> np.ndarray:
    """(N, m) diagonals of the inverses of (N, m, m) symmetric blocks of unit diagonal, eigenvalues floored at
    1e-12 of the largest. Blocks whose Cholesky factor shows the floor cannot act (their smallest eigenvalue is
    at least 1 / ||L^-1||_F^2, their largest at most m, the trace) are inverted through it, the others through
    their eigenvalues: the same diagonals to rounding (3e-13 relative at most on 95,136 random blocks of 8 x 8,
    the full ornament's count), in a quarter of the time or less (0.39 s against 1.4-3.6 s by eigenvalues alone
    on the 2-core dev box)."""
    n, m = hs.shape[:2]
    out = np.empty((n, m))
    floored = np.ones(n, bool)
    for b in range(0, n, UNCERTAINTY_CHUNK):
        block = hs[b:b + UNCERTAINTY_CHUNK]
        try:
            chol = np.linalg.cholesky(block)
        except np.linalg.LinAlgError:
            continue  # a block not positive definite: by eigenvalues
        inv = np.zeros_like(chol)  # L^-1, row by row (forward substitution for every block at once)
        for i in range(m):
            inv[:, i, i] = 1.0
            inv[:, i] -= np.einsum("nk,nkj->nj", chol[:, i, :i], inv[:, :i])
            inv[:, i] /= chol[:, i, i, None]
        diag = (inv * inv).sum(axis=1)  # diag of L^-T L^-1
        out[b:b + len(block)] = diag
        frob = diag.sum(axis=1)
        floored[b:b + len(block)] = ~(frob * 1e-12 * m <= 1.0)
    if floored.any():
        w, v = np.linalg.eigh(hs[floored])
        w = np.maximum(w, 1e-12 * np.maximum(w[:, -1:], 1e-300))
        out[floored] = np.einsum("nij,nj,nij->ni", v, 1.0 / w, v)
    return out


def distinct_rows(x: np.ndarray, k: int) -> int:
    """min(k, the number of distinct rows of ``x``), found row by row (k passes, not a sort of every row: for the
    full ornament's 95,136 texels the sort was two thirds of a k-means)."""
    found = []
    rest = np.ones(len(x), bool)
    while len(found) < k and rest.any():
        i = int(np.argmax(rest))
        found.append(x[i])
        rest &= np.any(x != x[i], axis=1)
        rest[i] = False  # a row with NaN differs even from itself (as in np.unique)
    return len(found)


def kmeans(x: np.ndarray, k: int, seed: int = 0, iterations: int = 100) -> tuple[np.ndarray, np.ndarray]:
    """(labels (M,), centres (k', D)) of Lloyd's k-means with k-means++ seeding from a fixed seed
    (deterministic); k' <= k when there are fewer distinct points. Empty clusters are dropped."""
    x = np.asarray(x, np.float64)
    rng = np.random.default_rng(seed)
    k = distinct_rows(x, k)
    if k <= 0:
        return np.zeros(len(x), int), np.zeros((0, x.shape[1]))
    centres = [x[rng.integers(len(x))]]
    for _ in range(1, k):
        d2 = ((x[:, None, :] - np.asarray(centres)[None]) ** 2).sum(-1).min(axis=1)
        if d2.sum() <= 0:
            break
        centres.append(x[rng.choice(len(x), p=d2 / d2.sum())])
    c = np.asarray(centres)
    labels = np.zeros(len(x), int)
    for _ in range(iterations):
        labels_new = ((x[:, None, :] - c[None]) ** 2).sum(-1).argmin(axis=1)
        keep = np.unique(labels_new)
        c = np.stack([x[labels_new == j].mean(axis=0) for j in keep])
        labels_new = np.searchsorted(keep, labels_new)
        if np.array_equal(labels_new, labels) and len(keep) == len(c):
            labels = labels_new
            break
        labels = labels_new
    # a fixed order: by the first feature (the log red albedo), so K materials are numbered alike run to run
    order = np.lexsort(c.T[::-1])
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return rank[labels], c[order]


def albedo_features(params: np.ndarray) -> np.ndarray:
    """(N, 3) log(rho_d + 1e-3): the clustering space (scale-free; 1e-3 keeps black finite)."""
    return np.log(np.maximum(np.asarray(params, np.float64)[:, 0:3], 0.0) + 1e-3)


@dataclasses.dataclass
class Materials:
    """K materials found in a per-texel fit (:func:`find_materials`)."""

    labels: np.ndarray
    """(N,) material per texel (-1: unseen)"""
    features: np.ndarray
    """(K, 3) centre of each material in :func:`albedo_features` space"""
    lobes: np.ndarray
    """(K, P) each material's lobe in the layout's columns (rho_d columns: the material's mean rho_d)"""
    spread: np.ndarray
    """(K, P) robust standard deviation of each lobe column over the material's constrained texels, floored"""
    has_lobe: np.ndarray
    """(K,) bool"""
    texels: np.ndarray
    """(K,) texels per material"""
    constrained: np.ndarray
    """(K,) of those, texels whose lobe is constrained"""
    contradicted_share: np.ndarray | None = None
    """(K,) share of the unconstrained texels whose photos contradict the material's lobe (:func:`reject_contradicted_lobes`)"""

    @property
    def k(self) -> int:
        return int(len(self.features))

    def to_json(self, layout: ModelLayout) -> list:
        out = []
        for m in range(self.k):
            row = {"texels": int(self.texels[m]), "constrained_lobes": int(self.constrained[m]),
                   "rho_d": [float(x) for x in self.lobes[m, 0:3]], "has_lobe": bool(self.has_lobe[m])}
            if self.contradicted_share is not None:
                row["contradicted_share"] = float(self.contradicted_share[m])
            if layout.n_lobes and self.has_lobe[m]:
                o = layout.lobe_offset(0)
                row["rho_s"] = [float(x) for x in self.lobes[m, o:o + 3]]
                row["c_z"] = float(self.lobes[m, o + layout.lobe_stride - 2])
                row["n"] = float(self.lobes[m, o + layout.lobe_stride - 1])
                row["n_spread"] = float(self.spread[m, o + layout.lobe_stride - 1])
            out.append(row)
        return out


def find_materials(params: np.ndarray, seen: np.ndarray, constrained: np.ndarray, layout: ModelLayout, k: int,
                   min_lobe_share: float = 0.05, spread_floor: float = 0.02, seed: int = 0) -> Materials:
    """Cluster the seen texels into ``k`` materials by diffuse albedo and give each the median lobe of its
    constrained texels (module doc, step 2)."""
    p = np.asarray(params, np.float64)
    seen = np.asarray(seen, bool)
    constrained = np.asarray(constrained, bool) & seen
    n_par = layout.n_params
    labels = -np.ones(len(p), int)
    if not seen.any():
        raise ConfigError("no texel is seen: nothing to cluster into materials", fix="check the capture and mesh")
    lab, feats = kmeans(albedo_features(p[seen]), k, seed=seed)
    labels[seen] = lab
    kk = len(feats)
    lobes = np.zeros((kk, n_par))
    spread = np.ones((kk, n_par))
    has = np.zeros(kk, bool)
    texels = np.bincount(lab, minlength=kk)
    ncon = np.zeros(kk, int)
    defaults = layout.defaults()
    for m in range(kk):
        sel = labels == m
        lobes[m] = defaults
        lobes[m, 0:3] = p[sel, 0:3].mean(axis=0)
        con = sel & constrained
        ncon[m] = int(con.sum())
        has[m] = layout.n_lobes > 0 and ncon[m] >= max(3, min_lobe_share * texels[m])
        for j in range(layout.n_lobes):
            o = layout.lobe_offset(j)
            nc = o + layout.lobe_stride - 1
            cz = nc - 1
            if not has[m]:
                lobes[m, o:o + 3] = 0.0
                spread[m, o:o + 3] = 0.01  # BRDF units: a faint highlight
                spread[m, cz] = 0.1
                spread[m, nc] = defaults[nc]
                continue
            q = p[con]
            for col in list(range(o, o + 3)) + [nc]:
                lg = np.log(np.maximum(q[:, col], 1e-12))
                med = np.median(lg)
                lobes[m, col] = float(np.exp(med))
                rel = 1.4826 * np.median(np.abs(lg - med))
                spread[m, col] = lobes[m, col] * max(rel, spread_floor)
            lobes[m, cz] = float(np.median(q[:, cz]))
            spread[m, cz] = max(1.4826 * float(np.median(np.abs(q[:, cz] - lobes[m, cz]))), spread_floor)
            # the gauge column keeps its held value
            for col in range(o, o + layout.lobe_stride):
                if layout.frozen()[col]:
                    lobes[m, col] = defaults[col]
    return Materials(labels, feats, lobes, spread, has, texels, ncon)


def assign_materials(params: np.ndarray, seen: np.ndarray, materials: Materials) -> np.ndarray:
    """(N,) nearest material of every seen texel in albedo space (-1 unseen): the labels of
    :func:`find_materials` for the texels it clustered, for a new fit of the same texels too."""
    labels = -np.ones(len(params), int)
    seen = np.asarray(seen, bool)
    f = albedo_features(np.asarray(params)[seen])
    labels[seen] = ((f[:, None, :] - materials.features[None]) ** 2).sum(-1).argmin(axis=1)
    return labels


@dataclasses.dataclass
class MaterialPrior:
    """The prior of one materials model (:func:`material_prior`)."""

    centre: np.ndarray
    """(N, P) the centre of each texel's prior (its own parameters where the weight is 0)"""
    weights: np.ndarray
    """(N, P) its weights (objective units per squared parameter unit)"""
    start: np.ndarray
    """(N, P) where the fit starts: the per-texel parameters, borrowing texels' lobes at their centre"""
    borrow: np.ndarray
    """(N,) bool: texels that take their material's lobe"""
    no_lobe: np.ndarray
    """(N,) bool: texels whose centre is no lobe (their material has none, or their photos contradict it)"""


def material_prior(params: np.ndarray, jtj: np.ndarray, seen: np.ndarray, constrained: np.ndarray,
                   labels: np.ndarray, materials: Materials, layout: ModelLayout, sigma2: float,
                   contradicted: np.ndarray | None, cfg: MaterialConfig, variant: str = "mixed") -> MaterialPrior:
    """The per-texel centres and weights of the prior (module doc, step 3). ``contradicted``: (N,) texels
    whose photos contradict their material's lobe (:func:`contradiction_test`); ``variant`` "mixed" or "shared" (every seen texel borrows)."""
    if variant not in VARIANTS:
        raise ConfigError(f"materials variant {variant!r} unknown", fix="use mixed or shared")
    p = np.asarray(params, np.float64)
    n, n_par = p.shape
    seen = np.asarray(seen, bool)
    lab = np.where(labels >= 0, labels, 0)
    cols = lobe_columns(layout)
    centre = p.copy()
    centre[:, cols] = materials.lobes[lab][:, cols]
    spread = materials.spread[lab]
    no_lobe = seen & ~materials.has_lobe[lab]
    if contradicted is not None:
        no_lobe |= seen & np.asarray(contradicted, bool) & ~np.asarray(constrained, bool)
    for j in range(layout.n_lobes):
        o = layout.lobe_offset(j)
        centre[no_lobe, o:o + 3] = 0.0
    borrow = seen & (~np.asarray(constrained, bool) if variant == "mixed" else True)
    base = np.zeros((n, n_par))
    base[:, cols] = cfg.prior_samples * sigma2 / np.maximum(spread[:, cols], 1e-300) ** 2
    diag = np.einsum("nii->ni", np.asarray(jtj, np.float64))
    strong = np.maximum(base, cfg.borrow_weight * diag)
    weights = np.where(borrow[:, None], strong, base)
    weights[:, ~cols] = 0.0
    weights[~seen] = 0.0
    start = p.copy()
    start[borrow[:, None] & cols[None]] = centre[borrow[:, None] & cols[None]]
    # a no-lobe texel's n and c_z have no effect on its model: keep them where they are, unpulled
    for j in range(layout.n_lobes):
        o = layout.lobe_offset(j)
        shape_cols = slice(o + 3, o + layout.lobe_stride)
        weights[no_lobe, shape_cols] = 0.0
        centre[no_lobe, shape_cols] = start[no_lobe, shape_cols]
    return MaterialPrior(centre, weights, start, borrow, no_lobe)


def contradiction_test(f_bare: np.ndarray, f_lobe: np.ndarray, f_doubled: np.ndarray, samples: np.ndarray,
                       sigma2: float, level: float) -> np.ndarray:
    """(N,) texels whose photos contradict a lobe put on them, from three per-texel objectives on the fitted
    photos: without the lobe (a = residuals), with it (l = its radiance) and with it doubled. The model is
    linear in rho_s, so f_lobe - f_bare = sum a l + E and f_doubled - 2 f_lobe + f_bare = 2 E exactly, with
    E = 1/2 sum l^2 the lobe's own energy on the texel's samples. The score (f_lobe - f_bare) / E = 1 + sum a l / E
    is 1 where the photos show nothing where the lobe predicts light and -1 where they show exactly the
    lobe; a texel is contradicted when it exceeds ``level`` and E exceeds the fit's residual energy there
    (3 sigma^2 per photo; below it, the photos did not look where the lobe shines and say nothing)."""
    energy = 0.5 * (np.asarray(f_doubled, np.float64) - 2.0 * np.asarray(f_lobe, np.float64) + np.asarray(f_bare, np.float64))
    visible = energy > 3.0 * np.asarray(samples, np.float64) * sigma2
    with np.errstate(divide="ignore", invalid="ignore"):
        score = (np.asarray(f_lobe, np.float64) - f_bare) / energy
    return visible & (score > level)


def reject_contradicted_lobes(materials: Materials, labels: np.ndarray, seen: np.ndarray, constrained: np.ndarray,
                              contradicted: np.ndarray, max_share: float) -> np.ndarray:
    """Drop the lobe of every material whose lobe the photos of more than ``max_share`` of its seen,
    unconstrained texels contradict (in place on ``materials.has_lobe``); returns each material's share."""
    share = np.zeros(materials.k)
    free = np.asarray(seen, bool) & ~np.asarray(constrained, bool)
    for m in range(materials.k):
        sel = free & (labels == m)
        if materials.has_lobe[m] and sel.any():
            share[m] = float(np.mean(np.asarray(contradicted, bool)[sel]))
            if share[m] > max_share:
                materials.has_lobe[m] = False
    return share


def material_lobes_on(params: np.ndarray, labels: np.ndarray, materials: Materials, layout: ModelLayout) -> np.ndarray:
    """(N, P) the texels' parameters with each seen texel's lobe replaced by its material's (for the
    contradiction test; texels of a material without a lobe keep theirs)."""
    p = np.asarray(params, np.float64).copy()
    lab = np.where(labels >= 0, labels, 0)
    cols = lobe_columns(layout)
    take = (labels >= 0) & materials.has_lobe[lab]
    p[np.ix_(take, cols)] = materials.lobes[lab[take]][:, cols]
    return p
