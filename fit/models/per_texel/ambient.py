"""The ambient radiance option of the lit per-texel models (``FitConfig.ambient``, render/layout.py
``ModelLayout.ambient``): off, on, or auto.

``auto`` decides per capture as every other option of the model choice does, by how well each fit predicts
photos it did not see, and never with the fit's own held-out photos: every ``materials.validation_every``-th
fitted photo is held back (lobes.py :func:`validation_split`), the model is fitted to the rest once without the
ambient term and once with it (the same stopping rule, the same lobe support rule) and both are scored by their
renders of the validation photos (pooled PSNR). The term is kept when it gains more than ``MIN_GAIN_DB``: ties
go to the simpler model, as in the materials choice, so a capture without room light keeps its flash-only
model."""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from texstream.core.progress import say
from texstream.fit.optim.fitter import FitStart, run_fit
from texstream.fit.models.per_texel.lobes import drop_unsupported_lobes, mesh_view_scores, validation_split
from texstream.fit.stream.problem import StreamProblem
from texstream.render.layout import layout_traits

MIN_GAIN_DB = 0.05
"""held-out gain (pooled PSNR on the validation photos) the ambient term must bring to be kept: the materials
choice's tie margin (lobes.py ``choose_materials``), below which the simpler model wins"""


def ambient_applies(layout) -> bool:
    """Whether the layout's kind can carry the term (``LayoutTraits.ambient``; lit kinds only)."""
    traits = layout_traits(layout.kind)
    return bool(traits.ambient and traits.lit)


def with_layout(problem: StreamProblem, layout) -> StreamProblem:
    """The same texels and photos under another layout (nothing decoded or mapped again)."""
    if layout == problem.layout:
        return problem
    return StreamProblem(problem.texels, problem.photos, layout, problem.cfg, problem.device)


def start_for(start: FitStart, problem: StreamProblem) -> FitStart:
    """``start`` (the initial guess of a layout without the term) for ``problem``'s layout: the ambient columns at
    their default 0 (the room's share starts inside rho_d, which the low percentile over-estimates by the
    ambient over the flash's weight; the fit moves it out)."""
    params, counts = start.numpy()
    n_params = problem.layout.n_params
    if params.shape[1] == n_params:
        return start
    extra = np.tile(problem.layout.defaults()[params.shape[1]:], (params.shape[0], 1))
    return FitStart.of((np.concatenate([params, extra], axis=1), counts), problem)


def choose_ambient(inputs, problem: StreamProblem, cfg) -> dict:
    """Whether to fit the ambient term (``cfg.fit.ambient`` auto), judged on a validation split of the fitted
    photos (module doc). Returns {"chosen": "on" | "off", "reason", and, where the split was fitted, the
    validation photos, each fit's pooled and worst-view PSNR, iterations and seconds}."""
    every = cfg.materials.validation_every
    n = len(inputs.frames)
    train, val = validation_split(n, every)
    if len(val) < 2 or len(train) < 2:
        return {"chosen": "off", "reason": f"{n} fitted photos are too few for a validation split of every {every}th; "
                                           "without the term (the simpler model)"}
    photos = problem.photos.subset(train)
    scores = {}
    for chosen, on in (("off", False), ("on", True)):
        t0 = time.perf_counter()
        sub = StreamProblem(problem.texels, photos, dataclasses.replace(problem.layout, ambient=on), problem.cfg,
                            problem.device)
        res = run_fit(sub, cfg.fit)
        fitted = time.perf_counter() - t0
        params, _ = drop_unsupported_lobes(sub, res, cfg.lobe_support)
        views = mesh_view_scores(inputs, val, cfg)(params, res, sub)
        pooled = float(-10 * np.log10(np.mean([10 ** (-v / 10) for v in views])))
        scores[chosen] = {"pooled_psnr_db": pooled, "worst_psnr_db": float(min(views)),
                          "iterations": len(res.trace) - 1,
                          "seconds": {"fit": fitted, "score": time.perf_counter() - t0 - fitted}}
        say("fit", f"ambient {chosen}: validation pooled {pooled:.2f} dB, worst view {min(views):.2f} dB")
    gain = scores["on"]["pooled_psnr_db"] - scores["off"]["pooled_psnr_db"]
    chosen = "on" if gain > MIN_GAIN_DB else "off"
    return {"chosen": chosen, "validation_photos": len(val), "fitted_on": len(train), "candidates": scores,
            "reason": f"ambient {chosen}: pooled PSNR on {len(val)} validation photos (every {every}th fitted photo) "
                      f"{scores['on']['pooled_psnr_db']:.2f} dB with the term against "
                      f"{scores['off']['pooled_psnr_db']:.2f} dB without (kept above a {MIN_GAIN_DB} dB gain)"}


def resolve_ambient(inputs, problem: StreamProblem, start: FitStart, cfg):
    """(problem, start, cfg, report) of the fit with ``cfg.fit.ambient`` resolved to on or off: auto chosen by
    :func:`choose_ambient`; the problem and start carry the term's columns where it is on. ``report`` (None for a
    kind without the term) goes to model.json's ``ambient``."""
    mode = cfg.fit.ambient
    if not ambient_applies(problem.layout):
        return problem, start, cfg, None
    report = {"mode": mode, "chosen": mode, "reason": "requested"}
    if mode == "auto":
        report = {"mode": mode, **choose_ambient(inputs, problem, cfg)}
        say("fit", report["reason"])
    on = report["chosen"] == "on"
    problem = with_layout(problem, dataclasses.replace(problem.layout, ambient=on))
    cfg = dataclasses.replace(cfg, fit=dataclasses.replace(cfg.fit, ambient=report["chosen"]))
    return problem, start_for(start, problem), cfg, report
