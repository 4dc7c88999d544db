"""Fitting a capture with light field mapping (``--model lfm``): its own problem (vertex light fields over triangle
rings, fit/models/lfm/problem.py; streaming CG, or the PCA / NMF baselines) and model folder
(fit/models/lfm/model_folder.py). Imports OpenImageIO and scipy inside its functions."""

from __future__ import annotations

import dataclasses
import math
import time
from pathlib import Path

import numpy as np
import warp as wp

from texstream.core.config import config_to_dict
from texstream.core.errors import ConfigError, InputError
from texstream.core.outputs import StageResult, atomic_output_dir, write_json_atomic
from texstream.core.progress import phase, say
from texstream.fit.common.inputs import SharedPhotoSet, load_fit_inputs, load_photos
from texstream.fit.common.model_folder import image_metrics, json_safe, pooled_psnr, render_comparisons
from texstream.fit.common.setup import build_problem, nearest_seen
from texstream.fit.models.lfm.baselines import fit_nmf, fit_pca
from texstream.fit.models.lfm.model_folder import LFMRenderer, lfm_geometry, write_lfm_maps
from texstream.fit.models.lfm.problem import LFMParams, LFMProblem, PhotoSamples, fit_lfm
from texstream.fit.multi.cpu_threads import MAX_AUTO_THREADS, MIN_TEXELS_PER_THREAD, usable_cpus
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


def lfm_threads(fit_cfg, n_texels: int) -> int:
    """CPU threads of the LFM fit's passes: ``stream.cpu_threads``, or with 0 (auto) the per-texel fit's rule
    (fit/multi/cpu_threads.py): every usable core, at most MAX_AUTO_THREADS, MIN_TEXELS_PER_THREAD texels or more
    a thread. Measured on the temple (545,635 texels, 10 photos, 2-core CPU): 10 iterations in 14.7 s on one
    thread, the slot pass 68% of it and the view-map gather 14%, the two that split; 10.4 s on two. With other
    jobs keeping both cores busy two threads lost (17-19 s against 15.6-15.9 s): stream.cpu_threads 1 there."""
    if fit_cfg.stream.cpu_threads > 0:
        return int(fit_cfg.stream.cpu_threads)
    return max(1, min(usable_cpus(), MAX_AUTO_THREADS, n_texels // MIN_TEXELS_PER_THREAD))


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


STOP_FIRST_CHECK = 10
"""the first iteration at which a candidate's validation fit (:class:`CannotWin`) scores the validation photos: the
first iterations move the surface maps onto the starting view maps (problem.py ``initial_view_maps``), where the
score says little of where the fit ends"""


STOP_MARGIN_DB = 0.2
"""how far below the score to beat :func:`can_still_win`'s bound must be: the validation score is noisy between
checks (the dino's LFM fell 0.21 dB from iteration 15 to 20, then rose 0.11 by 25)"""


def can_still_win(points: list[tuple[int, float]], cap: int, target_db: float) -> tuple[bool, float]:
    """(whether the fit may still reach ``target_db``, the score it is bounded by): ``points`` (iteration, validation
    pooled PSNR) at its checks, ``cap`` its last iteration. The bound: the last score rising, for the iterations
    left, at the best rate (dB an iteration, at least 0) of the last two intervals between checks; it may still
    win while the bound is within :data:`STOP_MARGIN_DB` of the target. CG's gains fall as it converges, so a
    recent interval's rate bounds the ones to come; the better of two covers one flat stretch between gains.
    Measured (benchmarks/lfm_choice_profile.py, the run's 50 iterations): the temple's LFM bounded by 19.92 dB at
    iteration 30 (20.20 to beat), reached 19.91; the dino's by 22.94 at 35 (23.25 to beat), reached 22.91. Fewer
    than three points: no bound."""
    if len(points) < 3:
        return True, math.inf
    (i0, s0), (i1, s1), (i2, s2) = points[-3:]
    rate = max((s1 - s0) / max(i1 - i0, 1), (s2 - s1) / max(i2 - i1, 1), 0.0)
    bound = s2 + rate * max(cap - i2, 0)
    return bound + STOP_MARGIN_DB >= target_db, bound


class CannotWin:
    """The model choice's stop for the LFM candidate's validation fit (``choice.beat_db``: the best validation pooled
    PSNR among the candidates judged before it; ``choice.stop_hopeless``): from :data:`STOP_FIRST_CHECK` on, at every
    objective read, the validation photos are rendered at the current parameters and scored as the choice scores
    them; the fit ends once :func:`can_still_win` says it cannot reach the score to beat. The choice then judges
    it by its score there, which loses: the decision is the one the fit to its cap would give whenever the bound
    holds. Only training photos are read (the validation split of the fitted photos)."""

    def __init__(self, target_db: float, cap: int, renderer, frames, photos, within_mask,
                 sources: np.ndarray | None = None):
        """``sources``: :func:`seen_sources` of the fit's texels (the renderer's fill, reused by the model folder)."""
        self.target_db, self.cap, self.renderer, self.sources = target_db, cap, renderer, sources
        self.frames, self.photos, self.within_mask = frames, photos, within_mask
        self.points: list[tuple[int, float]] = []
        self.stopped: str | None = None
        self.seconds = 0.0

    def score(self, G, H) -> float:
        """Validation pooled PSNR of the renderer's model with the fit's current surface and view maps."""
        wp.copy(self.renderer.G, G)
        wp.copy(self.renderer.H, H)
        rows = []
        for f, photo in zip(self.frames, self.photos):
            image, cover = self.renderer.render_frame(f)
            rows.append(image_metrics(image, photo, self.within_mask(f, cover)))
        return pooled_psnr(rows)["pooled_psnr_db"]

    def record(self) -> dict:
        """What the stop did, for the choice's record: why it stopped (None: it did not), the score to beat, the
        checks (iteration, validation pooled PSNR) and the seconds they took."""
        return {"stopped": self.stopped, "beat_db": self.target_db, "checks": self.points,
                "checks_s": self.seconds}

    def __call__(self, iteration: int, G, H) -> bool:
        if iteration < STOP_FIRST_CHECK or iteration >= self.cap:
            return False
        t = time.perf_counter()
        self.points.append((iteration, self.score(G, H)))
        self.seconds += time.perf_counter() - t
        hope, bound = can_still_win(self.points, self.cap, self.target_db)
        if not hope:
            self.stopped = (f"stopped at iteration {iteration} of {self.cap}: validation pooled PSNR "
                            f"{self.points[-1][1]:.2f} dB, at most {bound:.2f} dB by iteration {self.cap} at its "
                            f"recent rate, more than {STOP_MARGIN_DB:g} dB below the {self.target_db:.2f} dB to beat")
        return not hope


def _cannot_win(inputs, problem: LFMProblem, geom, sp, cfg) -> CannotWin | None:
    """The stop of a model choice's validation fit with a score to beat (``choice.beat_db`` above 0 and
    ``choice.stop_hopeless``), else None. Computes the diffuse term (the renderer's, fixed through the fit)."""
    if not (cfg.choice.validation_fit and cfg.choice.stop_hopeless and cfg.choice.beat_db > 0 and inputs.held):
        return None
    problem.compute_diffuse()
    start = LFMParams(problem.diffuse.numpy(), np.zeros((problem.S, problem.K, 3)),
                      np.zeros((problem.V, problem.K, problem.M, 3)))
    sources = seen_sources(geom, problem.seen)
    renderer = LFMRenderer(inputs.mesh, inputs.bake, geom, filled_params(start, geom, problem.seen, sources),
                           problem.cfg, np.asarray(sp.texels.grid_index, np.int64), cfg.device)
    photos = load_photos(inputs.capture, inputs.held)[0]
    return CannotWin(cfg.choice.beat_db, int(problem.cfg.iterations), renderer, inputs.held, photos,
                     inputs.capture.within_mask, sources)


def seen_sources(geom, seen: np.ndarray) -> np.ndarray | None:
    """Per texel, the texel whose diffuse term it shows: itself where a photo sees it, else the nearest seen texel;
    None where there is nothing to fill (every texel seen, or none). A k-d tree of the seen texels (1-2 s on the
    temple's 545,635), built once per fit: the stop's renderer and the model folder fill alike."""
    if not ((~seen).any() and seen.any()):
        return None
    sources = np.arange(len(seen))
    sources[~seen] = np.flatnonzero(seen)[nearest_seen(geom.texel_pos, seen)]
    return sources


def filled_params(params: LFMParams, geom, seen: np.ndarray, sources: np.ndarray | None = None) -> LFMParams:
    """``params`` with every texel no photo sees given the diffuse term of the nearest seen texel (no view terms):
    what the model folder holds and renders. ``sources``: :func:`seen_sources` of ``seen`` where known."""
    sources = seen_sources(geom, seen) if sources is None else sources
    if sources is None:
        return params
    return LFMParams(params.diffuse[sources], params.G, params.H)


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
        problem = LFMProblem(geom, PhotoSamples(sp, frames), lcfg, cfg.device, lfm_threads(cfg.fit, sp.n))
    t_setup = time.perf_counter() - t0
    info, stop = {}, None
    with phase("fit", f"lfm ({lcfg.method}): {problem.V} vertices, {problem.N} texels, K={problem.K}"):
        if lcfg.method == "stream":
            stop = _cannot_win(inputs, problem, geom, sp, cfg)
            res = fit_lfm(problem, time_budget_s=cfg.fit.time_budget_s, stop=stop)
            params, trace, fit_s = res.params, res.trace, res.fit_s
            info = {"iterations": res.iterations, "passes": res.passes}
            if stop is not None:
                info["stop"] = stop.record()
        else:
            params, info = fit_pca(problem) if lcfg.method == "pca" else fit_nmf(problem, lcfg.nmf_iterations)
            trace, fit_s = [], info["total_s"]
        err = problem.model_error(problem.new_G(params.G), problem.new_H(params.H))
    params = filled_params(params, geom, problem.seen, stop.sources if stop is not None else None)
    grid_index = np.asarray(sp.texels.grid_index, np.int64)
    renderer = LFMRenderer(mesh, bake, geom, params, lcfg, grid_index, cfg.device)

    def render(f):
        image, m = renderer.render_frame(f)
        return image, capture.within_mask(f, m)

    # the model choice's validation fit is judged by its scores and then removed: model.json alone (the
    # parameters and maps, compressed, took 3-4 s of the temple's candidate)
    scores_only = cfg.choice.validation_fit
    with atomic_output_dir(out_dir) as tmp, phase("fit", "lfm: held-out renders and the model folder"):
        files = {}
        if not scores_only:
            save_mesh(tmp / "mesh.obj", mesh)
            bake.save(tmp / "bake.npz")
            np.savez_compressed(tmp / "lfm.npz", diffuse=params.diffuse, G=params.G, H=params.H,
                                grid_index=grid_index, vpos=geom.vpos, vnrm=geom.vnrm, vtan=geom.vtan, vbit=geom.vbit)
            files = write_lfm_maps(tmp, params, bake, grid_index, problem.R)
        show = held if held else inputs.frames_as_photographed()[: max(cfg.renders, 0)]
        evals = render_comparisons(tmp / "renders", show, load_photos(capture, show)[0] if show else [], held, render,
                                   images=max(cfg.renders, 0))
        manifest = {"layout": {"kind": "lfm", **dataclasses.asdict(lcfg)}, "scores_only": scores_only,
                    **({} if scores_only else {"mesh": "mesh.obj", "bake": "bake.npz", "params": "lfm.npz"}),
                    "maps": files,
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
                                       "stop": info.get("stop"),
                                       "time_s": fit_s, "texels": problem.N, "photos": len(frames),
                                       "resumed_from": None, "render_eval": evals, "warnings": [],
                                       "heldout": manifest["heldout"]})
