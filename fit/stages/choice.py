"""The automatic model choice (``texstream fit --model auto``, and ``texstream run``): which appearance model
a capture calls for, which candidates are fitted beside it, and which one is kept.

The policy is written over the registry's declarations, never over model names: the base model is the plugin
of lowest ``auto_rank`` among those whose ``needs_light`` matches the capture (every photo with a known light:
a reflectance model; one fixed, unknown lighting: a radiance model). When the fit holds photos out, the base
model's ``candidates`` are fitted (e.g. diffuse beside Lafortune: a lobe only where it generalises; one whose
``supported`` says the photos cannot support it is left out unfitted), then its ``escalate`` may add fits once
the first round is scored (light field mapping where view dependence matters).

Every decision (the kept model, the escalation, the second lobe) is made on a validation split of the fitted
photos, the materials choice's (every ``materials.validation_every``-th fitted photo): the held-out photos only
score the model handed over, as a user meets it. A candidate whose own fit makes its materials choice on that
split is fitted once, to every fitted photo, and judged by that choice's score; any other is judged by a fit of
the split and fitted to every fitted photo only when kept (:func:`fit_choice`); a validation fit that can stop
early (light field mapping's) is told the best score so far and ends once it cannot reach it
(``choice.stop_hopeless``). The kept fit is renamed to ``<out>``; the other full fits stay beside it as
``<out>_<candidate>``.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import shutil
import time
from pathlib import Path
from typing import Callable

from texstream.core.config import option
from texstream.core.errors import InputError, TexstreamError
from texstream.core.outputs import StageResult, write_json_atomic
from texstream.core.progress import say
from texstream.capture.capture_json import split_holdout
from texstream.fit.common.inputs import validation_period
from texstream.fit.models import registry

AUTO = "auto"
LFM_CANDIDATE = ("auto", "always", "never")


@dataclasses.dataclass
class ModelChoiceConfig:
    """Options of the automatic model choice (``--model auto``). Every decision is made on a validation split of
    the fitted photos (every ``materials.validation_every``-th); the held-out photos only score the model kept."""

    second_lobe: bool = option(True, "known lights, held-out photos: also fit a two-lobe Lafortune model (the second "
                                     "lobe kept per texel only where it lowers the texel's error on the fitted "
                                     "photos, lobe_support) and keep it only when it predicts the validation photos "
                                     "best; fitted only where the photos can support it (second_lobe_min_constrained)")
    second_lobe_min_constrained: float = option(0.3, "second_lobe: the two-lobe model is fitted only when at least "
                                                     "this share of the seen texels have a lobe their photos "
                                                     "constrain in the one-lobe fit (materials.constrained_rel_std): "
                                                     "only those can pin a second lobe down; 0: always fitted",
                                                min=0.0, max=1.0)
    lfm: str = option("auto", "fixed unknown lighting, held-out photos: fit a light field mapping model ([fit.lfm]) "
                              "beside radiance and view_radiance and keep it when it predicts the validation photos "
                              "best: auto (only when view dependence matters: view_radiance's validation pooled PSNR "
                              "at least lfm_min_gain_db above radiance's), always, or never", choices=LFM_CANDIDATE)
    lfm_min_gain_db: float = option(0.5, "lfm auto: the validation gain (dB) of view_radiance over radiance from "
                                         "which view dependence counts as mattering", min=-60.0, max=60.0)
    lobe_min_highlight_share: float = option(0.001, "known lights: the Lafortune candidates are fitted only when at "
                                                    "least this share of the seen texels show a highlight "
                                                    "(fit/common/highlights.py) in the diffuse candidate's validation "
                                                    "fit, judged first: a lobe has nothing to explain where the "
                                                    "photos show none, and the Lafortune fit with its materials "
                                                    "choice was 140 of the 209 s of a 6 MP facade's fit stage; "
                                                    "0: always fitted", min=0.0, max=1.0)
    relightable: bool = option(False, "one fixed unknown lighting: also fit the relightable models of the registry "
                                      "(env_diffuse: albedo and the light, estimated) and keep one when its "
                                      "validation pooled PSNR is within relightable_margin_db of the best model's; "
                                      "off by default: one more fit (8.5 min on the temple on the 2-core CPU)")
    relightable_margin_db: float = option(1.0, "relightable: how far (dB, validation pooled PSNR) below the best model "
                                               "a relightable model may be and still be kept", min=0.0, max=60.0)
    stop_hopeless: bool = option(True, "a candidate's validation fit that can stop early (lfm) ends once it cannot "
                                       "win: its validation pooled PSNR, rising for the iterations left at the best "
                                       "rate of its last two checks, stays more than 0.2 dB below the best "
                                       "candidate's so far (it is judged by its score there; the temple's lfm "
                                       "stops after 30 of 50 iterations); off: fitted to its iteration cap")
    beat_db: float = option(0.0, "set by the choice on a candidate's validation fit (stop_hopeless): the best "
                                 "validation pooled PSNR (dB) of the candidates judged before it; 0: none", min=0.0)
    validation_fit: bool = option(False, "fit only the fitted photos less every materials.validation_every-th and "
                                         "score those validation photos where the held-out ones are scored (the "
                                         "held-out photos are not read): how the choice judges a candidate whose "
                                         "own fit makes no choice on that split (an lfm fit writes its scores "
                                         "only, model.json)")


@dataclasses.dataclass
class ChoicePlan:
    """What the choice will fit: the base kind and why, the first round of candidates (empty: the base model
    alone, no comparison), a phrase naming them for logs, and the period of the validation split of this
    capture's fitted photos (:func:`~texstream.fit.common.inputs.validation_period`; None: the configured one)."""

    base: str
    reason: str
    candidates: list
    also: str = ""
    validation_every: int | None = None

    @property
    def compare(self) -> bool:
        return bool(self.candidates)


def requested_model(capture, requested: str) -> tuple[str, str]:
    """(kind, reason) of the model the capture calls for; ``requested`` a kind or ``auto``. A kind that needs a
    light per photo on a capture without lights is an InputError."""
    if requested != AUTO:
        plugin = registry.get(requested)
        if plugin.needs_light and not capture.has_lights:
            raise InputError(f"--model {requested} needs a light per photo and the capture has none",
                             Path(capture.root) / "capture.json",
                             "use a model that needs no light (radiance, or auto), or give the lights")
        return requested, "requested"
    lit = bool(capture.has_lights)
    bases = [m for m in map(registry.get, registry.kinds()) if m.candidates is not None and m.needs_light == lit]
    if not bases:
        raise InputError("no model of the registry can fit this capture", Path(capture.root) / "capture.json",
                         "choose a model with --model")
    base = min(bases, key=lambda m: (m.auto_rank, m.kind))
    why = ("every photo has a known light: reflectance model" if lit else
           "no photo has a known light (one fixed, unknown lighting): radiance model")
    return base.kind, f"{why} ({base.title})"


def plan_choice(capture, requested: str, cfg) -> ChoicePlan:
    """The plan for ``requested`` (a kind or ``auto``) under the fit stage config ``cfg``: candidates only with
    ``auto`` and a fit that holds at least one photo out (``cfg.holdout_every``, the run's default: the user
    asked for the model to be scored as they will meet it). The candidates are judged on a validation split of
    the fitted photos; a bare ``texstream fit`` fits the base model alone, as before."""
    kind, why = requested_model(capture, requested)
    plugin = registry.get(kind)
    holds_out = 0 < cfg.holdout_every <= len(capture.frames)
    if requested != AUTO or not holds_out or plugin.candidates is None:
        return ChoicePlan(kind, why, [])
    cands = plugin.candidates(capture, cfg)
    if len(cands) < 2:
        return ChoicePlan(kind, why, [])
    also = " and ".join(c.label or c.name for c in cands if c.name != kind)  # the base kind need not come first
    if plugin.escalate is not None:
        also += plugin.escalate(None, cfg)[1]
    fitted = len(split_holdout(capture.frames, cfg.holdout_every)[0])
    return ChoicePlan(kind, why, cands, also, validation_period(fitted, cfg.materials.validation_every))


def _db(value) -> str:
    return "n/a" if value is None else f"{value:.2f} dB"


VALIDATION_SUFFIX = "_validation"
"""a candidate's validation fit goes to ``<out>_<name>_validation`` (removed once the choice is made)"""


@dataclasses.dataclass
class Judged:
    """A candidate as the choice judged it: its validation scores (None: no photo to validate on), how it was
    judged, the seconds that took, and its fit of every fitted photo (None: only a validation fit so far)."""

    candidate: object
    pooled_db: float | None
    worst_db: float | None
    judged_by: str
    seconds: float
    full: StageResult | None = None
    summary: dict | None = None
    """the summary of the fit it was judged by (its validation fit's, or its fit of every fitted photo)"""
    stop: dict | None = None
    """its validation fit's checks of whether it could still win (choice.stop_hopeless), None: not checked"""

    def record(self) -> dict:
        return {"pooled_psnr_db": self.pooled_db, "worst_psnr_db": self.worst_db, "judged_by": self.judged_by,
                "seconds": self.seconds, **({"stop": self.stop} if self.stop else {})}


def makes_own_choice(candidate, cfg) -> bool:
    """Whether the candidate's own fit chooses its materials on the validation split (a model with lobes and
    ``materials.mode`` not off: fit/models/per_texel/lobes.py ``choose_materials``), scoring that split on the
    way: its fit of every photo is then made once and judged by that score."""
    traits = registry.get(candidate.kind).layout_traits
    lobes = candidate.overrides.get("lobes", cfg.fit.lobes)
    return bool(traits is not None and traits.lobes and lobes > 0 and cfg.materials.mode != "off")


def own_validation_score(summary: dict) -> tuple[float, float] | None:
    """(pooled, worst-view) validation PSNR of the materials model a fit's own choice kept, or None where its
    choice scored nothing (too few fitted photos to split)."""
    m = summary.get("materials") or {}
    for c in m.get("candidates") or []:
        if c["model"] == m.get("chosen") and c.get("k") == m.get("k") and "excluded" not in c:
            return c["pooled_psnr_db"], c["worst_psnr_db"]
    return None


def fit_choice(capture_dir: Path, mesh_path: Path, out_dir: Path, cfg, plan: ChoicePlan,
               fit_one: Callable, log: Callable[[str], None] | None = None):
    """Fit the plan's candidates (``fit_one(capture_dir, mesh_path, out, cfg)`` is the single-model fit stage) and
    keep the one that predicts a validation split of the fitted photos best (every ``materials.validation_every``-th,
    the split of the materials choice) as ``out_dir``; the held-out photos only score the kept model.

    A candidate whose own fit chooses its materials on that split (:func:`makes_own_choice`: Lafortune) is
    fitted to every fitted photo into ``<out_dir>_<name>`` and judged by its choice's score; any other gets a
    validation fit (``choice.validation_fit``, into ``<out_dir>_<name>_validation``) and, when kept, its fit of
    every fitted photo afterwards (from its initial guess: no plugin takes a warm start). A candidate whose
    ``supported`` says the photos cannot support it is left out unfitted, with the reason. Returns the kept fit's
    StageResult, its summary carrying ``selection`` (chosen, chosen_kind, reason, validation scores by candidate,
    left_out, the kept model's held-out scores, seconds), also written to its model.json."""
    log = log or (lambda line: say("fit", line.removeprefix("[fit] ")))
    out_dir, t0 = Path(out_dir), time.perf_counter()
    every = plan.validation_every or cfg.materials.validation_every  # the split every candidate is judged on
    judged: dict[str, Judged] = {}
    left_out: dict[str, str] = {}
    failed: set[str] = set()  # escalations the capture could not take (said in the escalation's reason)

    def folder(c, suffix: str = "") -> Path:
        return out_dir.with_name(f"{out_dir.name}_{c.name}{suffix}")

    def config(c, validation: bool):
        beat = [j.pooled_db for j in judged.values() if j.pooled_db is not None and validation
                and cfg.choice.stop_hopeless]
        return dataclasses.replace(cfg, fit=dataclasses.replace(cfg.fit, model=c.kind, **c.overrides),
                                   choice=dataclasses.replace(cfg.choice, validation_fit=validation,
                                                              beat_db=max([0.0, *beat])),
                                   **({"renders": 0} if validation else {}))

    def judge(c) -> None:
        if c.supported is not None:
            why = c.supported({k: j.summary for k, j in judged.items() if j.summary is not None}, cfg)
            if why:
                left_out[c.name] = why
                log(f"[fit] {c.name} left out: {why}")
                return
        t, full, score, stop, fitted = time.perf_counter(), None, None, None, None
        if makes_own_choice(c, cfg):
            full = fit_one(capture_dir, mesh_path, folder(c), config(c, False))
            fitted = full.summary
            score, how = own_validation_score(full.summary), "its own materials choice on the validation split"
        if score is None:
            fitted = fit_one(capture_dir, mesh_path, folder(c, VALIDATION_SUFFIX), config(c, True)).summary
            h, how = fitted["heldout"], "a fit of the validation split"
            score = h.get("pooled_psnr_db"), h.get("worst_psnr_db")
            stop = fitted.get("stop")  # choice.stop_hopeless: the checks of whether it could still win
            if stop and stop["stopped"]:
                how += f", {stop['stopped']}"
        judged[c.name] = Judged(c, *score, how, time.perf_counter() - t, full, fitted, stop)
        log(f"[fit] {c.name}: validation pooled PSNR {_db(score[0])}, worst view {_db(score[1])} ({how})")

    for c in plan.candidates:
        judge(c)
    escalate = registry.get(plan.base).escalate
    extra_reason = None
    if escalate is not None:
        extra, extra_reason = escalate({k: j.pooled_db for k, j in judged.items()}, cfg)
        log(f"[fit] {extra_reason}")
        for c in extra:
            try:
                judge(c)
            except TexstreamError as e:  # an optional candidate the capture cannot take (e.g. streamed photos)
                extra_reason += f"; {c.name} could not be fitted ({e.message}), left out"
                left_out[c.name] = f"could not be fitted ({e.message})"
                failed.add(c.name)
                log(f"[fit] {c.name} could not be fitted ({e.message}): left out")
    relit = _relightable_candidates(plan, cfg)
    for c in relit:
        judge(c)
    best, reason = _best({k: j for k, j in judged.items() if k not in {c.name for c in relit}}, every)
    if relit:
        best, reason = _prefer_relightable(judged, best, reason, [c.name for c in relit], cfg.choice.relightable_margin_db)
    reason += "".join(f"; {k} left out: {why}" for k, why in left_out.items() if k not in failed)
    kept = judged[best]
    t_refit, refit = time.perf_counter(), kept.full is None
    if refit:
        log(f"[fit] {best}: fitted to every fitted photo")
        kept.full = fit_one(capture_dir, mesh_path, folder(kept.candidate), config(kept.candidate, False))
    for c in (j.candidate for j in judged.values()):
        shutil.rmtree(folder(c, VALIDATION_SUFFIX), ignore_errors=True)
    if out_dir.exists():
        shutil.rmtree(out_dir)
    os.replace(folder(kept.candidate), out_dir)
    res = kept.full
    res.output = out_dir
    held = res.summary.get("heldout") or {}
    selection = {"chosen": best, "chosen_kind": kept.candidate.kind, "reason": reason,
                 "validation_every": every,
                 "validation": {k: j.record() for k, j in judged.items()}, "left_out": left_out,
                 "heldout_pooled_db": held.get("pooled_psnr_db"), "heldout_worst_db": held.get("worst_psnr_db"),
                 "refit": ("its validation fit was fitted again to every fitted photo, from its initial guess"
                           if refit else None),
                 "seconds": {"choice": t_refit - t0, "refit": time.perf_counter() - t_refit if refit else 0.0}}
    if extra_reason is not None:
        selection[registry.get(plan.base).escalation_key] = extra_reason
    res.summary["selection"] = selection
    _record_selection(out_dir, selection)
    return res


def _relightable_candidates(plan: ChoicePlan, cfg) -> list:
    """The registry's relightable models for a capture like the base model's (``choice.relightable``)."""
    if not cfg.choice.relightable:
        return []
    lit = registry.get(plan.base).needs_light
    return [registry.Candidate(k, k, label=f"the relightable {k}") for k in registry.kinds()
            if registry.get(k).relightable and registry.get(k).needs_light == lit and k != plan.base]


def _prefer_relightable(judged: dict, best: str, reason: str, relit: list[str], margin_db: float) -> tuple[str, str]:
    """(kept, reason): the best relightable candidate when its validation pooled PSNR is within ``margin_db`` of
    ``best``'s (a model that can be relit is worth that much), else ``best`` with why not."""
    scored = [k for k in relit if judged[k].pooled_db is not None]
    if not scored:
        return best, reason + "; no relightable model could be validated, so none kept"
    top = max(scored, key=lambda k: judged[k].pooled_db)
    ref = judged[best].pooled_db
    if ref is None or judged[top].pooled_db >= ref - margin_db:
        return top, (f"{top} kept (relightable): validation pooled PSNR {_db(judged[top].pooled_db)}, within "
                     f"relightable_margin_db {margin_db:g} of the best other model's ({reason})")
    return best, (reason + f"; the relightable {top} not kept: {_db(judged[top].pooled_db)}, more than "
                  f"relightable_margin_db {margin_db:g} below")


def _best(judged: dict, every: int) -> tuple[str, str]:
    """(name, reason): the candidate of best validation pooled PSNR (the first on ties); the first when no photo
    could be validated on."""
    names = list(judged)
    score = {k: judged[k].pooled_db for k in names}
    if all(v is None for v in score.values()):
        return names[0], f"{names[0]} kept: too few fitted photos for a validation split, so no model could be judged"
    best = max(names, key=lambda k: -math.inf if score[k] is None else score[k])
    return best, (f"{best} kept: validation pooled PSNR (every {every}th fitted photo) "
                  + ", ".join(f"{k} {_db(score[k])}" for k in names))


def _record_selection(model_dir: Path, selection: dict) -> None:
    """The choice's record added to the kept model's model.json (written atomically)."""
    path = model_dir / "model.json"
    manifest = json.loads(path.read_text())
    manifest["selection"] = selection
    write_json_atomic(path, manifest)
