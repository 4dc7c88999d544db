"""Whether a run hands the refinement's cameras and mesh to the fit, under known lights: judged by the fit.

The refinement (geometry/refine.py) compares the photos with one shared texture under the light's Lambertian
shading; it has no specular lobe and no room light. Its own residual can therefore fall while the geometry gets
worse for the model the fit will make: on the synthetic glossy flash capture (issue 39, photos only) it fell
0.01129 -> 0.0108 while the Lafortune fit on the refined geometry held out 32.48 dB against 34.15 dB on the
registered one (the refinement had followed highlights that move with the camera-mounted flash). Under one fixed
unknown lighting its shared texture is the radiance model itself and its residual is the right judge; under known
lights the run asks the fit: the cheapest reflectance candidate (diffuse, the model choice's first), with the
fit's own options, on a validation split of the fitted photos (every ``materials.validation_every``-th, as the
model choice splits them), once on the registered cameras and mesh and once on the refined ones. The refined
geometry goes on only when its validation pooled PSNR is higher. The held-out photos play no part.

Measured on that capture (photos only, 2-core CPU, docs/real-data.md): diffuse validation 35.47 dB registered
against 35.32 dB refined (the Lafortune validation fits agree: 38.35 against 36.02 dB), about 10 s a fit.

The two fits are the model choice's own fit of its diffuse candidate (fit/stages/choice.py: the same options,
``fit_candidate`` with its stamp), so the kept side's is handed to the choice (:func:`hand_to_choice`), which
then does not fit it again: the judgement costs one validation fit, not two.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
import time
from pathlib import Path

from texstream.capture.capture_json import split_holdout
from texstream.core.errors import TexstreamError
from texstream.fit.common.inputs import SharedPhotoSet
from texstream.fit.stages.choice import VALIDATION_SUFFIX
from texstream.fit.stages.stage import fit_candidate

JUDGE_WORK = "refine_judged"
"""the run's folder of the judgement's two validation fits (resumable from their stamps; removed once handed on)"""

JUDGED_FILE = "refine_judged.json"
"""the run's record of its last judgement and the key of its inputs (``texstream run`` reuses it while they hold)"""

JUDGE_MODEL = "diffuse"
"""the candidate the judgement fits: the model choice's first under known lights, and its cheapest"""


def judged_by_fit(capture, refine_cfg) -> str | None:
    """None when the refinement should be judged by the fit (``refine.judge`` auto, every photo with a known light,
    enough fitted photos for a validation split), else why not."""
    if refine_cfg.judge == "off":
        return "refine judge off"
    if not capture.frames or any(f.light is None for f in capture.frames):
        return "no known light: the refinement's shared texture is the radiance model, its residual decides"
    fitted, _ = split_holdout(list(capture.frames), refine_cfg.holdout_every)
    return None if len(fitted) >= 6 else f"{len(fitted)} fitted photos: too few for a validation split"


def judge_config(fit_cfg):
    """The config of the judgement's fits: the model choice's validation fit of its first candidate
    (fit/stages/choice.py ``fit_choice``'s ``config(c, True)`` for :data:`JUDGE_MODEL`, no candidate judged before
    it), so the choice can take the kept one as its own."""
    return dataclasses.replace(fit_cfg, renders=0, fit=dataclasses.replace(fit_cfg.fit, model=JUDGE_MODEL),
                               choice=dataclasses.replace(fit_cfg.choice, validation_fit=True, beat_db=0.0))


def judge_refinement(registered: tuple[Path, Path], refined: tuple[Path, Path], work: Path, fit_cfg,
                     log=lambda m: None) -> tuple[bool, dict]:
    """(whether the refined cameras and mesh go on to the fit, the judgement's record). ``registered`` and
    ``refined`` are (capture folder, geometry) pairs; ``fit_cfg`` the run's fit stage config (its device,
    ambient and materials options are kept; the model is :data:`JUDGE_MODEL`, fitted on the validation split and
    scored there, no renders: :func:`judge_config`). The validation fits go to ``work/registered`` and
    ``work/refined``; the caller hands the kept one to the model choice (:func:`hand_to_choice`) and removes
    ``work``."""
    cfg = judge_config(fit_cfg)
    scores, t0 = {}, time.perf_counter()
    for name, (capture_dir, geometry) in (("registered", registered), ("refined", refined)):
        try:
            held = fit_candidate(capture_dir, geometry, Path(work) / name, cfg, progress=False).summary.get("heldout")
        except TexstreamError as e:  # a side the fit cannot take (no texel seen, ...) loses, with the reason
            scores[name] = {"pooled_psnr_db": None, "error": e.message}
            continue
        held = held or {}
        scores[name] = {"pooled_psnr_db": held.get("pooled_psnr_db"), "worst_psnr_db": held.get("worst_psnr_db"),
                        "views": held.get("views")}
    reg, ref = scores["registered"]["pooled_psnr_db"], scores["refined"]["pooled_psnr_db"]
    failed = [name for name in ("refined", "registered") if "error" in scores[name]]
    if len(failed) == 1 and (ref if failed[0] == "registered" else reg) is not None:  # one side failed, one scored
        kept, why = failed[0] == "registered", (f"the {JUDGE_MODEL} fit could not take the {failed[0]} geometry "
                                                f"({scores[failed[0]]['error']})")
    elif reg is None or ref is None:
        kept, why = True, "no validation photo was scored: the refinement's own residual decides"
    elif ref > reg:
        kept, why = True, (f"the {JUDGE_MODEL} fit's validation photos: {ref:.2f} dB refined against {reg:.2f} "
                           "registered")
    else:
        kept, why = False, (f"the {JUDGE_MODEL} fit predicts its validation photos no better on the refined cameras and "
                            f"mesh ({ref:.2f} dB against {reg:.2f} registered): the registered ones are kept")
        SharedPhotoSet.release()  # the photos the last fit shared were the refined side's, which no fit reads now
    log(f"[refine] judged by the fit: {why}")
    return kept, {"model": JUDGE_MODEL, "validation": scores, "kept": kept, "why": why,
                  "seconds": round(time.perf_counter() - t0, 2)}


def choice_folder(model_dir: Path) -> Path:
    """Where the model choice writing ``model_dir`` puts its :data:`JUDGE_MODEL` candidate's validation fit
    (fit/stages/choice.py ``fit_choice``'s ``folder(c, VALIDATION_SUFFIX)``)."""
    return model_dir.with_name(f"{model_dir.name}_{JUDGE_MODEL}{VALIDATION_SUFFIX}")


def hand_to_choice(work: Path, kept: bool, model_dir: Path) -> None:
    """The kept side's validation fit (its stamp with it) moved to where the model choice writing ``model_dir``
    looks for its first candidate's (:func:`choice_folder`), and ``work`` removed: the choice finds it finished with
    the same inputs and options and does not fit it again. The caller removes it when no choice came to take it."""
    target = choice_folder(model_dir)
    shutil.rmtree(target, ignore_errors=True)
    source = Path(work) / ("refined" if kept else "registered")
    if source.is_dir():
        source.rename(target)
    shutil.rmtree(work, ignore_errors=True)
