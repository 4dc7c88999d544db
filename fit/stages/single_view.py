"""The single-view fit stage (``texstream fit CAPTURE --normals N -o MODEL``): one camera, a photo per known
light, every pixel a texel (the geometry, problem and renders: fit/common/single_view.py).

Like the mesh fit (fit/stages/stage.py), ``--model auto`` takes part in the automatic model choice
(fit/stages/choice.py: with held-out photos the reflectance model's candidates are fitted, the one that predicts
a validation split of the fitted photos best kept and the held-out photos scoring it), and a model with lobes gets the shared materials' choice and fit (fit/models/per_texel/lobes.py),
judged on a validation split of the fitted photos rendered per pixel.

Model folder: parameter maps (EXR, image resolution), seen.png, normals.exr (world-space normals of the
texels), lobes.png / uncertainty.exr / materials.png (models with lobes), model.json, trace.json,
error_vs_time.png, renders/ and fit_config.json. OpenImageIO and matplotlib are imported inside the functions
that write files.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np

from texstream.capture.capture_json import read_capture
from texstream.capture.imageio import read_image, write_image
from texstream.core.config import check_config, option
from texstream.core.devices import DEVICE_HELP, resolve_device
from texstream.core.errors import ConfigError, InputError
from texstream.core.outputs import StageResult, atomic_output_dir
from texstream.core.progress import phase, say
from texstream.fit.common.inputs import FitInputs, check_output_path, read_photos
from texstream.fit.common.model_folder import (check_model, image_metrics, pooled_psnr, render_comparisons,
                                               write_model_folder)
from texstream.fit.common.setup import run_fit_with_progress
from texstream.fit.common.single_view import (NORMAL_SPACES, build_single_view_problem, find_normal_map,
                                              load_single_view, render_single_view, shared_camera)
from texstream.fit.models import registry
from texstream.fit.models.materials import MaterialConfig
from texstream.fit.models.per_texel.fit import Lobes, fit_chosen_materials, write_lobe_maps
from texstream.fit.models.per_texel.lobes import (_materials_manifest, choose_materials, drop_unsupported_lobes,
                                                  lobes_in_use, texel_evidence, validation_split)
from texstream.fit.optim.fitter import FitConfig, FitResult
from texstream.fit.stages import choice


@dataclasses.dataclass
class SingleViewConfig:
    """Options of the single-view fit (``texstream fit CAPTURE --normals N -o MODEL``)."""

    device: str = option("auto", DEVICE_HELP)
    normal_space: str = option("opengl", "frame of the normal map: opengl (camera space, x right, y up, z towards "
                               "the viewer: DiLiGenT, most normal-map files), opencv (camera space, x right, y down, "
                               "z into the scene) or world (capture.json's world frame)", choices=NORMAL_SPACES)
    depth: float = option(1.0, "nominal camera depth (z, world units) of every texel when the capture has no "
                          "depth map; irrelevant for directional lights", min=1e-9)
    holdout_every: int = option(0, "hold out every k-th photo from the fit for evaluation (0 = none)", min=0)
    renders: int = option(4, "photos rendered beside the fitted model in renders/", min=0)
    lobe_support: float = option(0.02, "per pixel, drop the specular lobes (rho_s = 0; flagged in lobes.png and "
                                       "model.json) that lower the pixel's error on the fitted photos by less than "
                                       "this fraction: no photo saw their highlight; 0 keeps every lobe",
                                 min=0.0, max=1.0)
    choice: choice.ModelChoiceConfig = option(default_factory=choice.ModelChoiceConfig,
                                              help="the automatic model choice (--model auto)")
    materials: MaterialConfig = option(default_factory=MaterialConfig,
                                       help="shared materials: pixels whose lobe no photo constrained borrow their "
                                            "material's (fit/models/materials.py)")
    fit: FitConfig = option(default_factory=FitConfig, help="the fit", flat=True)


def fit_single_view_stage(capture_dir: str | Path, normals_path: str | Path | None, out_dir: str | Path,
                          config: SingleViewConfig | None = None, progress: bool = True) -> StageResult:
    """Fit ``config.fit``'s model per pixel of a single-view capture and write the model folder atomically; with
    ``auto``, the model choice fits the candidates the capture calls for and keeps the one that predicts a
    validation split of the fitted photos best (the summary's ``selection`` says which and why).

    Args:
        capture_dir: folder with capture.json (one camera, a light per frame), see fit/common/single_view.py.
        normals_path: the normal map; None: normals.(exr|npy|png) beside capture.json.
        out_dir: model folder to write (replaced only when the fit succeeds).
        config: options; progress: show a progress bar.
    """
    cfg = config or SingleViewConfig()
    check_config(cfg)
    cfg = dataclasses.replace(cfg, device=resolve_device(cfg.device))
    check_output_path(out_dir)
    if cfg.fit.model != choice.AUTO:
        return fit_single_view_model(capture_dir, normals_path, out_dir, cfg, progress)
    capture = read_capture(capture_dir)
    shared_camera(capture.frames, capture.root / "capture.json")  # one camera, a light per photo: before planning
    normals = normals_path if normals_path is not None else find_normal_map(capture.root)
    plan = choice.plan_choice(capture, choice.AUTO, cfg)
    say("fit", f"model auto: {plan.base} ({plan.reason})"
        + (f"; the {plan.also} model too, the best on a validation split of the fitted photos kept"
           if plan.compare else ""))
    if not plan.compare:
        return fit_single_view_model(capture_dir, normals, out_dir, dataclasses.replace(
            cfg, fit=dataclasses.replace(cfg.fit, model=plan.base)), progress)
    return choice.fit_choice(Path(capture_dir), Path(normals), Path(out_dir), cfg, plan,
                             lambda c, n, o, k: fit_single_view_model(c, n, o, k, progress))


def fit_single_view_model(capture_dir: str | Path, normals_path: str | Path | None, out_dir: str | Path,
                          cfg: SingleViewConfig, progress: bool = True) -> StageResult:
    """One model kind's single-view fit (``cfg.fit.model`` a registered reflectance kind with a per-texel table:
    each pixel is rendered under its photo's light)."""
    plugin = registry.get(cfg.fit.model)
    if not plugin.needs_light or plugin.layout_traits is None:
        raise ConfigError(f"--model {cfg.fit.model} cannot fit a single view: the per-pixel fit renders each pixel "
                          "under its photo's known light with a per-texel reflectance model",
                          fix="use a reflectance model (--model auto, lafortune or diffuse)")
    check_output_path(out_dir)
    t0 = time.perf_counter()
    capture, frames, held, geo, images, masks = load_single_view(capture_dir, normals_path, cfg)
    geo_source = normals_path if normals_path is not None else find_normal_map(capture.root)
    problem = build_single_view_problem(geo, frames, images, masks, cfg.fit, cfg.device)
    inputs = FitInputs(capture, frames, held, None, None, None, images, masks)
    t_setup = time.perf_counter() - t0
    result = run_fit_with_progress(problem, cfg.fit, progress)
    result, lobes = _lobes_and_materials(inputs, problem, result, cfg)
    lay = result.layout
    h, w = geo.covered.shape
    grid = np.tile(lay.defaults().astype(np.float32), (h * w, 1))
    grid[problem.texels.grid_index] = result.params
    grid = grid.reshape(h, w, -1)
    check_model(grid, lay)  # before rendering it
    seen = np.zeros(h * w, bool)
    seen[problem.texels.grid_index] = result.samples > 0
    seen = seen.reshape(h, w)
    # every held-out photo is scored (the model choice reads them pooled), the first `renders` drawn
    show = held if held else frames[: max(cfg.renders, 0)]
    photos = [read_image(capture.image_path(f), channels=3) for f in show]
    for f, photo in zip(show, photos, strict=True):
        if photo.shape[:2] != (h, w):
            raise InputError(f"photo is {photo.shape[1]}x{photo.shape[0]} but the normal map is {w}x{h}",
                             capture.image_path(f), "give photos and normal map of one size")

    def render(f):  # texels no photo saw keep defaults: flagged, not scored
        return render_single_view(problem, result.params, lay, f), capture.within_mask(f, seen.copy())

    with atomic_output_dir(out_dir) as tmp:
        write_image(tmp / "normals.exr", np.where(geo.covered[..., None], geo.normal, 0.0).astype(np.float32))
        evals = render_comparisons(tmp / "renders", show, photos, held, render, images=max(cfg.renders, 0))
        write_lobe_maps(tmp, problem.texels, problem, result, lobes)
        last = result.trace[-1]
        manifest = {"geometry": {"type": "normal_map", "normals": "normals.exr", "normal_space_in": cfg.normal_space,
                                 "normals_out": "world", "source": str(geo_source)},
                    "image": {"width": w, "height": h, "texels": int(problem.n),
                              "unseen_texels": int((result.samples == 0).sum()),
                              "lobes_dropped": int(lobes.dropped.sum()),
                              "texels_with_lobe": lobes_in_use(result.params, lay, result.samples > 0),
                              "lobe_support": cfg.lobe_support},
                    "photos": {"fitted": len(frames), "held_out": len(held)},
                    "final": {k: last[k] for k in ("iteration", "time_s", "objective", "psnr_db", "ape_percent")},
                    "materials": _materials_manifest(lobes.info, lobes.evidence, cfg.materials),
                    "setup_s": t_setup, "passes": result.passes, "device": cfg.device, "render_eval": evals,
                    "heldout": pooled_psnr([e for e in evals if e["held_out"]]),
                    "units": plugin.units}
        write_model_folder(tmp, grid, lay, seen, result.trace,
                           f"single-view {lay.kind} fit, {cfg.fit.optimizer}, {cfg.device}", manifest, cfg)
    return StageResult(Path(out_dir), {"psnr_db": last["psnr_db"], "iterations": last["iteration"],
                                       "time_s": last["time_s"], "texels": problem.n, "photos": len(frames),
                                       "unseen_texels": int((result.samples == 0).sum()), "render_eval": evals,
                                       "heldout": manifest["heldout"], "materials": manifest["materials"]})


def _lobes_and_materials(inputs: FitInputs, problem, result: FitResult, cfg: SingleViewConfig):
    """(result, Lobes): for a model with lobes and materials not off, the shared materials' choice (on a
    validation split of the fitted photos, rendered per pixel) and, when a materials model wins, its fit;
    otherwise the per-pixel lobes no photo supports dropped (a model without lobes passes unchanged). As the
    mesh fit's phase (fit/models/per_texel/fit.py) without the traced polish: a single view has no mesh to
    trace taps to."""
    if not (result.layout.n_lobes and cfg.materials.mode != "off"):
        params, dropped = drop_unsupported_lobes(problem, result, cfg.lobe_support)
        return dataclasses.replace(result, params=params), Lobes(None, None, None, dropped)
    with phase("fit", "materials: per-pixel or shared lobes, judged on a validation split of the fitted photos"):
        _, val = validation_split(len(inputs.frames), cfg.materials.validation_every)
        picked = choose_materials(inputs, problem, cfg, score_views=pixel_view_scores(inputs, val))
        evidence = texel_evidence(problem, result, cfg.materials)
    info = {"mode": cfg.materials.mode, "traced": False, **picked}
    if picked["chosen"] == "per-texel":
        params, dropped = drop_unsupported_lobes(problem, result, cfg.lobe_support)
        return dataclasses.replace(result, params=params), Lobes(info, evidence, None, dropped)
    return fit_chosen_materials(problem, result, evidence, info, cfg)


def pixel_view_scores(inputs: FitInputs, val: list[int]):
    """The materials choice's scorer for a single view: ``score_views(params, result, sub_problem)`` -> the PSNR
    of each validation photo ``val`` (indices of ``inputs.frames``) against the per-pixel render of compact
    ``params``, over the pixels the sub-fit's photos saw and the photo's mask (as the stage scores its renders)."""
    frames = [inputs.frames[i] for i in val]
    images, masks = read_photos(inputs.images, inputs.masks, val)

    def score_views(params, result, sub) -> list[float]:
        tx = sub.texels
        seen = np.zeros(tx.height * tx.width, bool)
        seen[tx.grid_index] = result.samples > 0
        seen = seen.reshape(tx.height, tx.width)
        return [image_metrics(render_single_view(sub, params, result.layout, f), photo, seen & mask)["psnr_db"]
                for f, photo, mask in zip(frames, images, masks, strict=True)]

    return score_views
