"""The automatic model choice (``texstream fit --model auto``, and ``texstream run``): which appearance model
a capture calls for, which candidates are fitted beside it, and which one is kept.

The policy is written over the registry's declarations, never over model names: the base model is the plugin
of lowest ``auto_rank`` among those whose ``needs_light`` matches the capture (every photo with a known light:
a reflectance model; one fixed, unknown lighting: a radiance model). With held-out photos to judge by, the
base model's ``candidates`` are fitted (e.g. diffuse beside Lafortune: a lobe only where it generalises), then
its ``escalate`` may add fits once the first round is scored (light field mapping where view dependence
matters), and the candidate with the best pooled held-out PSNR is kept. Each candidate is fitted into a
sibling folder ``<out>_<candidate>``; the kept one is renamed to ``<out>``.
"""

from __future__ import annotations

import dataclasses
import math
import os
import shutil
from pathlib import Path
from typing import Callable

from texstream.core.config import option
from texstream.core.errors import InputError, TexstreamError
from texstream.core.progress import say
from texstream.fit.models import registry

AUTO = "auto"
LFM_CANDIDATE = ("auto", "always", "never")


@dataclasses.dataclass
class ModelChoiceConfig:
    """Options of the automatic model choice (``--model auto``)."""

    second_lobe: bool = option(True, "known lights, held-out photos: also fit a two-lobe Lafortune model (the second "
                                     "lobe kept per texel only where it lowers the texel's error on the fitted "
                                     "photos, lobe_support) and keep it only when its held-out error is the best")
    lfm: str = option("auto", "fixed unknown lighting, held-out photos: fit a light field mapping model ([fit.lfm]) "
                              "beside radiance and view_radiance and keep it when its held-out error is the best: "
                              "auto (only when view dependence matters: view_radiance's held-out pooled PSNR at least "
                              "lfm_min_gain_db above radiance's), always, or never", choices=LFM_CANDIDATE)
    lfm_min_gain_db: float = option(0.5, "lfm auto: the held-out gain (dB) of view_radiance over radiance from "
                                         "which view dependence counts as mattering", min=-60.0, max=60.0)


@dataclasses.dataclass
class ChoicePlan:
    """What the choice will fit: the base kind and why, the first round of candidates (empty: the base model
    alone, no comparison) and a phrase naming them for logs."""

    base: str
    reason: str
    candidates: list
    also: str = ""

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
    ``auto`` and at least one held-out photo (``cfg.holdout_every``)."""
    kind, why = requested_model(capture, requested)
    plugin = registry.get(kind)
    judged = 0 < cfg.holdout_every <= len(capture.frames)
    if requested != AUTO or not judged or plugin.candidates is None:
        return ChoicePlan(kind, why, [])
    cands = plugin.candidates(capture, cfg)
    if len(cands) < 2:
        return ChoicePlan(kind, why, [])
    also = " and ".join(c.label or c.name for c in cands[1:])
    if plugin.escalate is not None:
        also += plugin.escalate(None, cfg)[1]
    return ChoicePlan(kind, why, cands, also)


def _db(value) -> str:
    return "n/a" if value is None else f"{value:.2f} dB"


def fit_choice(capture_dir: Path, mesh_path: Path, out_dir: Path, cfg, plan: ChoicePlan,
               fit_one: Callable, log: Callable[[str], None] | None = None):
    """Fit the plan's candidates (``fit_one(capture_dir, mesh_path, out, cfg)`` is the single-model fit stage)
    into ``<out_dir>_<name>`` folders and keep the best held-out one as ``out_dir``; the StageResult of the
    kept fit, its summary carrying ``selection`` (chosen, chosen_kind, reason, scores)."""
    log = log or (lambda line: say("fit", line.removeprefix("[fit] ")))
    out_dir = Path(out_dir)
    results, kinds = {}, {}

    def fit_candidate(c) -> None:
        fit_cfg = dataclasses.replace(cfg.fit, model=c.kind, **c.overrides)
        res = fit_one(capture_dir, mesh_path, out_dir.with_name(f"{out_dir.name}_{c.name}"),
                      dataclasses.replace(cfg, fit=fit_cfg))
        results[c.name], kinds[c.name] = res, c.kind
        h = res.summary["heldout"]
        log(f"[fit] {c.name}: held-out pooled PSNR {_db(h.get('pooled_psnr_db'))}, "
            f"worst view {_db(h.get('worst_psnr_db'))}")

    for c in plan.candidates:
        fit_candidate(c)
    names = [c.name for c in plan.candidates]
    escalate = registry.get(plan.base).escalate
    extra_reason = None
    if escalate is not None:
        extra, extra_reason = escalate({k: r.summary["heldout"].get("pooled_psnr_db") for k, r in results.items()}, cfg)
        log(f"[fit] {extra_reason}")
        for c in extra:
            try:
                fit_candidate(c)
                names.append(c.name)
            except TexstreamError as e:  # an optional candidate the capture cannot take (e.g. streamed photos)
                extra_reason += f"; {c.name} could not be fitted ({e.message}), left out"
                log(f"[fit] {c.name} could not be fitted ({e.message}): left out")
    score = {k: r.summary["heldout"].get("pooled_psnr_db") for k, r in results.items()}
    if all(v is None for v in score.values()):
        best = names[0]
        reason = f"{best} kept: no photo was held out, so no model could be judged on held-out photos"
    else:
        best = max(names, key=lambda k: -math.inf if score[k] is None else score[k])
        reason = f"{best} kept: held-out pooled PSNR " + ", ".join(f"{k} {_db(score[k])}" for k in names)
    if out_dir.exists():
        shutil.rmtree(out_dir)
    os.replace(out_dir.with_name(f"{out_dir.name}_{best}"), out_dir)
    res = results[best]
    res.output = out_dir
    res.summary["selection"] = {"chosen": best, "chosen_kind": kinds[best], "reason": reason,
                                "heldout_pooled_db": score}
    if extra_reason is not None:
        res.summary["selection"][registry.get(plan.base).escalation_key] = extra_reason
    return res
