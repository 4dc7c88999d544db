"""The specular lobes of a per-texel fit: the lobe shape report, lobes no photo supports dropped, the traced
polish, and the shared materials' choice and fit (texels whose highlight no photo caught borrow their
material's lobe); seams averaged within bounds."""

from __future__ import annotations

import concurrent.futures
import dataclasses
import queue
import time
from typing import Callable

import numpy as np


from texstream.fit.optim.fitter import FitConfig, FitResult, light_view_angles, run_fit
from texstream.fit.models.materials import (MaterialConfig, contradiction_test, find_materials,
                                            material_lobes_on, material_prior, reject_contradicted_lobes,
                                            residual_variance, texel_uncertainty)
from texstream.render.layout import ModelLayout

from texstream.fit.common.inputs import read_photos, validation_period, FitInputs
from texstream.fit.common.highlights import highlight_masks
from texstream.fit.common.setup import (data_jtj, fill_unlit_reflectance, fill_unseen_texels, has_unlit_photos,
                                        params_to_grid, per_texel_objective, unseen_sources)
from texstream.fit.common.view_scores import ViewScores
from texstream.fit.multi.cpu_threads import MAX_AUTO_THREADS, cpu_threads, threaded_config, usable_cpus
from texstream.fit.multi.tiles import run_tiled_fit, tiled
from texstream.fit.stream.problem import PhotoFrame, StreamProblem
from texstream.geometry.seams import average_across_seams, seam_gaps


def lobe_shape_report(cfg: FitConfig, layout, frames, positions: np.ndarray) -> dict:
    """What model.json records of the lobe-shape choice (render/layout.py "Lobe shape")."""
    if layout.n_lobes == 0:
        return {"requested": cfg.lobe_shape, "fitted": None, "light_view_angle_deg": None}  # no lobe to shape
    angles = light_view_angles([PhotoFrame.from_capture_frame(f) for f in frames], positions.mean(axis=0))
    return {"requested": cfg.lobe_shape, "fitted": layout.lobe_shape,
            "light_view_angle_deg": [float(angles.min()), float(angles.max())] if angles.size else None}


def drop_unsupported_lobes(problem, result: FitResult, fraction: float,
                           evidence: "TexelEvidence | None" = None) -> tuple[np.ndarray, np.ndarray]:
    """(params, dropped): the fitted parameters with rho_s = 0 on every seen texel whose lobes lower its
    objective by less than ``fraction`` of the objective without them, and the (N,) mask of those texels.
    Such a lobe explains nothing the photos show; a narrow one whose peak fell between the cameras would
    still light up a new view at full height. ``evidence``: that of ``result`` on ``problem``, whose objective
    without the lobes is then not evaluated again."""
    lay = result.layout
    dropped = np.zeros(problem.n, bool)
    if lay.n_lobes == 0 or fraction <= 0:
        return result.params, dropped
    bare = scale_lobes(result.params, lay, 0.0)
    with_lobes = per_texel_objective(problem, result.params)
    without = (evidence.bare_objective(problem) if evidence is not None and evidence.params is result.params
               else per_texel_objective(problem, bare))
    dropped = (result.samples > 0) & (without - with_lobes <= fraction * np.maximum(without, 1e-30))
    params = np.where(dropped[:, None], bare, result.params)
    if lay.n_lobes > 1:
        # each further lobe on its own: kept only where the texel's error without it is higher by the fraction
        for j in range(1, lay.n_lobes):
            one_less = scale_lobes(params, lay, 0.0, only=j)
            f_with, f_without = per_texel_objective(problem, params), per_texel_objective(problem, one_less)
            weak = ~dropped & (result.samples > 0) & (f_without - f_with <= fraction * np.maximum(f_without, 1e-30))
            params = np.where(weak[:, None], one_less, params)
    return params, dropped


def scale_lobes(params: np.ndarray, layout: ModelLayout, factor: float, only: int | None = None) -> np.ndarray:
    """A copy of (N, P) ``params`` with every lobe's rho_s (or lobe ``only``'s) times ``factor``: 0 takes the
    lobes away, 2 doubles them (the model is linear in rho_s)."""
    out = params.copy()
    for j in range(layout.n_lobes) if only is None else (only,):
        o = layout.lobe_offset(j)
        out[:, o:o + 3] = 0.0 if factor == 0 else out[:, o:o + 3] * factor
    return out


def lobes_in_use(params: np.ndarray, layout: ModelLayout, seen: np.ndarray) -> list[int]:
    """Per lobe, the seen texels whose lobe is on (rho_s not all 0): what model.json records."""
    return [int((seen & np.any(params[:, layout.lobe_offset(j):layout.lobe_offset(j) + 3] != 0, axis=1)).sum())
            for j in range(layout.n_lobes)]


@dataclasses.dataclass
class TexelEvidence:
    """What a per-texel fit's photos say about each texel's lobe (fit/models/materials.py steps 1-2)."""

    params: np.ndarray
    samples: np.ndarray
    jtj: np.ndarray
    sigma2: float
    uncertainty: np.ndarray
    """(N, 3) relative std of rho_s, of n, std of c_z (materials.texel_uncertainty)"""
    constrained: np.ndarray
    bare: np.ndarray | None = None
    """(N,) each texel's objective without its lobes (:meth:`bare_objective`; None: not evaluated yet)"""

    def bare_objective(self, problem) -> np.ndarray:
        """Each texel's objective on ``problem`` (the problem these parameters were fitted on, or one over the same
        photos: the same arithmetic) with its lobes taken away: evaluated once, for the lobe support test and every
        materials candidate's contradiction test."""
        if self.bare is None:
            self.bare = per_texel_objective(problem, scale_lobes(self.params, problem.layout, 0.0))
        return self.bare


def texel_evidence(problem, result: FitResult, mcfg: MaterialConfig) -> TexelEvidence:
    """J^T J, residual variance and uncertainty of a per-texel fit's lobes, and which are constrained."""
    jtj, stats = data_jtj(problem, result.params)
    sigma2 = residual_variance(stats[result.samples > 0])
    unc = texel_uncertainty(jtj, result.params, result.layout, sigma2)
    constrained = (result.samples > 0) & (unc[:, 0] < mcfg.constrained_rel_std) & (unc[:, 1] < mcfg.constrained_rel_std)
    return TexelEvidence(result.params, result.samples, jtj, sigma2, unc, constrained)


def confirm_at_material_lobes(traced, evidence: TexelEvidence, plane: TexelEvidence, k: int,
                              mcfg: MaterialConfig) -> tuple[TexelEvidence, int]:
    """``evidence`` (a fit's on traced taps) with its constrained texels kept only where the photos also
    constrain the lobe of the texel's material: J^T J on ``traced`` taps linearised at the materials' lobes
    (found from the ``plane``-tap evidence, as the default path finds them), not at the texel's own lobe.
    A texel whose own wrong lobe is steep where its photos looked (the flank of a highlight no photo showed
    at its peak) passes the test at its own lobe; at the material's lobe those samples see almost no lobe
    and it fails. A texel that saw its (even sub-pixel) highlight passes both. Returns (the evidence, how
    many constrained texels the second test took away)."""
    lay = traced.layout
    seen = plane.samples > 0
    mats = find_materials(plane.params, seen, plane.constrained, lay, k, mcfg.min_lobe_share, mcfg.spread_floor)
    at = material_lobes_on(evidence.params, mats.labels, mats, lay)
    jtj, _ = data_jtj(traced, at)
    unc = texel_uncertainty(jtj, at, lay, evidence.sigma2)
    keep = (unc[:, 0] < mcfg.constrained_rel_std) & (unc[:, 1] < mcfg.constrained_rel_std)
    constrained = evidence.constrained & keep
    return dataclasses.replace(evidence, constrained=constrained), int((evidence.constrained & ~keep).sum())


def traced_polish_applies(problem, cfg) -> bool:
    """Whether the fit ends with :func:`traced_polish`: a model with specular lobes, fitted with filtered plane
    taps on a mesh (an atlas fit, not a single view), untiled."""
    s = problem.cfg
    return (cfg.traced_polish > 0 and problem.layout.n_lobes > 0 and s.photo_sampling == "filtered"
            and s.tap_geometry == "plane" and problem.photos.mesh_normals is not None
            and problem.photos.mesh_uvs is not None and not tiled(cfg.fit))


def traced_problem(problem):
    """``problem``'s texels and photos with every filtered tap traced to the mesh (``tap_geometry`` mesh)."""
    return StreamProblem(problem.texels, problem.photos, problem.layout,
                         dataclasses.replace(problem.cfg, tap_geometry="mesh"), problem.device)


def traced_polish(problem, result: FitResult, cfg, prior=None) -> FitResult:
    """``cfg.traced_polish`` Levenberg-Marquardt iterations from ``result`` on the same texels and photos with
    traced taps (``StreamConfig.tap_geometry`` mesh), the materials' ``prior`` (centre, weights) kept on, fewer
    where one lowers the objective by less than ``cfg.traced_polish_rel_tol`` (a traced pass costs 7-20x a plane
    one; the iterations before the stop are those of the full polish, to the bit); the trace continues
    ``result``'s (its first row: the start, evaluated with traced taps). Returns ``result`` unchanged where
    :func:`traced_polish_applies` says no."""

    if not traced_polish_applies(problem, cfg):
        return result
    traced = traced_problem(problem)
    if prior is not None:
        traced.set_material_prior(*prior)
    fit = dataclasses.replace(cfg.fit, max_iterations=cfg.traced_polish, optimizer="lm",
                              rel_tol=cfg.traced_polish_rel_tol, sync_every=1, stream=traced.cfg)
    threads, _ = cpu_threads(traced, fit)  # on a multi-core CPU in tiles of texels, traced too: the same bits
    res = (run_tiled_fit(traced, threaded_config(fit, threads), start=(result.params, result.samples))[0]
           if threads > 1 else run_fit(traced, fit, start=(result.params, result.samples)))
    t_end = result.trace[-1]["time_s"] if result.trace else 0.0
    extra = [{**r, "iteration": r["iteration"] + len(result.trace), "time_s": r["time_s"] + t_end,
              "stage": "traced polish"} for r in res.trace]
    return dataclasses.replace(res, trace=result.trace + extra, passes=result.passes + res.passes)


def fit_with_materials(problem, result: FitResult, evidence: TexelEvidence, k: int, variant: str,
                       cfg, polish: bool = False, fit_cfg: FitConfig | None = None) -> tuple[FitResult, dict]:
    """The materials model with ``k`` materials (fit/models/materials.py): cluster, prior, Levenberg-Marquardt from
    the per-texel fit ``result``, then (``polish``) :func:`traced_polish` with the prior on. Returns the fit
    and what model.json records of it. ``fit_cfg``: the fit's stopping rule (default ``cfg.fit``'s; the choice's
    candidates stop by :func:`choice_fit_config`'s)."""
    mcfg = cfg.materials
    lay = result.layout
    seen = evidence.samples > 0
    mats = find_materials(evidence.params, seen, evidence.constrained, lay, k, mcfg.min_lobe_share,
                          mcfg.spread_floor)
    with_lobe = material_lobes_on(evidence.params, mats.labels, mats, lay)
    doubled = scale_lobes(with_lobe, lay, 2.0)
    f_mat, f_bare = per_texel_objective(problem, with_lobe), evidence.bare_objective(problem)
    contradicted = contradiction_test(f_bare, f_mat, per_texel_objective(problem, doubled), evidence.samples,
                                      evidence.sigma2, mcfg.contradiction)
    mats.contradicted_share = reject_contradicted_lobes(mats, mats.labels, seen, evidence.constrained, contradicted,
                                                        mcfg.max_contradicted)
    prior = material_prior(evidence.params, evidence.jtj, seen, evidence.constrained, mats.labels, mats, lay,
                           evidence.sigma2, contradicted, mcfg, variant)
    problem.set_material_prior(prior.centre, prior.weights)
    try:
        base = fit_cfg or cfg.fit
        # the tiles take their stream config from the fit's: the problem's tap geometry (traced with
        # traced_materials) must reach them
        fit = dataclasses.replace(base, max_iterations=mcfg.iterations, optimizer="lm",
                                  stream=dataclasses.replace(base.stream, tap_geometry=problem.cfg.tap_geometry))
        threads, _ = cpu_threads(problem, fit)  # on a multi-core CPU in tiles (their rows of the prior), the same bits
        res = (run_tiled_fit(problem, threaded_config(fit, threads), start=(prior.start, evidence.samples))[0]
               if threads > 1 else run_fit(problem, fit, start=(prior.start, evidence.samples)))
    finally:
        problem.set_material_prior(None)
    if polish:
        res = traced_polish(problem, res, cfg, prior=(prior.centre, prior.weights))
    info = {"variant": variant, "k": mats.k, "materials": mats.to_json(lay),
            "borrowed_texels": int(prior.borrow.sum()), "no_lobe_texels": int(prior.no_lobe.sum()),
            "contradicted_texels": int((contradicted & seen & ~evidence.constrained).sum()),
            "labels": mats.labels, "borrow_mask": prior.borrow, "no_lobe_mask": prior.no_lobe}
    return res, info


def model_grid(params: np.ndarray, result: FitResult, problem, bake, cfg, seams=None,
               unseen: tuple[np.ndarray, np.ndarray] | None = None, lit_seen: np.ndarray | None = None) -> np.ndarray:
    """(H, W, P) maps of compact ``params`` as the stage writes them: padding, texels seen only without the flash,
    unseen texels, seams. ``unseen``: :func:`unseen_sources` of ``problem`` and ``result`` (computed here when None);
    ``lit_seen``: which texels a lit photo saw, where some photos were taken with the flash off (else None)."""
    res = dataclasses.replace(result, params=params)
    grid = params_to_grid(res, problem, bake)
    if cfg.unseen == "nearest":
        if lit_seen is not None:
            grid, _ = fill_unlit_reflectance(grid, problem, bake, result.samples > 0, lit_seen, result.layout)
        grid, _ = fill_unseen_texels(grid, problem, bake, res, sources=unseen)
    grid, _ = average_seams_in_bounds(grid, seams, result.layout)
    return grid


def validation_split(n: int, every: int) -> tuple[list[int], list[int]]:
    """(fitted, validation) indices of ``n`` fitted photos for the materials choice: every k-th is a validation
    photo, k = ``every`` or shorter for few photos (:func:`~texstream.fit.common.inputs.validation_period`)."""
    k = validation_period(n, every)
    return [i for i in range(n) if i % k != k - 1], [i for i in range(n) if i % k == k - 1]


def mesh_view_scores(inputs: "FitInputs", val: list[int], cfg) -> Callable:
    """The materials choice's default scorer: ``score_views(params, result, sub_problem)`` -> the PSNR of each
    validation photo ``val`` (indices of ``inputs.frames``) against the mesh's render of compact ``params``, made
    into maps as the stage writes them (padding, unseen texels, seams). The validation photos are read on a
    thread from here on (beside the validation fit); one renderer (the mesh's BVH), the photos on the device
    (fit/common/view_scores.py) and the unseen texels' nearest seen ones serve every candidate: all are fitted
    on one sub-problem, with one set of samples."""
    frames = [inputs.frames[i] for i in val]
    reading = concurrent.futures.ThreadPoolExecutor(1)
    kept: dict = {"photos": reading.submit(read_photos, inputs.images, inputs.masks, val)}
    reading.shutdown(wait=False)

    def score_views(params, result, sub) -> list[float]:
        if "views" not in kept:  # the photos uploaded, the host's copies let go
            kept["views"] = ViewScores(inputs.mesh, result.layout, frames, *kept.pop("photos").result(), cfg.device)
            kept["unseen"] = unseen_sources(sub, result) if cfg.unseen == "nearest" else None
            # which texels a lit photo saw (the same for every candidate's parameters): the written maps fill the
            # reflectance of those seen only without the flash, so the scored maps do too
            kept["lit_seen"] = (highlight_masks(sub, params).seen if has_unlit_photos(inputs.frames)
                                and not (result.layout.is_radiance or result.layout.view_terms) else None)
        return kept["views"].psnr(model_grid(params, result, sub, inputs.bake, cfg, inputs.seams,
                                             unseen=kept["unseen"], lit_seen=kept["lit_seen"]))

    return score_views


def choice_fit_config(cfg) -> FitConfig:
    """The stopping rule of the materials choice's candidates (each materials model fitted to the validation
    split): ``materials.choice_rel_tol`` tested every 2 iterations, or the fit's own rule where that is 0."""
    tol = cfg.materials.choice_rel_tol
    return cfg.fit if tol <= 0 else dataclasses.replace(cfg.fit, rel_tol=tol, sync_every=2)


def choose_materials(inputs: "FitInputs", problem, cfg, log=None, score_views: Callable | None = None,
                     on_validation_fit: Callable[[FitResult], None] | None = None) -> dict:
    """Pick the per-texel or a materials model (variant and K) on a validation split of the fitted photos:
    every ``materials.validation_every``-th fitted photo is held back (:func:`validation_split`), the per-texel
    fit and every candidate are fitted to the rest and scored by their renders of the validation photos (pooled
    PSNR; ties within 0.05 dB go to the simpler model). The fit's own held-out photos play no part. Every fit stops
    by the candidates' rule (:func:`choice_fit_config`); where the per-texel model scores within
    ``materials.choice_refit_margin_db`` of the best, its fit is continued by the fit's own rule and scored again.
    The candidates share one set-up: the sub-problem's photos are the fit's own, copied on the device
    (PhotoSet.subset: nothing decoded or shadow-mapped again), and one scorer. Each candidate's seconds (fit,
    score) and iterations, and the set-up's and validation fit's, are recorded.
    ``score_views(params, result, sub_problem)``: the validation photos' PSNRs of compact ``params`` (fitted on
    ``sub_problem`` from ``result``); None: the mesh's renders (:func:`mesh_view_scores`).
    ``on_validation_fit(result)``: given the validation split's per-texel fit once the choice is made (the fit
    of every photo starts from it: ``materials.fit_from_validation``). Returns the choice
    and every candidate's score, or {"chosen": "per-texel", "reason": ...} when the fitted photos are too few
    to split."""
    mcfg = cfg.materials
    n = len(inputs.frames)
    every = validation_period(n, mcfg.validation_every)
    train, val = validation_split(n, every)
    if len(val) < 2 or len(train) < 2:
        return {"chosen": "per-texel", "reason": f"{n} fitted photos are too few for a validation split of every "
                                                 f"{every}th"}
    clock = _Clock()
    score_views = score_views or mesh_view_scores(inputs, val, cfg)
    sub = StreamProblem(problem.texels, problem.photos.subset(train), problem.layout, problem.cfg, problem.device)
    seconds = {"setup": clock.lap()}
    fit_cfg = choice_fit_config(cfg)
    # the candidates' rule first (the per-texel fit is the candidates' start and evidence); the fit's own rule
    # only where the per-texel model would be chosen (below). On a multi-core CPU in tiles of texels, one thread
    # each (the same parameters to the bit, fit/multi/cpu_threads.py)
    res, split_rule = _split_fit(sub, fit_cfg), fit_cfg
    seconds["validation_fit"] = clock.lap()

    def score(params, fitted: float) -> dict:
        views = score_views(params, res, sub)
        pooled = float(-10 * np.log10(np.mean([10 ** (-v / 10) for v in views])))
        return {"pooled_psnr_db": pooled, "worst_psnr_db": float(min(views)),
                "seconds": {"fit": fitted, "score": clock.lap()}}

    def per_texel(fitted: float) -> dict:
        params, _ = drop_unsupported_lobes(sub, res, cfg.lobe_support, evidence)
        out = {"model": "per-texel", "iterations": len(res.trace) - 1, **score(params, fitted)}
        return {**out, "excluded": "materials mode on"} if mcfg.mode == "on" else out

    evidence = texel_evidence(sub, res, mcfg)
    seconds["evidence"] = clock.lap()
    cands = [per_texel(seconds["validation_fit"])]
    fitted = candidate_fits(sub, res, evidence, cfg, fit_cfg)
    clock.lap()
    for variant in mcfg.variant_list():
        for k in range(1, mcfg.max_materials + 1):
            (r, info), fit_seconds = fitted((variant, k))
            clock.lap()  # a candidate fitted when asked ran since the last lap: the score's seconds are its own
            if info["k"] < k:
                break  # fewer distinct albedos than k: no new model
            cands.append({"model": variant, "k": info["k"], "iterations": len(r.trace) - 1,
                          **score(r.params, fit_seconds)})
            if log is not None:
                log(f"[fit] validation: {variant} K={k}: pooled {cands[-1]['pooled_psnr_db']:.2f} dB, "
                    f"worst {cands[-1]['worst_psnr_db']:.2f} dB")
    best = _best_candidate(cands)
    if fit_cfg is not cfg.fit and "excluded" not in cands[0] and (
            cands[0]["pooled_psnr_db"] >= best["pooled_psnr_db"] - mcfg.choice_refit_margin_db):
        # the per-texel model would be chosen, or nearly: judged on (and the fit of every photo started from) the
        # fit it stands for, continued by the fit's own rule
        clock.lap()
        early = cands[0]
        res = _split_fit(sub, cfg.fit, start=res)
        split_rule = cfg.fit
        seconds["validation_fit_own_rule"] = clock.lap()
        cands[0] = {**per_texel(seconds["validation_fit"] + seconds["validation_fit_own_rule"]),
                    "at_candidates_rule": {k: early[k] for k in ("pooled_psnr_db", "worst_psnr_db", "iterations")}}
        best = _best_candidate(cands)
    if on_validation_fit is not None:
        on_validation_fit(res)
    name = best["model"] + (f" K={best['k']}" if "k" in best else "")
    return {"chosen": best["model"], "k": best.get("k"), "validation_photos": len(val), "fitted_on": len(train),
            "candidates": cands, "seconds": clock.total(), "seconds_by_part": seconds,
            "stopping": {"candidates": {"rel_tol": fit_cfg.rel_tol, "sync_every": fit_cfg.sync_every},
                         "validation_fit": {"rel_tol": split_rule.rel_tol, "sync_every": split_rule.sync_every}},
            "reason": f"{name}: best pooled PSNR on {len(val)} validation photos (every {every}th fitted photo), "
                      f"{best['pooled_psnr_db']:.2f} dB against per-texel {cands[0]['pooled_psnr_db']:.2f} dB"}


def _split_fit(sub, fit: FitConfig, start: FitResult | None = None) -> FitResult:
    """The validation split's per-texel fit under ``fit``'s rule, from ``start`` (a fit to continue; None: the
    initial guess), in tiles of texels on a multi-core CPU (the same parameters to the bit)."""
    threads, _ = cpu_threads(sub, fit)
    at = None if start is None else (start.params, start.samples)
    res = (run_tiled_fit(sub, threaded_config(fit, threads), start=at)[0] if threads > 1
           else run_fit(sub, fit, start=at))
    return res if start is None else dataclasses.replace(res, trace=start.trace + res.trace[1:])


def _best_candidate(cands: list[dict]) -> dict:
    """The candidate of best validation pooled PSNR, ties within 0.05 dB to the one listed first (the simpler)."""
    eligible = [c for c in cands if "excluded" not in c]
    best = eligible[0]
    for c in eligible[1:]:
        if c["pooled_psnr_db"] > best["pooled_psnr_db"] + 0.05:
            best = c
    return best


def candidate_fits(sub, res: FitResult, evidence: TexelEvidence, cfg, fit_cfg: FitConfig) -> Callable:
    """``fitted((variant, K))`` -> ((FitResult, info), fit seconds) of a materials candidate of the choice, fitted
    on the validation split's problem ``sub`` from its per-texel fit ``res``. On a multi-core CPU every candidate
    is fitted up front, one worker thread per core (a CPU launch runs on its caller's thread and releases the GIL),
    each thread on its own problem over the same photos (a problem holds the candidate's prior and scratch; the
    photos are only read, as the tiles of fit/multi share them): each candidate's fit is its own arithmetic, so the
    choice is the same to the bit on any number of threads (candidates past the distinct albedos, fewer than K, are
    fitted and ignored). Elsewhere a candidate is fitted when asked, as before."""
    jobs = [(variant, k) for variant in cfg.materials.variant_list() for k in range(1, cfg.materials.max_materials + 1)]
    # photos streamed from the host or disk share one window buffer between problems: one thread there
    resident = str(sub.device) == "cpu" and sub.photos.residency == "device"
    asked = fit_cfg.stream.cpu_threads  # 0 auto, 1 one thread, k threads (fit/multi/cpu_threads.py)
    threads = (min(asked or min(usable_cpus(), MAX_AUTO_THREADS), len(jobs)) if resident and asked != 1 else 1)
    problems = queue.SimpleQueue()
    problems.put(sub)
    for _ in range(threads - 1):
        problems.put(StreamProblem(sub.texels, sub.photos, sub.layout, sub.cfg, sub.device))

    def fit_one(job, job_cfg=fit_cfg):
        problem = problems.get()
        try:
            t0 = time.perf_counter()
            out = fit_with_materials(problem, res, evidence, job[1], job[0], cfg, fit_cfg=job_cfg)
            return out, time.perf_counter() - t0
        finally:
            problems.put(problem)

    if threads == 1:
        return fit_one
    # each candidate on one thread (no tiles inside a worker), the first alone: its launches load the prior's
    # kernels, which the others then find loaded
    single = dataclasses.replace(fit_cfg, stream=dataclasses.replace(fit_cfg.stream, cpu_threads=1))
    done = {jobs[0]: fit_one(jobs[0], single)}
    with concurrent.futures.ThreadPoolExecutor(threads) as pool:
        done.update(zip(jobs[1:], pool.map(lambda job: fit_one(job, single), jobs[1:])))
    return done.__getitem__


class _Clock:
    """Seconds since the last lap, and since the start."""

    def __init__(self):
        self.start = self.last = time.perf_counter()

    def lap(self) -> float:
        now = time.perf_counter()
        out, self.last = now - self.last, now
        return out

    def total(self) -> float:
        return time.perf_counter() - self.start


def average_seams_in_bounds(grid: np.ndarray, seams, layout: ModelLayout) -> tuple[np.ndarray, dict | None]:
    """Tie the texels across chart seams (no cracks in bilinear lookups), keeping every value in its
    bounds; returns the maps and what model.json records of the seams."""
    if seams is None:
        return grid, None

    # the view terms' coefficients live in each chart's own tangent frame, so two sides of a seam do
    # not share them: only the radiance along the normal (columns 0:3) is tied there
    cols = slice(0, 3) if layout.view_terms else slice(0, grid.shape[-1])
    part = np.ascontiguousarray(grid[..., cols])
    before = float(np.abs(seam_gaps(part, seams)).max()) if seams.n_samples else 0.0
    part = average_across_seams(part, seams, lower=layout.lower()[cols], upper=layout.upper()[cols])
    grid = grid.copy()
    grid[..., cols] = part
    grid = grid.astype(np.float32)
    after = float(np.abs(seam_gaps(part, seams)).max()) if seams.n_samples else 0.0
    return grid, {"samples": int(seams.n_samples), "max_gap_before": before, "max_gap_after": after}


def _materials_manifest(info: dict | None, evidence: TexelEvidence | None, mcfg: MaterialConfig) -> dict | None:
    """What model.json records of the materials choice (no masks or label arrays)."""
    if info is None:
        return None
    out = {k: v for k, v in info.items() if not k.endswith("_mask")}
    if evidence is not None:
        seen = evidence.samples > 0
        out["uncertainty"] = {"map": "uncertainty.exr", "channels": ["rho_s relative std", "n relative std", "c_z std"],
                              "residual_variance": evidence.sigma2, "constrained_rel_std": mcfg.constrained_rel_std,
                              "constrained_texels": int(evidence.constrained.sum()), "seen_texels": int(seen.sum())}
    return out

