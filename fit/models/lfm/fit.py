"""Fitting a capture with light field mapping (``--model lfm``): its own problem (vertex light fields over triangle
rings, fit/models/lfm/problem.py; streaming CG, or the PCA / NMF baselines) and model folder
(fit/models/lfm/model_folder.py). Imports OpenImageIO and scipy inside its functions."""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np

from texstream.core.config import config_to_dict
from texstream.core.errors import ConfigError, InputError
from texstream.core.outputs import StageResult, atomic_output_dir, write_json_atomic
from texstream.core.progress import phase, say
from texstream.fit.common.inputs import SharedPhotoSet, load_fit_inputs, load_photos
from texstream.fit.common.model_folder import json_safe, pooled_psnr, render_comparisons
from texstream.fit.common.setup import build_problem
from texstream.fit.models.lfm.baselines import fit_nmf, fit_pca
from texstream.fit.models.lfm.model_folder import LFMRenderer, lfm_geometry, write_lfm_maps
from texstream.fit.models.lfm.problem import LFMParams, LFMProblem, PhotoSamples, fit_lfm
from texstream.fit.multi.tiles import split_photos, tiled
from texstream.geometry.mesh_io import save_mesh


def fit(request) -> StageResult:
    """The plugin's fit (registry.FitRequest): tiles and photo splits are per-texel options, refused here."""
    cfg = request.cfg
    if tiled(cfg.fit) or split_photos(cfg.fit):
        raise ConfigError("stream.tiles, stream.devices and stream.tile_backend ray split per-texel models; "
                          "light field mapping couples the texels of a triangle ring",
                          fix="drop those options with --model lfm")
    return lfm_fit_stage(request.capture_dir, request.mesh_path, request.out_dir, cfg, request.progress)


def _radiance_problem(inputs, cfg):
    """The radiance StreamProblem the LFM samples are distributed from, on the photo set the model choice's
    radiance candidates built (fit/common/inputs.py SharedPhotoSet: the same photos, maps and stream options;
    the distribution step only reads them), else on one built here and kept for the next fit."""
    key = SharedPhotoSet.key_for(inputs, cfg)
    shared = SharedPhotoSet.take(key)
    if shared is not None:
        say("fit", "lfm: photos and their maps shared with the previous fit of this capture")
    sp = build_problem(inputs.mesh, inputs.bake, inputs.frames, inputs.images, inputs.masks, cfg.fit, cfg.device,
                       photos=shared)
    SharedPhotoSet.keep(key, sp.photos)
    return sp


def lfm_fit_stage(capture_dir, mesh_path, out_dir, cfg, progress: bool = True) -> StageResult:
    """Fit an LFM model (streaming, PCA or NMF per ``cfg.fit.lfm.method``) and write the model folder."""
    lcfg = cfg.fit.lfm
    lcfg.check()
    t0 = time.perf_counter()
    fit_cfg = dataclasses.replace(cfg.fit, model="radiance")
    with phase("fit", f"lfm ({lcfg.method}): reading the photos and setting up the texels"):
        radiance_cfg = dataclasses.replace(cfg, fit=fit_cfg)
        inputs = load_fit_inputs(capture_dir, mesh_path, radiance_cfg)
        capture, frames, held, mesh, bake = inputs.capture, inputs.frames, inputs.held, inputs.mesh, inputs.bake
        if mesh.uvs is None:
            raise InputError("the mesh has no UVs", mesh_path, "pass an atlas folder (texstream atlas)")
        sp = _radiance_problem(inputs, radiance_cfg)
        geom = lfm_geometry(mesh, bake, sp.texels)
        if lcfg.method == "nmf":
            lcfg = dataclasses.replace(lcfg, diffuse="min")
        elif lcfg.method == "pca":
            lcfg = dataclasses.replace(lcfg, diffuse="mean")
        problem = LFMProblem(geom, PhotoSamples(sp, frames), lcfg, cfg.device)
    t_setup = time.perf_counter() - t0
    info = {}
    with phase("fit", f"lfm ({lcfg.method}): {problem.V} vertices, {problem.N} texels, K={problem.K}"):
        if lcfg.method == "stream":
            res = fit_lfm(problem, time_budget_s=cfg.fit.time_budget_s)
            params, trace, fit_s = res.params, res.trace, res.fit_s
            info = {"iterations": res.iterations, "passes": res.passes}
        else:
            params, info = fit_pca(problem) if lcfg.method == "pca" else fit_nmf(problem, lcfg.nmf_iterations)
            trace, fit_s = [], info["total_s"]
        err = problem.model_error(problem.new_G(params.G), problem.new_H(params.H))
    seen = problem.seen
    if (~seen).any() and seen.any():  # unseen texels: the diffuse of the nearest seen texel, no view terms
        from scipy.spatial import cKDTree

        _, near = cKDTree(geom.texel_pos[seen]).query(geom.texel_pos[~seen])
        diffuse = params.diffuse.copy()
        diffuse[~seen] = diffuse[seen][near]
        params = LFMParams(diffuse, params.G, params.H)
    grid_index = np.asarray(sp.texels.grid_index, np.int64)
    renderer = LFMRenderer(mesh, bake, geom, params, lcfg, grid_index, cfg.device)

    def render(f):
        image, m = renderer.render_frame(f)
        return image, capture.within_mask(f, m)

    with atomic_output_dir(out_dir) as tmp, phase("fit", "lfm: held-out renders and the model folder"):
        save_mesh(tmp / "mesh.obj", mesh)
        bake.save(tmp / "bake.npz")
        np.savez_compressed(tmp / "lfm.npz", diffuse=params.diffuse, G=params.G, H=params.H, grid_index=grid_index,
                            vpos=geom.vpos, vnrm=geom.vnrm, vtan=geom.vtan, vbit=geom.vbit)
        files = write_lfm_maps(tmp, params, bake, grid_index, problem.R)
        show = held if held else inputs.frames_as_photographed()[: max(cfg.renders, 0)]
        evals = render_comparisons(tmp / "renders", show, load_photos(capture, show)[0] if show else [], held, render,
                                   images=max(cfg.renders, 0))
        manifest = {"layout": {"kind": "lfm", **dataclasses.asdict(lcfg)}, "mesh": "mesh.obj", "bake": "bake.npz",
                    "params": "lfm.npz", "maps": files,
                    "lfm": {"vertices_welded": problem.V, "texels": problem.N, "slots": problem.S,
                            "view_texels_in_mask": int(problem.mask_np.sum()), "sample_cache": bool(problem.cache),
                            "parameters": int(problem.S * problem.K * 3 + problem.V * problem.K * problem.M * 3
                                              + problem.N * 3)},
                    "method_info": info, "sample_error": err, "fit_s": fit_s, "setup_s": t_setup,
                    "photos": {"fitted": len(frames), "held_out": len(held)}, "trace": trace,
                    "render_eval": evals, "heldout": pooled_psnr([e for e in evals if e["held_out"]]),
                    "device": cfg.device, "config": config_to_dict(cfg),
                    "units": "exitant radiance in photo values per unit exposure"}
        write_json_atomic(tmp / "model.json", json_safe(manifest))  # a black view's APE is undefined (None)
    return StageResult(Path(out_dir), {"psnr_db": err["psnr_db"], "iterations": info.get("iterations", 0),
                                       "time_s": fit_s, "texels": problem.N, "photos": len(frames),
                                       "resumed_from": None, "render_eval": evals, "warnings": [],
                                       "heldout": manifest["heldout"]})
