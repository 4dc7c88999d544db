"""The fit of a per-texel model (Lafortune, diffuse, radiance, view-dependent radiance): inputs, set-up, the
streaming fit, the lobes and materials where the model has lobes, held-out renders and the model folder."""

from __future__ import annotations

import dataclasses
import shutil
import time
from pathlib import Path

import numpy as np

from texstream.core.outputs import StageResult, atomic_output_dir
from texstream.core.progress import say

from texstream.fit.optim.fitter import resumable

from texstream.fit.common import model_folder
from texstream.fit.models import registry
from texstream.fit.common.inputs import load_photos, load_fit_inputs, set_up_skipping_bad_photos
from texstream.fit.common.setup import params_to_grid, render_model, run_fit_with_progress, Checkpoint, fill_unseen_texels
from texstream.fit.models.per_texel.lobes import lobe_shape_report, drop_unsupported_lobes, lobes_in_use, texel_evidence, confirm_at_material_lobes, traced_polish_applies, traced_problem, traced_polish, fit_with_materials, choose_materials, average_seams_in_bounds, _materials_manifest


def _fit_per_texel_model(capture_dir: str | Path, mesh_path: str | Path, out_dir: str | Path, cfg,
                        progress: bool, plotter=None) -> StageResult:
    """:func:`fit_stage` for the per-texel models (Lafortune, radiance): ``plotter`` draws the
    error-against-time plot (:func:`~texstream.fit.common.model_folder.start_plotter`; None: a child started at
    the end does)."""
    from texstream.capture.imageio import read_mask
    from texstream.core.progress import phase
    from texstream.geometry.mesh_io import save_mesh

    from texstream.fit.common.model_folder import (bound_report, check_model, pooled_psnr, render_comparisons, trace_plot,
                               write_model_folder)
    from texstream.fit.common.numerics import numerics_warnings

    t0 = time.perf_counter()
    with phase("fit", f"{cfg.fit.model}: reading the photos and setting up the texels"):
        inputs = load_fit_inputs(capture_dir, mesh_path, cfg)
        t_inputs = time.perf_counter() - t0
        capture, frames, held, mesh, bake = inputs.capture, inputs.frames, inputs.held, inputs.mesh, inputs.bake
        problem, seen_before, start, skipped = set_up_skipping_bad_photos(inputs, cfg, capture_dir)
        frames = inputs.frames
    t_setup = time.perf_counter() - t0
    from texstream.fit.multi.tiles import run_tiled_fit, tiled

    ckpt, resume, tiles_report = None, None, None
    if cfg.checkpoint and resumable(cfg.fit) and not tiled(cfg.fit):
        from texstream.core.config import config_to_dict

        ckpt = Checkpoint(out_dir, {"capture": str(Path(capture_dir).resolve()), "mesh": str(Path(mesh_path).resolve()),
                                    "config": config_to_dict(cfg), "texels": problem.n,
                                    "capture_mtime": (Path(capture_dir) / "capture.json").stat().st_mtime_ns
                                    if (Path(capture_dir) / "capture.json").exists() else 0})
        resume = ckpt.load()
    if tiled(cfg.fit):
        with phase("fit", f"{cfg.fit.model}: tiles of texels ({cfg.fit.stream.tile_backend})"):
            result, tiles_report = run_tiled_fit(problem, cfg.fit, start)
        say("fit", f"tiles: {tiles_report['tiles']} on {','.join(tiles_report['devices'])} "
                   f"({tiles_report['backend']}), photos per tile {min(tiles_report['photos_per_tile'])}.."
                   f"{max(tiles_report['photos_per_tile'])} of {tiles_report['photos']}")
    else:
        result = run_fit_with_progress(problem, cfg.fit, progress, start=start,
                                       **({"checkpoint": ckpt.save, "resume": resume} if ckpt else {}))
    t_loop = time.perf_counter()
    lay = result.layout
    materials_info, evidence, borrowed = None, None, None
    materials_problem = problem
    if lay.n_lobes and cfg.materials.mode != "off":
        with phase("fit", "materials: per-texel or shared lobes, judged on a validation split of the fitted photos"):
            choice = choose_materials(inputs, problem, cfg)
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
        materials_info = {"mode": cfg.materials.mode, "traced": materials_problem is not problem, **traced_extra,
                          **choice}
    if materials_info is not None and materials_info["chosen"] != "per-texel":
        with phase("fit", f"materials: {materials_info['reason']}"):
            # on traced taps the materials' fit is the polish (traced_polish does nothing more there)
            res_m, info = fit_with_materials(materials_problem, result, evidence, materials_info["k"],
                                             materials_info["chosen"], cfg, polish=True)
        labels = info.pop("labels")
        materials_info.update(info)
        borrowed = (info, labels, res_m)
        t_end = result.trace[-1]["time_s"]
        extra = [{**r, "iteration": r["iteration"] + len(result.trace), "time_s": r["time_s"] + t_end,
                  "stage": r.get("stage", "materials")} for r in res_m.trace]
        lobes_dropped = np.zeros(problem.n, bool)
        result = dataclasses.replace(res_m, trace=result.trace + extra)
    else:
        if traced_polish_applies(problem, cfg):
            with phase("fit", f"traced polish: {cfg.traced_polish} iterations with taps traced to the mesh"):
                result = traced_polish(problem, result, cfg)
        params, lobes_dropped = drop_unsupported_lobes(problem, result, cfg.lobe_support)
        result = dataclasses.replace(result, params=params)
    title = f"{lay.kind} fit, {cfg.fit.optimizer}, {cfg.device}"
    polish_iterations = max(0, sum(r.get("stage") == "traced polish" for r in result.trace) - 1)  # less its start row
    grid, filled = params_to_grid(result, problem, bake), 0
    if cfg.unseen == "nearest":
        grid, filled = fill_unseen_texels(grid, problem, bake, result)
    grid, seams_info = average_seams_in_bounds(grid, inputs.seams, lay)
    check_model(grid, lay)  # before rendering it

    def render(f):
        image, coverage = render_model(mesh, grid, lay, f, cfg.device)
        m = coverage.astype(bool)
        if capture.mask_path(f) is not None and capture.mask_path(f).exists():
            m &= read_mask(capture.mask_path(f), coverage.shape)
        return image, m

    t_fitted = time.perf_counter()
    with (atomic_output_dir(out_dir) as tmp, phase("fit", f"{cfg.fit.model}: held-out renders and the model folder"),
          trace_plot(tmp, result.trace, title, plotter) as plot):  # drawn by the child while this one renders
        save_mesh(tmp / "mesh.obj", mesh)
        baked = Path(mesh_path) / "bake.npz"
        if Path(mesh_path).is_dir() and baked.is_file():  # the bake the fit read (load_geometry): copied
            shutil.copyfile(baked, tmp / "bake.npz")
        else:
            bake.save(tmp / "bake.npz")
        # every held-out view is scored (pooled and worst-view PSNR); the first `renders` are written as images
        show = held if held else frames[: max(cfg.renders, 0)]
        evals = render_comparisons(tmp / "renders", show, load_photos(capture, show)[0] if show else [], held, render,
                                   images=max(cfg.renders, 0))
        seen = np.zeros(bake.height * bake.width, bool)
        seen[problem.texels.grid_index] = result.samples > 0
        if lay.n_lobes:
            from texstream.capture.imageio import write_image

            kept = np.zeros(bake.height * bake.width, np.float32)
            kept[problem.texels.grid_index] = np.where(lobes_dropped, 0.5, (result.samples > 0).astype(np.float32))
            if borrowed is not None:
                # white: own lobe, grey: the material's lobe borrowed, dark grey: no lobe (material without one,
                # or photos that contradict it), black: unseen or padding
                prior_borrow, prior_none = borrowed[0]["borrow_mask"], borrowed[0]["no_lobe_mask"]
                kept[problem.texels.grid_index] = np.where(result.samples > 0, np.where(
                    prior_none, 0.25, np.where(prior_borrow, 0.5, 1.0)), 0.0).astype(np.float32)
            # white: lobe kept, grey: lobe dropped (no photo saw its highlight), black: unseen or padding
            write_image(tmp / "lobes.png", np.repeat(kept.reshape(bake.height, bake.width, 1), 3, axis=2), bits=8)
        if evidence is not None:
            from texstream.capture.imageio import write_image

            unc = np.zeros((bake.height * bake.width, 3), np.float32)
            unc[problem.texels.grid_index] = np.minimum(evidence.uncertainty, 1e6)
            # relative std of rho_s, relative std of n, std of c_z; 1e6: not constrained at all
            write_image(tmp / "uncertainty.exr", unc.reshape(bake.height, bake.width, 3), bits=32)
            if borrowed is not None:
                lab = np.full(bake.height * bake.width, -1, np.int64)
                lab[problem.texels.grid_index] = borrowed[1]
                palette = np.array([[0.9, 0.6, 0.1], [0.1, 0.6, 0.2], [0.8, 0.8, 0.8], [0.2, 0.3, 0.9],
                                    [0.8, 0.1, 0.1], [0.6, 0.2, 0.8], [0.1, 0.8, 0.8], [0.5, 0.4, 0.2]], np.float32)
                colours = np.where(lab[:, None] >= 0, palette[np.maximum(lab, 0) % len(palette)], 0.0)
                write_image(tmp / "materials.png", colours.reshape(bake.height, bake.width, 3), bits=8)
        last = result.trace[-1]
        at_bounds, warnings = bound_report(result.params, lay, result.samples > 0)
        warnings = numerics_warnings(cfg.fit.stream, len(frames), inputs.images, inputs.masks) + warnings
        manifest = {"mesh": "mesh.obj", "bake": "bake.npz", "warnings": warnings, "at_bounds": at_bounds,
                    "atlas": {"width": bake.width, "height": bake.height, "texels": int(problem.n),
                              "unseen_texels": int((result.samples == 0).sum()), "seen_before_fit": seen_before,
                              "unseen_filled_from_nearest": filled, "lobes_dropped": int(lobes_dropped.sum()),
                              "texels_with_lobe": lobes_in_use(result.params, lay, result.samples > 0),
                              "lobe_support": cfg.lobe_support},
                    "photos": {"fitted": len(frames), "held_out": len(held), "skipped": skipped,
                               "residency": problem.photos.residency,
                               "residency_reason": problem.photos.residency_reason,
                               "photos_per_window": problem.photos.window},
                    "tiles": tiles_report,
                    "traced_polish_iterations": polish_iterations,
                    "final": {k: last[k] for k in ("iteration", "time_s", "objective", "psnr_db", "ape_percent")},
                    "lobe_shape": lobe_shape_report(cfg.fit, lay, frames, problem.texels.position),
                    "materials": _materials_manifest(materials_info, evidence, cfg.materials),
                    "seams": seams_info, "setup_s": t_setup, "passes": result.passes, "device": cfg.device,
                    "timings_s": {"inputs": t_inputs, "setup": t_setup - t_inputs, "fit": t_loop - t0 - t_setup,
                                  "after_fit": t_fitted - t_loop, "renders": time.perf_counter() - t_fitted},
                    "render_eval": evals, "heldout": pooled_psnr([e for e in evals if e["held_out"]]),
                    "units": registry.get(lay.kind).units}
        write_model_folder(tmp, grid, lay, seen.reshape(bake.height, bake.width), result.trace, title, manifest, cfg,
                           plot=plot)
    if ckpt is not None:
        ckpt.remove()
    problem.photos.wait_for_cache()  # a photo cache written in the background is complete for the next fit
    return StageResult(Path(out_dir), {"psnr_db": last["psnr_db"], "iterations": last["iteration"],
                                       "time_s": last["time_s"], "texels": problem.n, "photos": len(frames),
                                       "resumed_from": None if resume is None else int(resume["iteration"]),
                                       "skipped_photos": [p["file"] for p in skipped],
                                       "render_eval": evals, "warnings": warnings,
                                       "heldout": manifest["heldout"], "materials": manifest["materials"]})



def fit(request) -> StageResult:
    """A per-texel model's fit (registry.FitRequest): a child process draws the error-against-time plot while
    the photos are read and fitted (it imports matplotlib meanwhile)."""
    plotter = model_folder.start_plotter()  # through the module: tests replace it there
    try:
        return _fit_per_texel_model(request.capture_dir, request.mesh_path, request.out_dir, request.cfg,
                                    request.progress, plotter)
    finally:
        model_folder.stop_plotter(plotter)
