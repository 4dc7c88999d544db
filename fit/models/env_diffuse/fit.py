"""Fitting a capture under one unknown environment light (``--model env_diffuse``).

Three phases:
1. the photos stream through the radiance model's per-texel fit (fit/models/per_texel: the same set-up,
   photo levels, robust loss and passes), which leaves each texel's radiance R_t and sample count w_t, the
   statistics of a Lambertian texel's data term under one light (solve.py's docstring);
2. each texel's transfer vector with self-occlusion from the mesh (geometry/sh_transfer.py);
3. the light (estimated through shared materials, or given by ``--env.light``) and every texel's albedo
   (solve.py), the ambiguities fixed as the options say.

The model folder (folder.py reads it back): mesh.obj, bake.npz, albedo.exr, radiance.exr (the albedo lit by
the estimated light: what the photos saw), transfer.npz (the atlas's transfer vectors, (H, W, 9)), light.json
(the SH light, the format ``--env`` reads), environment.exr (that light as a 64 x 32 latitude-longitude map),
renders/, model.json (layout kind "env_diffuse", the light, its gauge and trace, the held-out scores) and
fit_config.json.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np

from texstream.capture.imageio import write_image
from texstream.core.config import config_to_dict, save_config
from texstream.core.outputs import StageResult, atomic_output_dir, write_json_atomic
from texstream.core.progress import phase
from texstream.fit.common.inputs import load_fit_inputs, load_photos, set_up_skipping_bad_photos
from texstream.fit.common.model_folder import pooled_psnr, render_comparisons
from texstream.fit.common.setup import fill_unseen_texels, params_to_grid, run_fit_with_progress
from texstream.fit.models.env_diffuse.light_file import read_light, write_light_json
from texstream.fit.models.env_diffuse.model import (ENV_MAP_SIZE, EnvDiffuseRenderer, lit_radiance, transfer_grid)
from texstream.fit.models.env_diffuse.solve import solve
from texstream.geometry.mesh_io import save_mesh
from texstream.geometry.sh_transfer import sh_transfer
from texstream.render import sh

UNITS = "albedo in [0, 1] x the SH light's radiance in photo values per unit exposure (render/sh.py)"


def fit(request) -> StageResult:
    """The plugin's fit (registry.FitRequest)."""
    cfg, env = request.cfg, request.cfg.fit.env
    fixed = read_light(env.light) if env.light else None  # a bad light file fails before any work
    t0 = time.perf_counter()
    rad_cfg = dataclasses.replace(cfg, fit=dataclasses.replace(cfg.fit, model="radiance"))
    with phase("fit", "env_diffuse: reading the photos and setting up the texels"):
        inputs = load_fit_inputs(request.capture_dir, request.mesh_path, rad_cfg)
        problem, _, start, skipped = set_up_skipping_bad_photos(inputs, rad_cfg, request.capture_dir)
    t_setup = time.perf_counter()
    with phase("fit", "env_diffuse: the photos streamed into per-texel radiance (the radiance model's fit)"):
        result = run_fit_with_progress(problem, rad_cfg.fit, request.progress, start=start)
    t_stream = time.perf_counter()
    tx, mesh = problem.texels, inputs.mesh
    with phase("fit", f"env_diffuse: transfer vectors of {problem.n} texels, {env.directions} rays each"):
        transfer = sh_transfer(mesh.vertices, mesh.faces, tx.position, tx.normal, tx.face_normal, env.directions,
                               env.occlusion, cfg.device)
    t_transfer = time.perf_counter()
    seen = result.samples > 0
    what = "given" if fixed is not None else "estimated with shared materials"
    with phase("fit", f"env_diffuse: the light ({what}) and the albedo of {int(seen.sum())} seen texels"):
        sol = solve(result.params[seen], result.samples[seen], transfer[seen], env, fixed, tx.position[seen])
    t_solve = time.perf_counter()
    albedo = np.zeros((problem.n, 3))
    albedo[seen] = sol.albedo
    albedo_res = dataclasses.replace(result, params=albedo)
    grid = params_to_grid(albedo_res, problem, inputs.bake)
    filled = 0
    if cfg.unseen == "nearest":
        grid, filled = fill_unseen_texels(grid, problem, inputs.bake, albedo_res)
    tgrid = transfer_grid(inputs.bake, tx.grid_index, transfer)
    timings = {"setup": t_setup - t0, "stream": t_stream - t_setup, "transfer": t_transfer - t_stream,
               "light_and_albedo": t_solve - t_transfer}
    out = _write_folder(request, inputs, grid, tgrid, sol, fixed is not None, timings,
                        {"texels": int(problem.n), "seen": int(seen.sum()), "filled": filled, "skipped": skipped,
                         "trace": result.trace, "passes": result.passes})
    last = result.trace[-1]
    return StageResult(Path(request.out_dir), {"psnr_db": last["psnr_db"], "iterations": last["iteration"],
                                               "time_s": time.perf_counter() - t0, "texels": problem.n,
                                               "photos": len(inputs.frames), "resumed_from": None,
                                               "skipped_photos": [p["file"] for p in skipped],
                                               "render_eval": out["render_eval"], "warnings": out["warnings"],
                                               "heldout": out["heldout"]})


def _write_folder(request, inputs, grid, tgrid, sol, given: bool, timings: dict, run: dict) -> dict:
    """The model folder, atomically; returns model.json."""
    cfg, bake = request.cfg, inputs.bake
    capture = inputs.capture
    renderer = EnvDiffuseRenderer(inputs.mesh, grid, tgrid, sol.light, cfg.device)

    def render(f):
        image, m = renderer.render(f)
        return image, capture.within_mask(f, m)

    covered = np.asarray(bake.covered, bool)
    over_one = int((grid[covered].max(axis=-1) > 1.0).sum())
    warnings = [f"{over_one} texels have an albedo above 1 (the scale fixed by --env.scale)"] if over_one else []
    with atomic_output_dir(request.out_dir) as tmp, phase("fit", "env_diffuse: held-out renders and the model folder"):
        save_mesh(tmp / "mesh.obj", inputs.mesh)
        bake.save(tmp / "bake.npz")
        write_image(tmp / "albedo.exr", grid.astype(np.float32), bits=32)
        write_image(tmp / "radiance.exr", lit_radiance(grid, tgrid, sol.light).astype(np.float32), bits=32)
        np.savez_compressed(tmp / "transfer.npz", transfer=tgrid.astype(np.float32))
        write_light_json(tmp / "light.json", sol.light)
        write_image(tmp / "environment.exr", np.maximum(sh.latlong_from_sh(sol.light, *ENV_MAP_SIZE), 0.0)
                    .astype(np.float32), bits=32)
        show = inputs.held if inputs.held else inputs.frames_as_photographed()[: max(cfg.renders, 0)]
        evals = render_comparisons(tmp / "renders", show, load_photos(capture, show)[0] if show else [],
                                   inputs.held, render, images=max(cfg.renders, 0))
        env = cfg.fit.env
        manifest = {
            "layout": {"kind": "env_diffuse"}, "mesh": "mesh.obj", "bake": "bake.npz",
            "maps": {"albedo": "albedo.exr", "radiance": "radiance.exr"}, "transfer": "transfer.npz",
            "light": {"file": "light.json", "environment": "environment.exr", "source": "given" if given else
                      "estimated", "given_file": env.light or None, "sh": [[float(v) for v in r] for r in sol.light],
                      "gauge": sol.gauge, "materials": [[float(v) for v in r] for r in sol.materials],
                      "trace": sol.trace},
            "ambiguities": _ambiguities(env, given),
            "atlas": {"width": bake.width, "height": bake.height, "texels": run["texels"],
                      "seen_texels": run["seen"], "unseen_filled_from_nearest": run["filled"]},
            "photos": {"fitted": len(inputs.frames), "held_out": len(inputs.held), "skipped": run["skipped"]},
            # the photos' stream (the radiance fit): its trace and last row, as the report reads a fit's
            "passes": run["passes"], "trace": run["trace"], "setup_s": timings["setup"],
            "final": {k: run["trace"][-1][k] for k in ("iteration", "time_s", "objective", "psnr_db")},
            "timings_s": timings, "warnings": warnings, "device": cfg.device, "config": config_to_dict(cfg),
            "render_eval": evals, "heldout": pooled_psnr([e for e in evals if e["held_out"]]), "units": UNITS}
        write_json_atomic(tmp / "model.json", manifest)
        save_config(cfg, tmp / "fit_config.json")  # the report reads the held-out split from it, as other models'
    return manifest


def _ambiguities(env, given: bool) -> dict:
    """What the photos under one light cannot tell, and how the fit decided it (model.json)."""
    if given:
        return {"light": "given (--env.light): the albedo is determined, no gauge"}
    return {
        "light_vs_albedo": "with a free albedo per texel any light fits; the light was estimated with shared "
                           "materials (texels of one albedo seen at different normals and visibility), then each "
                           "texel's albedo given it",
        "scale": f"albedo x s and light / s render alike: {env.scale} fixed at {env.scale_value:g}",
        "colour": "per channel, albedo x g and light / g render alike: "
                  + ("the environment's mean colour is grey" if env.white == "light" else
                     "the seen texels' mean albedo is grey"),
        "relighting": "renders under another light are right up to these two choices; a benchmark compares "
                      "scale-invariantly or fixes them from the truth (--env.scale light_mean --env.scale-value)"}
