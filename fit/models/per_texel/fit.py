"""The fit of a per-texel model (Lafortune, diffuse, radiance, view-dependent radiance): inputs, set-up, the
streaming fit, the lobes and materials where the model has lobes, held-out renders and the model folder.

One function per phase; :func:`fit` (the plugins' ``fit``) runs them in order. Heavy packages (OpenImageIO in
capture.imageio, pymeshlab in the mesh writer) are imported inside the functions that write files."""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import shutil
import time
from pathlib import Path

import numpy as np

from texstream.capture.imageio import read_mask, write_image
from texstream.core.config import config_to_dict
from texstream.core.outputs import StageResult, atomic_output_dir
from texstream.core.progress import phase, say
from texstream.fit.common import model_folder, shading_normals
from texstream.fit.common.inputs import FitInputs, load_fit_inputs, load_photos, set_up_skipping_bad_photos
from texstream.fit.common.model_folder import (bound_report, check_model, pooled_psnr, render_comparisons, trace_plot,
                                               write_model_folder)
from texstream.fit.common.numerics import numerics_warnings
from texstream.fit.common.setup import (Checkpoint, ModelRenders, fill_unlit_reflectance, fill_unseen_texels,
                                        fit_inputs_signature, has_unlit_photos, params_to_grid, run_fit_with_progress,
                                        unseen_sources)
from texstream.fit.common.highlights import highlight_image, highlight_masks, highlight_report
from texstream.fit.models import registry
from texstream.fit.models.per_texel.ambient import resolve_ambient
from texstream.fit.models.per_texel.lobes import (_materials_manifest, average_seams_in_bounds, choose_materials,
                                                  confirm_at_material_lobes, drop_unsupported_lobes, fit_with_materials,
                                                  lobe_shape_report, lobes_in_use, texel_evidence, traced_polish,
                                                  traced_polish_applies, traced_problem)
from texstream.fit.multi.cpu_threads import cpu_threads, threaded_config
from texstream.fit.multi.tiles import run_tiled_fit_with_progress, tiled
from texstream.fit.optim.fitter import resumable
from texstream.geometry.mesh_io import save_mesh

MATERIAL_PALETTE = np.array([[0.9, 0.6, 0.1], [0.1, 0.6, 0.2], [0.8, 0.8, 0.8], [0.2, 0.3, 0.9],
                             [0.8, 0.1, 0.1], [0.6, 0.2, 0.8], [0.1, 0.8, 0.8], [0.5, 0.4, 0.2]], np.float32)
"""materials.png's colour per material label"""


VALIDATION_SEAMS = ("a validation fit of the model choice: its seams are left as fitted (averaging them, an "
                    "active set of sparse factorisations, took 4-8 s of CPU time in each of the temple's "
                    "candidates; without it radiance's validation pooled PSNR moved by -0.002 dB, view_radiance's "
                    "by +0.03 dB)")
"""why a validation fit's seams are not averaged (model.json's ``seams``)"""


@dataclasses.dataclass
class Lobes:
    """What the lobes phase decided: the materials choice (None: no lobes, or materials off), the texels'
    evidence, the borrowed materials (info, labels, result; None: per-texel lobes) and the texels whose lobes
    were dropped."""

    info: dict | None
    evidence: object
    borrowed: tuple | None
    dropped: np.ndarray


def fit(request) -> StageResult:
    """A per-texel model's fit (registry.FitRequest): a child process draws the error-against-time plot while
    the photos are read and fitted (it imports matplotlib meanwhile)."""
    plotter = model_folder.start_plotter()  # through the module: tests replace it there
    try:
        return _fit_per_texel_model(request.capture_dir, request.mesh_path, request.out_dir, request.cfg,
                                    request.progress, plotter)
    finally:
        model_folder.stop_plotter(plotter)


def _fit_per_texel_model(capture_dir: str | Path, mesh_path: str | Path, out_dir: str | Path, cfg,
                         progress: bool, plotter=None) -> StageResult:
    """The phases of a per-texel fit (``cfg``: the fit stage's FitStageConfig); ``plotter`` draws the
    error-against-time plot (:func:`~texstream.fit.common.model_folder.start_plotter`; None: a child started at
    the end does)."""
    t0 = time.perf_counter()
    with phase("fit", f"{cfg.fit.model}: reading the photos and setting up the texels"):
        inputs = load_fit_inputs(capture_dir, mesh_path, cfg)
        t_inputs = time.perf_counter() - t0
        problem, seen_before, start, skipped = set_up_skipping_bad_photos(inputs, cfg, capture_dir)
    problem, start, cfg, ambient = resolve_ambient(inputs, problem, start, cfg)  # auto: by a validation split
    t_setup = time.perf_counter() - t0
    ckpt, resume = _checkpoint(capture_dir, mesh_path, out_dir, cfg, problem)
    choice, p0 = _choice_before_fit(inputs, problem, cfg, start, resume)
    t_choice = time.perf_counter() - t0 - t_setup
    result, tiles_report = _core_fit(problem, start_fit_config(cfg, choice, p0), start, progress, ckpt, resume, p0)
    result, inputs, normals = _shading_normals(inputs, problem, result, cfg, start)
    t_loop = time.perf_counter()
    result, lobes = _lobes_and_materials(inputs, problem, result, cfg, choice)
    masks = lit_masks(problem, result)
    grid, filled, seams_info = _model_grid(inputs, problem, result, cfg, masks)
    t_fitted = time.perf_counter()
    title = f"{result.layout.kind} fit, {cfg.fit.optimizer}, {cfg.device}"
    # the model choice's validation fit is judged by its scores and then removed: model.json alone (its maps, mesh,
    # bake and plot were 2-3 s of each of the temple's candidates)
    scores_only = cfg.choice.validation_fit
    with (atomic_output_dir(out_dir) as tmp, phase("fit", f"{cfg.fit.model}: held-out renders and the model folder"),
          contextlib.nullcontext() if scores_only else trace_plot(tmp, result.trace, title, plotter) as plot):
        evals = _write_geometry_and_renders(tmp, inputs, mesh_path, grid, result.layout, cfg, scores_only,
                                            bake_changed=bool(normals and normals.get("rounds_kept")))
        seen = np.zeros(inputs.bake.height * inputs.bake.width, bool)
        seen[problem.texels.grid_index] = result.samples > 0
        if not scores_only:
            write_lobe_maps(tmp, inputs.bake, problem, result, lobes)
        # a validation fit's counts too: the model choice leaves the lobes out where the diffuse fit saw no highlight
        highlights = write_highlights(tmp, inputs.bake, problem, result, lobes, image=not scores_only, masks=masks)
        timings = {"inputs": t_inputs, "setup": t_setup - t_inputs, "choice_before_fit": t_choice,
                   "fit": t_loop - t0 - t_setup - t_choice, "after_fit": t_fitted - t_loop,
                   "renders": time.perf_counter() - t_fitted}
        manifest = _manifest(inputs, problem, result, lobes, cfg, evals,
                             {"seen_before": seen_before, "filled": filled[0], "unlit_filled": filled[1],
                              "skipped": skipped, "tiles": tiles_report,
                              "seams": seams_info, "setup_s": t_setup, "timings_s": timings, "ambient": ambient,
                              "highlights": highlights, "scores_only": scores_only, "normals": normals})
        write_model_folder(tmp, grid, result.layout, seen.reshape(inputs.bake.height, inputs.bake.width), result.trace,
                           title, manifest, cfg, plot=plot, maps=not scores_only)
    if ckpt is not None:
        ckpt.remove()
    problem.photos.wait_for_cache()  # a photo cache written in the background is complete for the next fit
    last = result.trace[-1]
    return StageResult(Path(out_dir), {"psnr_db": last["psnr_db"], "iterations": last["iteration"],
                                       "time_s": last["time_s"], "texels": problem.n, "photos": len(inputs.frames),
                                       "resumed_from": None if resume is None else int(resume["iteration"]),
                                       "skipped_photos": [p["file"] for p in skipped],
                                       "render_eval": evals, "warnings": manifest["warnings"],
                                       "heldout": manifest["heldout"], "materials": manifest["materials"],
                                       "highlights": highlights})


def _checkpoint(capture_dir, mesh_path, out_dir, cfg, problem) -> tuple[Checkpoint | None, dict | None]:
    """The fit's checkpoint (LM fits, untiled or tiles on threads) and the state it holds from an interrupted run."""
    if not (cfg.checkpoint and resumable(cfg.fit) and cfg.fit.stream.tile_backend != "ray"):
        return None, None
    capture_json = Path(capture_dir) / "capture.json"
    ckpt = Checkpoint(out_dir, {"capture": str(Path(capture_dir).resolve()), "mesh": str(Path(mesh_path).resolve()),
                                "config": config_to_dict(cfg), "texels": problem.n,
                                "files": fit_inputs_signature(capture_dir, mesh_path),
                                "capture_mtime": capture_json.stat().st_mtime_ns if capture_json.exists() else 0})
    return ckpt, ckpt.load()


def _choice_before_fit(inputs: FitInputs, problem, cfg, start, resume) -> tuple[dict | None, np.ndarray | None]:
    """(the materials choice, the fit's starting parameters) where the choice runs before the fit of every
    fitted photo (``materials.fit_from_validation``): that fit then starts from the validation split's
    per-texel fit, which saw 7/8 of its photos, on every texel the split saw (the fit's own guess ``start`` on
    the rest), and needs a few iterations instead of a fit's worth. The choice never reads the full fit, so it
    is the same either way. (None, None) where the choice runs after the fit (no lobes, materials off, tiles,
    a resumed checkpoint, a layout with the ambient term: from the split's fit the flash-only sphere's fit stopped
    on a plateau, 50.5 dB held out against 53.9 dB from its initial guess, benchmarks/ambient_term.py); (choice,
    None) where the photos were too few to split."""
    m = cfg.materials
    if not (m.fit_from_validation and problem.layout.n_lobes and m.mode != "off" and resume is None
            and not tiled(cfg.fit) and not problem.layout.extra_term):
        return None, None
    kept = {}
    with phase("fit", "materials: per-texel or shared lobes, judged on a validation split of the fitted photos"):
        choice = choose_materials(inputs, problem, cfg, on_validation_fit=lambda res: kept.update(fit=res))
    if "fit" not in kept:
        return choice, None
    split = kept["fit"]
    return choice, np.where((split.samples > 0)[:, None], split.params, start.params.numpy())


def _shading_normals(inputs: FitInputs, problem, result, cfg, start):
    """(result, inputs, report or None): the shading normals fitted to the fitted photos where ``cfg.shading_normals``
    asks and the model is lit (fit/common/shading_normals.py); the inputs' mesh and bake then carry them (the renders,
    the model folder and the materials' validation scores use them), and the refits' iterations are appended to
    the trace (stage "normals")."""
    ncfg = cfg.shading_normals
    ok, why = shading_normals.applies(cfg, problem, inputs.frames)
    if not ok:
        return result, inputs, {"mode": "on", "applied": False, "why": why} if ncfg.mode == "on" else None
    refit_cfg = dataclasses.replace(cfg, fit=dataclasses.replace(cfg.fit, max_iterations=ncfg.refit_iterations))

    def refit(params):
        return _core_fit(problem, refit_cfg, start, False, None, None, params)[0]

    with phase("fit", f"shading normals: up to {ncfg.rounds} rounds of tilts from the photos, each refitted"):
        out = shading_normals.fit_shading_normals(problem, result, inputs.mesh, inputs.bake, cfg, refit,
                                                  log=lambda m: say("fit", m))
    report = {"applied": True, **out.report}
    if out.vertex_normals is None:
        return result, inputs, report
    trace = list(result.trace)
    for probe_s, rows in out.traces:  # each kept round's refit after the fit's rows, as the materials' fit appends
        t_end = trace[-1]["time_s"] + probe_s
        trace += [{**r, "iteration": len(trace) + k, "time_s": r["time_s"] + t_end, "stage": "normals"}
                  for k, r in enumerate(rows[1:])]
    kept = dataclasses.replace(out.result, trace=trace)
    mesh = dataclasses.replace(inputs.mesh, normals=out.vertex_normals)
    return kept, dataclasses.replace(inputs, mesh=mesh, bake=shading_normals.bake_with(inputs.bake, problem)), report


def start_fit_config(cfg, choice: dict | None, p0: np.ndarray | None):
    """The stage config of the fit of every fitted photo: with ``materials.start_fit_rel_tol`` where that fit only
    starts the chosen materials' fit (a materials model chosen before the fit, from the split's fit ``p0``)."""
    tol = cfg.materials.start_fit_rel_tol
    if p0 is None or tol <= 0 or not choice or choice.get("chosen", "per-texel") == "per-texel":
        return cfg
    return dataclasses.replace(cfg, fit=dataclasses.replace(cfg.fit, rel_tol=tol, sync_every=2))


def _core_fit(problem, cfg, start, progress: bool, ckpt, resume, p0: np.ndarray | None = None):
    """(FitResult, tiles report or None): the streaming fit, tiled where asked or on the CPU's cores
    (``stream.cpu_threads``: the same maps), with the checkpoint ``ckpt`` and its state ``resume``; ``p0``: its
    starting parameters (None: ``start``'s)."""
    threads, why = cpu_threads(problem, cfg.fit)
    kept = {"checkpoint": ckpt.save, "resume": resume} if ckpt else {}
    if not tiled(cfg.fit) and threads == 1:
        return run_fit_with_progress(problem, cfg.fit, progress, start=start, p0=p0, **kept), None
    fit_cfg = threaded_config(cfg.fit, threads) if threads > 1 else cfg.fit
    with phase("fit", f"{cfg.fit.model}: tiles of texels ({cfg.fit.stream.tile_backend}"
                      + (f", {threads} CPU threads: {why})" if threads > 1 else ")")):
        result, report = run_tiled_fit_with_progress(problem, fit_cfg, progress, start, p0=p0, **kept)
    say("fit", f"tiles: {report['tiles']} on {','.join(report['devices'])} ({report['backend']}), photos per tile "
               f"{min(report['photos_per_tile'])}..{max(report['photos_per_tile'])} of {report['photos']}")
    return result, report


def _lobes_and_materials(inputs: FitInputs, problem, result, cfg, choice: dict | None = None):
    """(result, Lobes): for a model with lobes, the shared materials' choice (``choice``: made before the fit,
    :func:`_choice_before_fit`) and fit (texels whose highlight no photo caught borrow their material's lobe), or
    the traced polish and the per-texel lobes no photo supports dropped; a model without lobes passes through
    the latter unchanged."""
    info, evidence, materials_problem = None, None, problem
    if result.layout.n_lobes and cfg.materials.mode != "off":
        with (phase("fit", "materials: per-texel or shared lobes, judged on a validation split of the fitted photos")
              if choice is None else contextlib.nullcontext()):
            choice = choice or choose_materials(inputs, problem, cfg)
            traced_extra = {}
            if cfg.traced_materials and choice["chosen"] != "per-texel" and traced_polish_applies(problem, cfg):
                plane_evidence = texel_evidence(problem, result, cfg.materials)
                result = traced_polish(problem, result, cfg)
                materials_problem = traced_problem(problem)
                evidence, dropped = confirm_at_material_lobes(
                    materials_problem, texel_evidence(materials_problem, result, cfg.materials), plane_evidence,
                    choice["k"], cfg.materials)
                traced_extra = {"unconfirmed_at_material_lobe": dropped}
            else:
                evidence = texel_evidence(problem, result, cfg.materials)
        info = {"mode": cfg.materials.mode, "traced": materials_problem is not problem, **traced_extra, **choice}
    if info is not None and info["chosen"] != "per-texel":
        # on traced taps the materials' fit is the polish (traced_polish does nothing more there)
        return fit_chosen_materials(materials_problem, result, evidence, info, cfg, polish=True)
    if traced_polish_applies(problem, cfg):
        with phase("fit", f"traced polish: {cfg.traced_polish} iterations with taps traced to the mesh"):
            result = traced_polish(problem, result, cfg)
    params, dropped = drop_unsupported_lobes(problem, result, cfg.lobe_support)
    return dataclasses.replace(result, params=params), Lobes(info, evidence, None, dropped)


def fit_chosen_materials(problem, result, evidence, info: dict, cfg, polish: bool = False):
    """(result, Lobes) of the materials model the choice ``info`` picked (variant and K), fitted from ``result``;
    its iterations appended to the trace (stage "materials")."""
    t0 = time.perf_counter()
    with phase("fit", f"materials: {info['reason']}"):
        res_m, extra_info = fit_with_materials(problem, result, evidence, info["k"], info["chosen"], cfg,
                                               polish=polish)
    labels = extra_info.pop("labels")
    info.update(extra_info)
    info["chosen_fit_seconds"] = time.perf_counter() - t0  # beside the choice's "seconds"
    t_end = result.trace[-1]["time_s"]
    extra = [{**r, "iteration": r["iteration"] + len(result.trace), "time_s": r["time_s"] + t_end,
              "stage": r.get("stage", "materials")} for r in res_m.trace]
    result = dataclasses.replace(res_m, trace=result.trace + extra)
    return result, Lobes(info, evidence, (extra_info, labels, res_m), np.zeros(problem.n, bool))


def lit_masks(problem, result):
    """The highlight diagnostic's masks (fit/common/highlights.py: which texels a lit photo saw, ...) of a lit model,
    computed once for the maps and the report; None for the radiance models (no light)."""
    if result.layout.is_radiance or result.layout.view_terms:
        return None
    return highlight_masks(problem, result.params)


def _model_grid(inputs: FitInputs, problem, result, cfg, masks=None) -> tuple[np.ndarray, tuple, dict | None]:
    """(parameter maps, (texels filled from the nearest seen one, texels seen only by photos without the flash that
    took their reflectance from the nearest lit one), seams report), checked finite and in bounds. The model
    choice's validation fit (``choice.validation_fit``: scored, then removed) keeps its seams as fitted, as the light
    field mapping candidate it is judged beside does; see :data:`VALIDATION_SEAMS`. ``masks``: :func:`lit_masks`."""
    grid, filled, unlit = params_to_grid(result, problem, inputs.bake), 0, 0
    if cfg.unseen == "nearest":  # texels seen unlit first: an unseen texel may take its values from one
        if masks is not None and has_unlit_photos(inputs.frames):
            grid, unlit = fill_unlit_reflectance(grid, problem, inputs.bake, result.samples > 0, masks.seen,
                                                 result.layout)
        grid, filled = fill_unseen_texels(grid, problem, inputs.bake, result, _unseen_sources(problem, result))
    if cfg.choice.validation_fit and inputs.seams is not None:
        seams_info = {"samples": int(inputs.seams.n_samples), "averaged": False, "why": VALIDATION_SEAMS}
    else:
        grid, seams_info = average_seams_in_bounds(grid, inputs.seams, result.layout)
    check_model(grid, result.layout)  # before rendering it
    return grid, (filled, unlit), seams_info


_UNSEEN_SOURCES: dict = {}
"""the last fit's :func:`~texstream.fit.common.setup.unseen_sources`, by its texels and which of them its photos saw"""


def _unseen_sources(problem, result) -> tuple[np.ndarray, np.ndarray]:
    """:func:`~texstream.fit.common.setup.unseen_sources` of ``problem``'s texels and ``result``'s samples, kept for
    the next fit with the same texels seen: the model choice's radiance and view_radiance validation fits (the same
    photos) share its k-d tree (1.2 s of CPU time on the temple's 545,635 texels)."""
    h = hashlib.sha1()
    for a in (problem.texels.grid_index, problem.texels.position, result.samples > 0):
        h.update(np.ascontiguousarray(a).tobytes())
    key = h.digest()
    if key not in _UNSEEN_SOURCES:
        _UNSEEN_SOURCES.clear()
        _UNSEEN_SOURCES[key] = unseen_sources(problem, result)
    return _UNSEEN_SOURCES[key]


def _write_geometry_and_renders(tmp: Path, inputs: FitInputs, mesh_path, grid, layout, cfg,
                                scores_only: bool = False, bake_changed: bool = False) -> list[dict]:
    """mesh.obj, bake.npz (not ``scores_only``) and renders/ into the model folder; every held-out view scored
    (pooled and worst-view PSNR), the first ``cfg.renders`` written as images. ``bake_changed``: the inputs' bake
    is not the geometry folder's (fitted shading normals), so it is written rather than copied."""
    capture, mesh, bake = inputs.capture, inputs.mesh, inputs.bake

    renders = ModelRenders(mesh, layout, cfg.device)  # one renderer, its BVH built once, for every frame
    renders.set_grid(grid)

    def render(f):
        image, coverage = renders.render(f)
        m = coverage.astype(bool)
        if capture.mask_path(f) is not None and capture.mask_path(f).exists():
            m &= read_mask(capture.mask_path(f), coverage.shape)
        return image, m

    if not scores_only:
        save_mesh(tmp / "mesh.obj", mesh)
        baked = Path(mesh_path) / "bake.npz"
        if Path(mesh_path).is_dir() and baked.is_file() and not bake_changed:  # the bake the fit read: copied
            shutil.copyfile(baked, tmp / "bake.npz")
        else:
            bake.save(tmp / "bake.npz")
    show = inputs.held if inputs.held else inputs.frames_as_photographed()[: max(cfg.renders, 0)]
    return render_comparisons(tmp / "renders", show, load_photos(capture, show)[0] if show else [], inputs.held,
                              render, images=max(cfg.renders, 0))


def write_lobe_maps(tmp: Path, bake, problem, result, lobes: Lobes) -> None:
    """lobes.png (which texels kept, dropped or borrowed a lobe), uncertainty.exr and materials.png; ``bake``:
    what gives the texel grid's ``height`` and ``width`` (the atlas's bake, a single view's TexelSet)."""
    size, index = bake.height * bake.width, problem.texels.grid_index
    if result.layout.n_lobes:
        kept = np.zeros(size, np.float32)
        # white: lobe kept, grey: lobe dropped (no photo saw its highlight), black: unseen or padding
        kept[index] = np.where(lobes.dropped, 0.5, (result.samples > 0).astype(np.float32))
        if lobes.borrowed is not None:
            # white: own lobe, grey: the material's lobe borrowed, dark grey: no lobe (material without one,
            # or photos that contradict it), black: unseen or padding
            prior_borrow, prior_none = lobes.borrowed[0]["borrow_mask"], lobes.borrowed[0]["no_lobe_mask"]
            kept[index] = np.where(result.samples > 0, np.where(
                prior_none, 0.25, np.where(prior_borrow, 0.5, 1.0)), 0.0).astype(np.float32)
        write_image(tmp / "lobes.png", np.repeat(kept.reshape(bake.height, bake.width, 1), 3, axis=2), bits=8)
    if lobes.evidence is None:
        return
    unc = np.zeros((size, 3), np.float32)
    # relative std of rho_s, relative std of n, std of c_z; 1e6: not constrained at all
    unc[index] = np.minimum(lobes.evidence.uncertainty, 1e6)
    write_image(tmp / "uncertainty.exr", unc.reshape(bake.height, bake.width, 3), bits=32)
    if lobes.borrowed is not None:
        lab = np.full(size, -1, np.int64)
        lab[index] = lobes.borrowed[1]
        colours = np.where(lab[:, None] >= 0, MATERIAL_PALETTE[np.maximum(lab, 0) % len(MATERIAL_PALETTE)], 0.0)
        write_image(tmp / "materials.png", colours.reshape(bake.height, bake.width, 3), bits=8)


def write_highlights(tmp: Path, bake, problem, result, lobes: Lobes, image: bool = True, masks=None) -> dict | None:
    """What model.json records of the highlight diagnostic (fit/common/highlights.py) for a lit model, and
    highlights.png (``image``); None for the radiance models (no light, no mirror configuration). ``masks``: the
    model's :func:`lit_masks` where the caller has them."""
    if result.layout.is_radiance or result.layout.view_terms:
        return None
    masks = masks if masks is not None else highlight_masks(problem, result.params)
    if image:
        write_image(tmp / "highlights.png", highlight_image(masks, problem.texels.grid_index, bake.height,
                                                            bake.width), bits=8)
    return highlight_report(masks, None if lobes.evidence is None else lobes.evidence.constrained)


def _manifest(inputs: FitInputs, problem, result, lobes: Lobes, cfg, evals: list[dict], run: dict) -> dict:
    """model.json of a per-texel fit (``run``: seen_before, filled, skipped, tiles, seams, setup_s, timings_s, the
    ambient option's report, ambient.py ``resolve_ambient``, and the highlight diagnostic's)."""
    lay, last, frames = result.layout, result.trace[-1], inputs.frames
    at_bounds, warnings = bound_report(result.params, lay, result.samples > 0)
    warnings = numerics_warnings(cfg.fit.stream, len(frames), inputs.images, inputs.masks) + warnings
    polish_iterations = max(0, sum(r.get("stage") == "traced polish" for r in result.trace) - 1)  # less its start row
    files = {"scores_only": True} if run["scores_only"] else {"mesh": "mesh.obj", "bake": "bake.npz"}
    return {**files, "warnings": warnings, "at_bounds": at_bounds,
            "atlas": {"width": inputs.bake.width, "height": inputs.bake.height, "texels": int(problem.n),
                      "unseen_texels": int((result.samples == 0).sum()), "seen_before_fit": run["seen_before"],
                      "unseen_filled_from_nearest": run["filled"],
                      "seen_only_without_flash_reflectance_from_nearest_lit": run["unlit_filled"],
                      "lobes_dropped": int(lobes.dropped.sum()),
                      "texels_with_lobe": lobes_in_use(result.params, lay, result.samples > 0),
                      "lobe_support": cfg.lobe_support},
            "photos": {"fitted": len(frames), "held_out": len(inputs.held), "skipped": run["skipped"],
                       "residency": problem.photos.residency, "residency_reason": problem.photos.residency_reason,
                       "photos_per_window": problem.photos.window, "resolution": inputs.photo_level},
            "tiles": run["tiles"],
            "traced_polish_iterations": polish_iterations,
            "final": {k: last[k] for k in ("iteration", "time_s", "objective", "psnr_db", "ape_percent")},
            "lobe_shape": lobe_shape_report(cfg.fit, lay, frames, problem.texels.position),
            "materials": _materials_manifest(lobes.info, lobes.evidence, cfg.materials),
            **({"ambient": run["ambient"]} if run["ambient"] is not None else {}),
            **({"highlights": run["highlights"]} if run["highlights"] is not None else {}),
            **({"shading_normals": run["normals"]} if run["normals"] is not None else {}),
            "seams": run["seams"], "setup_s": run["setup_s"], "passes": result.passes, "device": cfg.device,
            "timings_s": run["timings_s"],
            "render_eval": evals, "heldout": pooled_psnr([e for e in evals if e["held_out"]]),
            "units": registry.get(lay.kind).units}
