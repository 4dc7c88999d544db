"""The fit and eval stages over folders (``texstream fit`` / ``texstream eval``).

fit: a posed capture with lights + a mesh with UVs (or an atlas folder with ``mesh.obj`` and
``bake.npz``, e.g. ``texstream atlas`` output or a synthetic set's ``ground_truth/``) -> a model
folder: mesh.obj, bake.npz, parameter maps (EXR), seen.png (texels no photo saw keep their
default values and are flagged here), model.json, trace.json, error_vs_time.png, renders/ (fitted
render beside each of a few photos) and fit_config.json.

The fit itself is the model plugin's (fit/models/registry.py); ``--model auto`` goes through the model choice
(fit/stages/choice.py). Heavy packages (OpenImageIO, through capture.imageio) load inside the functions that
read and write files.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np

from texstream.capture.capture_json import read_capture
from texstream.capture.imageio import read_image
from texstream.core.errors import ConfigError, InputError
from texstream.core.checkpoint import inputs_key
from texstream.core.config import check_config, config_to_dict, option
from texstream.core.devices import DEVICE_HELP, resolve_device
from texstream.core.outputs import StageResult, write_json_atomic
from texstream.core.progress import bar, say

from texstream.fit.kernels.build_notice import mark_kernels_built
from texstream.fit.kernels.overloads import declare_precision
from texstream.fit.stream.config import resolve_accumulate
from texstream.fit.optim.fitter import FitConfig
from texstream.fit.models import registry
from texstream.fit.stages import choice
from texstream.fit.stages.prewarm import (build_kernels_ahead, build_kernels_if_cold, declare_group_overloads,
                                          kernel_group)
from texstream.fit.models.materials import MaterialConfig
from texstream.fit.common.shading_normals import NormalsConfig
from texstream.fit.common.inputs import SharedPhotoSet, check_output_path, split_holdout
from texstream.fit.common.model_folder import check_render, image_metrics, json_safe, pooled_psnr
# the shared helpers of a fit, where tests and benchmarks import them beside the stages
from texstream.fit.common.inputs import load_geometry, load_photos, photo_files  # noqa: F401
from texstream.fit.common.setup import (build_problem, fit_synthetic, heldout_psnr, load_model,  # noqa: F401
                                        params_to_grid, render_model)
from texstream.fit.common.setup import fit_inputs_signature
from texstream.fit.models.per_texel.lobes import drop_unsupported_lobes, lobe_shape_report  # noqa: F401
from texstream.fit.stream.photo_stream import loaders_closed_after


@dataclasses.dataclass
class FitStageConfig:
    """Options of ``texstream fit`` around the numerical FitConfig."""

    device: str = option("auto", DEVICE_HELP)
    texture_size: int = option(256, "atlas side in texels when the mesh has UVs but no bake; 0: automatic, the "
                                    "power of two whose texels are about texel_pixels of the photos' pixels wide; at least 8, the "
                                    "smallest the atlas packs (geometry/atlas.py)",
                                    min=8, max=16384, also=(0,))
    texel_pixels: float = option(3.0, "texture_size 0: the texel width to aim at, in photo pixels (texels narrower "
                                      "than a pixel or two share their pixels with their neighbours and fit the "
                                      "photos' filtered highlights as broad, weak lobes that new views contradict; "
                                      "wider ones lose detail: docs/accuracy.md)", min=0.25, max=1024.0)
    photo_level: int = option(-1, "the pyramid level the fitted photos stream at (L: 2^L x 2^L pixel boxes "
                                  "averaged): -1 automatic, the coarsest whose texels stay at least 2 of its "
                                  "pixels wide (fit/common/photo_levels.py); 0 the photos as they are. Held-out "
                                  "views are scored at full resolution", min=-1, max=8)
    holdout_every: int = option(0, "hold out every k-th photo from the fit for evaluation (0 = none)", min=0)
    renders: int = option(4, "photos rendered beside the fitted model in renders/", min=0)
    unseen: str = option("nearest", "texels no photo saw: nearest (the value of the nearest seen texel on the "
                                    "surface, as texture bakers fill; flagged in seen.png) or default (the "
                                    "model's default values)", choices=("nearest", "default"))
    lobe_support: float = option(0.02, "per texel, drop the specular lobes (rho_s = 0; flagged in lobes.png and "
                                       "model.json) that lower the texel's error on the fitted photos by less than "
                                       "this fraction: no photo saw their highlight, so in new views they only guess "
                                       "it; with two lobes the second is also tested on its own; 0 keeps every lobe",
                                 min=0.0, max=1.0)
    traced_polish: int = option(5, "Levenberg-Marquardt iterations that end a fit with specular lobes with each "
                                    "filtered tap's pixel ray traced to the mesh (stream.tap_geometry mesh, the "
                                    "renderer's surface at every tap) when the fit ran with plane taps: a highlight "
                                    "narrower than a pixel is then fitted as the photos filtered it, not as a "
                                    "broad, weak lobe new views contradict (docs/accuracy.md); a traced pass costs "
                                    "~7-20x a plane one; 0: off", min=0)
    traced_polish_rel_tol: float = option(1e-5, "the traced polish stops after an iteration that lowers its objective "
                                                "by less than this, relative (tested every iteration: on the full "
                                                "ornament the polish settles after its first iteration, 2e-6 from the "
                                                "second on, while on the dense ornament each iteration still gains "
                                                "1-8%); 0: every iteration runs", min=0.0, max=1.0)
    traced_materials: bool = option(False, "with the traced polish and shared materials chosen: polish the "
                                            "per-texel fit on traced taps first, and find the materials' evidence, "
                                            "contradictions and fit on traced taps too. It helps texels narrower "
                                            "than a pixel that saw narrow highlights; the constrained test on traced "
                                            "taps is confirmed at the materials' lobes, yet a few texels that never "
                                            "saw their highlight still pass it and keep wrong lobes "
                                            "(docs/accuracy.md): off by default")
    checkpoint: bool = option(True, "Levenberg-Marquardt fits keep a checkpoint beside the output (every sync_every "
                                    "iterations); a rerun after Ctrl-C or a killed process resumes from it to the "
                                    "same result as an uninterrupted fit")
    skip_bad_photos: bool = option(False, "leave out photos that cannot be read (corrupt, truncated, wrong size, "
                                          "NaN values) instead of failing: each is printed and listed in "
                                          "model.json's photos.skipped (every photo is decoded once at set-up, "
                                          "before the fit; each bad one costs the set-up again)")
    min_seen_fraction: float = option(0.01, "fail before fitting when fewer than this fraction of the atlas's texels "
                                            "is seen by any photo (the mesh faces away or is in another frame)",
                                      min=0.0, max=1.0)
    choice: choice.ModelChoiceConfig = option(default_factory=choice.ModelChoiceConfig,
                                              help="the automatic model choice (--model auto)")
    shading_normals: NormalsConfig = option(default_factory=NormalsConfig,
                                            help="shading normals fitted to the photos under known lights "
                                                 "(fit/common/shading_normals.py)")
    materials: MaterialConfig = option(default_factory=MaterialConfig,
                                       help="shared materials: texels whose lobe no photo constrained borrow their "
                                            "material's (fit/models/materials.py)")
    fit: FitConfig = option(default_factory=FitConfig, help="the fit", flat=True)




def fit_stage(capture_dir: str | Path, mesh_path: str | Path, out_dir: str | Path,
              config: FitStageConfig | None = None, progress: bool = True) -> StageResult:
    """Fit the appearance model of ``config.fit.model`` to a capture and write the model folder atomically; with
    ``auto``, the model choice (fit/stages/choice.py) fits the candidates the capture calls for and keeps the
    one that predicts a validation split of the fitted photos best (its summary's ``selection`` says which and
    why; the held-out photos only score it)."""
    try:
        return _fit_stage(capture_dir, mesh_path, out_dir, config or FitStageConfig(), progress)
    finally:
        SharedPhotoSet.release()  # the candidates' shared photos and maps, freed with the stage


def _fit_stage(capture_dir, mesh_path, out_dir, cfg: FitStageConfig, progress: bool) -> StageResult:
    check_config(cfg)
    check_output_path(out_dir)
    cfg = dataclasses.replace(cfg, device=resolve_device(cfg.device))  # the model.json names the device used
    if cfg.fit.model != choice.AUTO:
        registry.get(cfg.fit.model)  # an unknown kind fails before any work
        return fit_model(capture_dir, mesh_path, out_dir, cfg, progress)

    capture = read_capture(capture_dir)
    plan = choice.plan_choice(capture, choice.AUTO, cfg)
    say("fit", f"model auto: {plan.base} ({plan.reason})"
        + (f"; the {plan.also} model too, the best on a validation split of the fitted photos kept"
           if plan.compare else ""))
    if not plan.compare:
        return fit_model(capture_dir, mesh_path, out_dir, dataclasses.replace(cfg, fit=dataclasses.replace(
            cfg.fit, model=plan.base)), progress)
    res = choice.fit_choice(Path(capture_dir), Path(mesh_path), Path(out_dir), cfg, plan,
                            lambda c, m, o, k: fit_candidate(c, m, o, k, progress))
    forget_candidates(out_dir)
    return res


def fit_model(capture_dir: str | Path, mesh_path: str | Path, out_dir: str | Path, cfg: FitStageConfig,
              progress: bool = True) -> StageResult:
    """One model kind's fit, by its plugin (``cfg.fit.model`` a registered kind)."""
    plugin = registry.get(cfg.fit.model)
    check_output_path(out_dir)
    cfg = dataclasses.replace(cfg, device=resolve_device(cfg.device))
    precision = compute_precision(capture_dir, cfg)
    declare_precision(precision)  # before any build or launch: the same modules cold and warm
    declare_group_overloads(cfg.fit.model)
    build_kernels_if_cold("fit", cfg.device, cfg.fit.model, precision)
    with loaders_closed_after():  # photos streamed from disk: their loaders' threads end with the stage
        result = plugin.fit(registry.FitRequest(Path(capture_dir), Path(mesh_path), Path(out_dir), cfg, progress))
    mark_kernels_built(cfg.device, precision, kernel_group(cfg.fit.model))
    return result


def fit_kernels_ahead(capture_dir: str | Path, cfg: FitStageConfig, kind: str, now: list = (),
                      later_stages: bool = True) -> None:
    """Before a run's mesh, atlas and refinement: on a GPU with a cold kernel cache, ``now`` (the Warp modules of
    the next stage) built at once, then the modules a fit of ``kind`` (its group's, fit/stages/prewarm.py) launches
    start compiling on a thread of their own (with the atlas's and refinement's when ``later_stages``); the fit
    waits for them. The fit's precision and group overloads are declared here, as :func:`fit_model` declares them."""
    device = resolve_device(cfg.device)
    if not str(device).startswith("cuda"):
        return
    precision = compute_precision(capture_dir, cfg)
    declare_precision(precision)
    declare_group_overloads(kind)
    build_kernels_ahead("fit", device, kind, precision, now, later_stages)


def compute_precision(capture_dir: str | Path, cfg: FitStageConfig) -> str:
    """The precision the fit's passes accumulate in (``stream.accumulate``; auto: by the capture's photo count, an
    upper bound of the fitted photos', so a fit near the threshold may declare float64 it does not use)."""
    try:  # a capture.json folder, a nerfstudio transforms.json or a file: as the fit reads it
        frames = read_capture(capture_dir).frames
    except InputError:  # the fit's own reading says what is wrong with it, in one line
        frames = []
    return resolve_accumulate(cfg.fit.stream.accumulate, len(frames))


CANDIDATE_STAMP = ".texstream_candidate.json"
"""in a candidate's model folder while its choice is unfinished: the key of its inputs and options, its summary"""


def forget_candidates(out_dir: str | Path) -> None:
    """After the model choice into ``out_dir`` finished: its candidates' stamps go, so only an interrupted choice
    keeps candidates (a later fit, with code or data changed in ways the key does not see, fits them all)."""
    out = Path(out_dir)
    for stamp in [out / CANDIDATE_STAMP, *out.parent.glob(f"{out.name}_*/{CANDIDATE_STAMP}")]:
        stamp.unlink(missing_ok=True)


def fit_candidate(capture_dir: str | Path, mesh_path: str | Path, out_dir: str | Path, cfg: FitStageConfig,
                  progress: bool = True) -> StageResult:
    """:func:`fit_model` of one candidate of the model choice (``fit_choice``'s ``fit_one``): a candidate folder
    that a choice interrupted later (Ctrl-C, a killed process) finished with the same inputs and options is kept,
    with a line, so the rerun fits only the candidates not finished. The key: what the fit reads
    (:func:`~texstream.fit.common.setup.fit_inputs_signature`), the options, the device."""
    key = inputs_key("fit candidate", fit_inputs_signature(capture_dir, mesh_path), config_to_dict(cfg),
                     resolve_device(cfg.device))
    stamp = Path(out_dir) / CANDIDATE_STAMP
    try:
        done = json.loads(stamp.read_text())
    except (OSError, ValueError):
        done = None
    if isinstance(done, dict) and done.get("key") == key:
        say("fit", f"{cfg.fit.model}: {out_dir} was fitted before with the same inputs and options (by an "
                   "interrupted run, or by the run's judgement of its refinement): kept")
        return StageResult(Path(out_dir), done["summary"])
    res = fit_model(capture_dir, mesh_path, out_dir, cfg, progress)
    write_json_atomic(stamp, {"key": key, "summary": json.loads(json.dumps(json_safe(res.summary), default=str))})
    return res


def eval_stage(model_dir: str | Path, capture_dir: str | Path, device: str = "cpu",
               out_json: str | Path | None = None, holdout_every: int = 0) -> StageResult:
    """Render the model for the frames of a capture (all, or the held-out ones of the fit's split with
    ``holdout_every``); PSNR / APE on foreground pixels, pooled over the views and the worst view."""
    if holdout_every < 0:
        raise ConfigError(f"--holdout-every {holdout_every} is negative",
                          fix="use 0 (every frame) or k >= 1 (the frames a fit with that --holdout-every held out)")
    render = registry.load_model_folder(model_dir).renderer(resolve_device(device))
    capture = read_capture(capture_dir)
    frames = split_holdout(capture.frames, holdout_every)[1] if holdout_every > 0 else capture.frames
    if not frames:
        raise InputError(f"no frame is held out with --holdout-every {holdout_every}", Path(capture_dir) / "capture.json",
                         "use a smaller --holdout-every, or 0 for every frame")

    rows = []
    for f in bar(frames, "eval", unit="view"):
        photo = read_image(capture.image_path(f), channels=3, response=capture.response)
        rend, rmask = render(f)
        check_render(rend, f.file_path)
        m = capture.within_mask(f, rmask.astype(bool))
        rows.append({"frame": f.file_path, **image_metrics(rend, photo, m)})
    mse_all = [10 ** (-r["psnr_db"] / 10) for r in rows if r["pixels"]]
    pooled = pooled_psnr(rows)
    summary = {"frames": len(rows), "holdout_every": holdout_every,
               "mean_psnr_db": float(np.mean([r["psnr_db"] for r in rows if r["pixels"]])),
               "psnr_of_mean_mse_db": float(-10 * np.log10(np.mean(mse_all))) if mse_all else float("nan"),
               "pooled_psnr_db": pooled["pooled_psnr_db"], "worst_psnr_db": pooled["worst_psnr_db"],
               "worst_view": pooled.get("worst_view"),
               "mean_ape_percent": float(np.mean([r["ape_percent"] for r in rows if r["pixels"]])), "per_frame": rows}
    out = Path(out_json) if out_json else Path(model_dir) / f"eval_{Path(capture_dir).resolve().name}.json"
    write_json_atomic(out, summary)
    return StageResult(out, {k: v for k, v in summary.items() if k != "per_frame"})
