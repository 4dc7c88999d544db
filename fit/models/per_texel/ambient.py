"""The ambient option of the lit per-texel models (``FitConfig.ambient``, render/layout.py ``ModelLayout.ambient``
and ``ModelLayout.room``): off, on (a free per-texel ambient radiance, 3 unknowns per texel), room (the room's
light as one global SH environment lighting the same albedo, 27 unknowns, room_light.py), or auto.

``auto`` decides per capture as every other option of the model choice does, by how well each fit predicts
photos it did not see, and never with the fit's own held-out photos: every ``materials.validation_every``-th
fitted photo is held back (lobes.py :func:`validation_split`), the model is fitted to the rest without a term,
with the room light and with the free ambient (the same stopping rule, the same lobe support rule) and each is
scored by its renders of the validation photos (pooled PSNR). A candidate replaces a simpler one only when it
gains more than ``MIN_GAIN_DB``: ties go to the simpler model (off, then room, then on), as in the materials
choice, so a capture without room light keeps its flash-only model.

Photos taken with the flash off (capture_json.py ``no_flash``, flash/no-flash pairs) see the room's light alone:
the ambient radiance is observed directly, not told from the albedo by how little the flash's light varies between
views. With them ``auto`` fits ``on`` without the validation comparison (the reason in model.json), ``off`` is
refused (those photos would be predicted black), and the fit starts from the flash photos' samples alone (a
no-flash sample over its light's weight, ~0, is no estimate of the albedo or the lobes)."""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from texstream.capture.capture_json import flash_fired
from texstream.core.errors import ConfigError
from texstream.core.progress import say
from texstream.fit.optim.fitter import FitStart, fit_start, run_fit
from texstream.fit.models.per_texel.lobes import drop_unsupported_lobes, mesh_view_scores, validation_split
from texstream.fit.common.inputs import validation_period
from texstream.fit.models.per_texel.room_light import fit_room, texel_transfer
from texstream.fit.stream.problem import StreamProblem
from texstream.render.layout import layout_traits

MIN_GAIN_DB = 0.05
"""held-out gain (pooled PSNR on the validation photos) the ambient term must bring to be kept: the materials
choice's tie margin (lobes.py ``choose_materials``), below which the simpler model wins"""


def ambient_applies(layout) -> bool:
    """Whether the layout's kind can carry the term (``LayoutTraits.ambient``; lit kinds only; the room light too)."""
    traits = layout_traits(layout.kind)
    return bool(traits.ambient and traits.lit)


def with_layout(problem: StreamProblem, layout) -> StreamProblem:
    """The same texels and photos under another layout (nothing decoded or mapped again)."""
    if layout == problem.layout:
        return problem
    return StreamProblem(problem.texels, problem.photos, layout, problem.cfg, problem.device)


def start_for(start: FitStart, problem: StreamProblem) -> FitStart:
    """``start`` (the initial guess of a layout without the term) for ``problem``'s layout: the ambient (or room)
    columns at their default 0 (the room's share starts inside rho_d, which the low percentile over-estimates by the
    ambient over the flash's weight; the fit moves it out)."""
    params, counts = start.numpy()
    n_params = problem.layout.n_params
    if params.shape[1] == n_params:
        return start
    extra = np.tile(problem.layout.defaults()[params.shape[1]:], (params.shape[0], 1))
    return FitStart.of((np.concatenate([params, extra], axis=1), counts), problem)


MODES = ("off", "room", "on")
"""the candidates of auto, simplest first (ties keep the earlier)"""


def layout_for(layout, mode: str):
    """``layout`` with the term ``mode`` (off, on, room) asks for."""
    return dataclasses.replace(layout, ambient=mode == "on", room=mode == "room")


def room_start(inputs, problem: StreamProblem, start: FitStart, cfg) -> tuple[FitStart, dict | None]:
    """(start, room report): for a room-light layout, the alternation's rounds (room_light.py) and the start of
    the last per-texel fit, whose room columns hold the fitted light; ``start`` and None otherwise."""
    if not problem.layout.room:
        return start, None
    t0 = time.perf_counter()
    transfer = texel_transfer(problem, inputs.mesh, cfg.device)
    start, room = fit_room(problem, cfg.fit, start, transfer)
    return start, {**room.to_json(), "seconds": time.perf_counter() - t0}


def choose_ambient(inputs, problem: StreamProblem, cfg) -> dict:
    """Which term to fit (``cfg.fit.ambient`` auto), judged on a validation split of the fitted photos (module
    doc). Returns {"chosen": "off" | "room" | "on", "reason", and, where the split was fitted, the validation
    photos, each fit's pooled and worst-view PSNR, iterations and seconds}."""
    n = len(inputs.frames)
    every = validation_period(n, cfg.materials.validation_every)
    train, val = validation_split(n, every)
    if len(val) < 2 or len(train) < 2:
        return {"chosen": "off", "reason": f"{n} fitted photos are too few for a validation split of every {every}th; "
                                           "without the term (the simpler model)"}
    photos = problem.photos.subset(train)
    scores = {}
    for chosen in MODES:
        t0 = time.perf_counter()
        sub = StreamProblem(problem.texels, photos, layout_for(problem.layout, chosen), problem.cfg, problem.device)
        start, _ = room_start(inputs, sub, fit_start(sub, cfg.fit), cfg)
        res = run_fit(sub, cfg.fit, start=start)
        fitted = time.perf_counter() - t0
        params, _ = drop_unsupported_lobes(sub, res, cfg.lobe_support)
        views = mesh_view_scores(inputs, val, cfg)(params, res, sub)
        pooled = float(-10 * np.log10(np.mean([10 ** (-v / 10) for v in views])))
        scores[chosen] = {"pooled_psnr_db": pooled, "worst_psnr_db": float(min(views)),
                          "iterations": len(res.trace) - 1,
                          "seconds": {"fit": fitted, "score": time.perf_counter() - t0 - fitted}}
        say("fit", f"ambient {chosen}: validation pooled {pooled:.2f} dB, worst view {min(views):.2f} dB")
    chosen = "off"
    for mode in MODES[1:]:
        if scores[mode]["pooled_psnr_db"] > scores[chosen]["pooled_psnr_db"] + MIN_GAIN_DB:
            chosen = mode
    listed = ", ".join(f"{m} {scores[m]['pooled_psnr_db']:.2f} dB" for m in MODES)
    return {"chosen": chosen, "validation_photos": len(val), "fitted_on": len(train), "candidates": scores,
            "reason": f"ambient {chosen}: pooled PSNR on {len(val)} validation photos (every {every}th fitted photo) "
                      f"{listed} (a richer term kept above a {MIN_GAIN_DB} dB gain)"}


def no_flash_decision(inputs, mode: str) -> dict | None:
    """The ambient term's report when some fitted photos were taken with the flash off (module doc), else None.

    Raises:
        ConfigError: ``mode`` off with no-flash photos.
    """
    dark = [f.name for f in inputs.frames if not flash_fired(f)]
    if not dark:
        return None
    if mode == "off":
        raise ConfigError(f"--ambient off with {len(dark)} no-flash photo(s) (e.g. {dark[0]}): the room's light they "
                          "show alone would be predicted black", fix="use --ambient on or auto")
    chosen = "on" if mode == "auto" else mode
    return {"mode": mode, "chosen": chosen, "no_flash_photos": len(dark),
            "reason": f"{len(dark)} of {len(inputs.frames)} fitted photos were taken with the flash off: they see the "
                      "room's light alone, so the ambient term is observed directly"
                      + (" (on, without the validation comparison)" if mode == "auto" else " (requested)")}


def flash_only_start(problem: StreamProblem, start: FitStart, inputs, cfg) -> FitStart:
    """The initial guess from the flash photos' samples alone (module doc), with ``start``'s sample counts (a texel
    only no-flash photos see is still seen)."""
    lit = [k for k, f in enumerate(inputs.frames) if flash_fired(f)]
    if not lit:
        return start
    sub = StreamProblem(problem.texels, problem.photos.subset(lit), problem.layout, problem.cfg, problem.device)
    guess, _ = fit_start(sub, cfg.fit).numpy()
    return FitStart.of((guess, start.numpy()[1]), problem)


def resolve_ambient(inputs, problem: StreamProblem, start: FitStart, cfg):
    """(problem, start, cfg, report) of the fit with ``cfg.fit.ambient`` resolved to off, on or room: auto chosen
    by :func:`choose_ambient`; the problem and start carry the term's columns where it is on (the room light's
    fitted by its alternation, the report's ``room``). ``report`` (None for a kind without the term) goes to
    model.json's ``ambient``."""
    mode = cfg.fit.ambient
    if not ambient_applies(problem.layout):
        return problem, start, cfg, None
    report = no_flash_decision(inputs, mode)
    if report is not None and problem.cfg.residual_space != "radiance":
        raise ConfigError(f"stream.residual_space {problem.cfg.residual_space} divides each sample by its flash's "
                          f"light, which is 0 in the {report['no_flash_photos']} no-flash photos",
                          fix="use stream.residual_space radiance (the default)")
    if report is not None:
        say("fit", report["reason"])
        start = flash_only_start(problem, start, inputs, cfg)
    elif mode != "auto":
        report = {"mode": mode, "chosen": mode, "reason": "requested"}
    else:
        report = {"mode": mode, **choose_ambient(inputs, problem, cfg)}
        say("fit", report["reason"])
    problem = with_layout(problem, layout_for(problem.layout, report["chosen"]))
    cfg = dataclasses.replace(cfg, fit=dataclasses.replace(cfg.fit, ambient=report["chosen"]))
    start, room = room_start(inputs, problem, start_for(start, problem), cfg)
    if room is not None:
        report["room"] = room
    return problem, start, cfg, report
