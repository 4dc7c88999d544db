"""The conventional two-step approach (seed Table 4.1 / Alg. 4) with scipy.optimize.least_squares.

Step 1 resamples every training photo once into per-texel sample arrays (common.resample:
texstream's own distribution step, bilinear photo filter). Step 2 fits texstream's Lafortune
model (common.lafortune_numpy: same layout, lobe shape, box bounds and start) to each texel's
samples, radiance-space residuals ``w * m(p; u, v) - y``, with an analytic Jacobian.

Two ways a capable scipy user would organise step 2 (``mode``):

* ``blocks``: texels in batches of ``batch``, each batch one ``least_squares(method="trf")`` problem
  whose Jacobian is a sparse block-diagonal CSR matrix (one dense block per texel), solved with
  ``tr_solver="lsmr"`` and ``x_scale="jac"``: no Python loop over texels, but the texels of one
  batch share one trust region and every step is an iterative sparse solve.
* ``per_texel``: one ``least_squares(method="lm")`` (MINPACK) call per texel, ``x_scale="jac"``: the
  seed's Alg. 4 as written, independent damping per texel, a Python call per texel.

texstream's bounds and energy bound (rho_s <= (n + 2) / 2 pi) are not all boxes, so both modes
evaluate the model at the projected parameters (common.projected_model: clip, then cap; the
Jacobian through the projection), as the torch peer does; without the energy bound the held-out
PSNR of this capture collapses (lobes fitted to one highlight sample render far too bright).

The time axis starts before step 1 (resampling and the initial guess count; the kernels are
compiled by a warm-up call first). ``per_texel``: MINPACK cannot hand back its iterates, so each check
of the stopping rule (common.early_stop) is a run of its own with ``max_nfev`` = the check's budget
(MINPACK is deterministic: the run with budget k stops where an unlimited one is after k evaluations),
timed whole; the checks run in order and end where the rule stops. ``blocks``: a snapshot after each
batch (texels not fitted yet hold their start values) and, within one-batch runs, after every trf
iteration.
"""

from __future__ import annotations

import numpy as np

from common import (HeldOut, Recorder, build_problem, check_supported, early_stop, fit_config, free_columns, project,
                    projected_model, resample, sample_psnr, schedule)


class BatchProblem:
    """Residuals and sparse Jacobian of one batch of texels over their free parameters."""

    def __init__(self, samples, texels: np.ndarray, params: np.ndarray, layout, lobe_albedo_max: float):
        import scipy.sparse as sp

        self.layout = layout
        self.albedo_max = lobe_albedo_max
        self.texels = texels
        self.free = free_columns(layout)
        F = self.free.size
        rows = np.concatenate([np.arange(samples.start[t], samples.start[t + 1]) for t in texels]) if texels.size else np.zeros(0, int)
        self.rows = rows
        local = np.repeat(np.arange(texels.size), samples.counts[texels])  # batch-local texel of each sample
        self.local = local
        self.u = samples.u[rows].astype(np.float64)
        self.v = samples.v[rows].astype(np.float64)
        self.w = samples.w[rows].astype(np.float64)
        self.y = samples.y[rows].astype(np.float64)
        self.base = params[texels].copy()  # frozen columns keep these
        S = rows.size
        # CSR pattern: residual row 3 s + c holds the F free columns of its texel's block
        self.indptr = np.arange(0, 3 * S * F + 1, F)
        self.indices = (local[:, None, None] * F + np.arange(F)[None, None, :]).repeat(3, axis=1).reshape(-1)
        self.shape = (3 * S, texels.size * F)
        self.sp = sp

    def full(self, x: np.ndarray) -> np.ndarray:
        p = self.base.copy()
        p[:, self.free] = x.reshape(-1, self.free.size)
        return p

    def residual(self, x: np.ndarray) -> np.ndarray:
        m = projected_model(self.full(x)[self.local], self.layout, self.u, self.v, self.albedo_max)
        return (self.w * m - self.y).reshape(-1)

    def jacobian(self, x: np.ndarray):
        _, J = projected_model(self.full(x)[self.local], self.layout, self.u, self.v, self.albedo_max, jac=True)
        data = (self.w[:, :, None] * J[:, :, self.free]).reshape(-1)
        return self.sp.csr_matrix((data, self.indices, self.indptr), shape=self.shape)


class TexelProblem:
    """Residuals and dense Jacobian of one texel (``per_texel`` mode)."""

    def __init__(self, samples, t: int, base: np.ndarray, layout, free: np.ndarray, lobe_albedo_max: float):
        r = slice(samples.start[t], samples.start[t + 1])
        self.u, self.v = samples.u[r].astype(np.float64), samples.v[r].astype(np.float64)
        self.w, self.y = samples.w[r].astype(np.float64), samples.y[r].astype(np.float64)
        self.base, self.layout, self.free, self.albedo_max = base, layout, free, lobe_albedo_max

    def full(self, x: np.ndarray) -> np.ndarray:
        p = self.base.copy()
        p[self.free] = x
        return np.broadcast_to(p, (self.u.shape[0], p.size))

    def residual(self, x: np.ndarray) -> np.ndarray:
        return (self.w * projected_model(self.full(x), self.layout, self.u, self.v, self.albedo_max) - self.y).reshape(-1)

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        _, J = projected_model(self.full(x), self.layout, self.u, self.v, self.albedo_max, jac=True)
        return (self.w[:, :, None] * J[:, :, self.free]).reshape(-1, self.free.size)


def fit_per_texel(samples, params: np.ndarray, seen: np.ndarray, lay, albedo_max: float, max_nfev: int) -> dict:
    """One MINPACK LM call per seen texel from ``params`` (updated in place); evaluation counts."""
    from scipy.optimize import least_squares

    free = free_columns(lay)
    stats = {"nfev": 0, "njev": 0}
    for t in seen:
        tp = TexelProblem(samples, int(t), params[t].copy(), lay, free, albedo_max)
        res = least_squares(tp.residual, params[t, free], jac=tp.jacobian, method="lm", x_scale="jac",
                            max_nfev=max_nfev)
        params[t] = project(tp.full(res.x)[0][None], lay, albedo_max)[0]
        stats["nfev"] += int(res.nfev)
        stats["njev"] += int(res.njev or 0)
    return stats


def run_checks(prob, cfg, scorer, max_nfev: int) -> tuple[list, dict, object]:
    """``per_texel``: one whole timed run (resampling, initial guess, fit) per check of max_nfev, scored on the
    validation and held-out views between runs (not timed); stops where the rule does."""
    from texstream.fit.optim.fitter import initial_guess

    lay = prob.layout
    trace, stats = [], {}
    # MINPACK's evaluations per check: every one to 6, then 4 per doubling (each check is a whole run)
    for budget in sorted(schedule(max_nfev, dense=6, per_doubling=4)):
        rec = Recorder()
        rec.start()
        samples = resample(prob)
        p0, counts = initial_guess(prob, cfg)
        params = project(p0, lay, cfg.lobe_albedo_max)
        if budget > 0:
            stats = fit_per_texel(samples, params, np.flatnonzero(counts > 0), lay, cfg.lobe_albedo_max, budget)
        rec.snap(budget, params)
        trace += rec.trace(scorer.score, sample_psnr(samples, lay, cfg.lobe_albedo_max))
        if early_stop(trace)["by"] == "patience":
            break
    return trace, stats, samples


def run(data, device: str, mode: str = "per_texel", batch: int = 0, max_nfev: int = 100) -> dict:
    """Fit every texel: ``mode`` "per_texel" (MINPACK LM per texel) or "blocks" (``batch`` texels per
    sparse trf problem, 0 = all in one)."""
    from scipy.optimize import least_squares
    from texstream.fit.optim.fitter import initial_guess

    cfg = fit_config(data, "bilinear")
    prob = build_problem(data, cfg, device)
    lay = prob.layout
    check_supported(lay)
    resample(prob)  # compile the sampling kernels (not timed)
    initial_guess(prob, cfg)
    scorer = HeldOut(data, prob, lay, device)
    if mode == "per_texel":
        trace, stats, samples = run_checks(prob, cfg, scorer, max_nfev)
        return {"trace": trace, "texels": prob.n, "samples": int(samples.y.shape[0]), "mode": mode, **stats,
                "val_check_s": scorer.check_seconds(),
                "settings": f"least_squares lm (MINPACK) per texel, x_scale=jac, max_nfev up to {max_nfev} (a run "
                            "per check), projected model"}
    if mode != "blocks":
        raise ValueError(f"mode {mode!r}: use per_texel or blocks")
    rec = Recorder()
    rec.start()
    samples = resample(prob)
    p0, counts = initial_guess(prob, cfg)
    params = project(p0, lay, cfg.lobe_albedo_max)
    rec.snap(0, params)
    free = free_columns(lay)
    lo, hi = lay.lower()[free], lay.upper()[free]
    seen = np.flatnonzero(counts > 0)
    stats = {"nfev": 0, "njev": 0, "iterations": 0}
    size = seen.size if batch <= 0 else batch
    batches = [seen[b:b + size] for b in range(0, seen.size, size)]
    for bi, texels in enumerate(batches):
        bp = BatchProblem(samples, texels, params, lay, cfg.lobe_albedo_max)
        x0 = np.clip(params[texels][:, free], lo, hi).reshape(-1)

        def snap_iteration(x, bp=bp, texels=texels):
            stats["iterations"] += 1
            if len(batches) == 1:
                p = params.copy()
                p[texels] = project(bp.full(x), lay, cfg.lobe_albedo_max)
                rec.snap(stats["iterations"], p)

        res = least_squares(bp.residual, x0, jac=bp.jacobian,
                            bounds=(np.tile(lo, texels.size), np.tile(hi, texels.size)), method="trf",
                            tr_solver="lsmr", x_scale="jac", max_nfev=max_nfev, callback=snap_iteration)
        params[texels] = project(bp.full(res.x), lay, cfg.lobe_albedo_max)
        stats["nfev"] += int(res.nfev)
        stats["njev"] += int(res.njev or 0)
        if len(batches) > 1:
            rec.snap(bi + 1, params)
    settings = (f"least_squares trf, lsmr, x_scale=jac, sparse block-diagonal Jacobian, {len(batches)} "
                f"batch(es) of {size} texels, max_nfev {max_nfev}, box bounds, projected model")
    return {"trace": rec.trace(scorer.score, sample_psnr(samples, lay, cfg.lobe_albedo_max)), "texels": prob.n,
            "samples": int(samples.y.shape[0]), "mode": mode, "batches": len(batches), "batch": size, **stats,
            "val_check_s": scorer.check_seconds(), "settings": settings}
