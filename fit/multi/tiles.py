"""Tiled fits: the atlas's texels split into tiles, each fitted over only the photos that see it, on one
device or several (one thread per device), or as Ray actors (fit/multi/tiles_ray.py).

A tile is a range of consecutive texels (the compact texel order is the atlas's row order: a band of
atlas rows). Its photos are those in which any of its texels has a sample, from the distribution step's
own acceptance test at set-up (:mod:`texstream.fit.kernels.tiles`), so a tile's passes see every sample
its texels have in the untiled fit. The per-texel fits (LM; SD, CG and L-BFGS with per-texel line
searches) couple no texels, and every tile's problem steps in lockstep with the others: one stopping
test on the objective summed over all tiles, the robust loss's scale and the view prior's exposure
from all photos, the accumulate precision of the whole photo set. With the photos on the device and
one photo group per pass (the CPU's: the same summation order per texel), a tiled fit gives the
untiled fit's parameters to the last bit.

LM's smoothness (``penalties.smooth_weight``) couples each texel to its four atlas neighbours, held
at their current values while it steps (red-black block Gauss-Seidel, fit/optim/lm.py). A tile then
also holds its halo: the neighbours of its texels that other tiles own, never stepped or counted,
their values copied from their owners after every iteration (device to device); with that a tiled
smooth fit is exact too (Ray actors exchange through the object store). The other options that couple texels
(the Laplacian penalty, the renderer's bilinear lookup, the global line search) are refused.
"""

from __future__ import annotations

import concurrent.futures
import time

import numpy as np
import warp as wp

from texstream.core.errors import ConfigError
from texstream.core.progress import bar, bars_enabled

from texstream.fit.optim.fitter import FitConfig, FitResult, robust_scale_from_stats, start_arrays
from texstream.fit.kernels.tiles import gather_rows_kernel, scatter_rows_kernel
from texstream.fit.multi.lockstep import TileWorker, lockstep, tile_resume
from texstream.fit.multi.tile_plan import (TilePlan, assemble, halo_pairs, plan_tiles, texel_subset, tile_config,
                                           tile_photos, tile_start)
from texstream.fit.multi.tile_plan import parse_devices  # noqa: F401  (re-exported: the fit stage's import)
from texstream.fit.multi.tiles_ray import run_ray_tiled_fit
from texstream.fit.stream.problem import StreamProblem, exposure_mean_square


def tiled(cfg: FitConfig) -> bool:
    """Whether ``cfg`` asks for a tiled fit (more than one tile, or other devices than the fit's, or Ray).
    Photos split over devices (``device_split`` photos) are not tiles: refused together with them."""
    s = cfg.stream
    if s.device_split == "photos":
        split_photos(cfg)  # refuses tiles with it
        return False
    return s.tiles > 1 or len([d for d in s.devices.split(",") if d.strip()]) > 1 or s.tile_backend == "ray"


def split_photos(cfg: FitConfig) -> bool:
    """Whether ``cfg`` splits the photos over several devices (``device_split`` photos, two or more devices);
    refuses tiles with it."""
    s = cfg.stream
    if s.device_split != "photos":
        return False
    if s.tiles > 1 or s.tile_backend == "ray":
        raise ConfigError("stream.device_split photos splits the photos, not the texels, and takes no tiles",
                          fix="set stream.tiles to 0 and stream.tile_backend to threads, or device_split to tiles")
    return len([d for d in s.devices.split(",") if d.strip()]) > 1


def tile_problem(problem: StreamProblem, plan: TilePlan, t: int, cfg: FitConfig) -> StreamProblem:
    """Tile ``t``'s StreamProblem on its device: its texels, and its photos (:func:`tile_photos`) with their
    maps (the parent's own when it takes every photo on the parent's device, else a copy,
    :meth:`PhotoSet.subset`), and its rows of the parent's shared-materials prior when it has one."""
    dev = plan.devices[plan.slots[t]]
    idx = tile_photos(plan, t, problem.photos.n)
    photos = problem.photos
    if dev != problem.device or not np.array_equal(idx, np.arange(photos.n)):
        photos = photos.subset(idx, device=dev)
    return texels_problem(problem, plan.texels(t), photos, cfg, dev)


def texels_problem(problem: StreamProblem, rows: np.ndarray, photos, cfg: FitConfig, device: str) -> StreamProblem:
    """The StreamProblem of the parent's texels ``rows`` over ``photos`` on ``device``, with those rows of the
    parent's shared-materials prior when it has one."""
    tile = StreamProblem(texel_subset(problem.texels, rows), photos, problem.layout, cfg.stream, device=device)
    if problem.material_centre is not None:  # the shared materials' prior: per texel, so each tile takes its rows
        tile.set_material_prior(problem.material_centre.numpy()[rows], problem.material_weights.numpy()[rows])
    return tile


WARM_UP_TEXELS = 64
"""the seen texels of tile 0 that :func:`warm_up` steps alone before the tiles run at once"""


def warm_up(problem: StreamProblem, first: TileWorker, cfg: FitConfig, guess: np.ndarray, counts: np.ndarray,
            mean_sq: float) -> bool:
    """Load every Warp module the tiles' fit launches before their threads run (Warp loads a module at its first
    launch, which two threads must not do at once): a throwaway fit of :data:`WARM_UP_TEXELS` seen texels of tile 0
    (``first``, whose own texels lead the parent's), over its photos, through the calls :func:`lockstep` makes
    of a tile up to its first iteration, instead of tile 0's whole scale pass, start and first iteration alone
    (the temple's view_radiance fit, two iterations, ran two thirds of its passes on one of the two threads). The
    tiles' fit is untouched: the warm-up has problem, state and robust scale of its own. False (no warm-up):
    tile 0 sees no texel, so the tiles keep lockstep's tile-0-first order."""
    own = np.flatnonzero(counts[:first.own] > 0)[:WARM_UP_TEXELS]
    if own.size == 0:
        return False
    tile = texels_problem(problem, own, first.problem.photos, cfg, first.problem.device)
    worker = TileWorker(tile, cfg, (guess[own], counts[own]), mean_sq)
    scale = None
    if worker.needs_scale_pass():
        scale = robust_scale_from_stats(worker.scale_pass_stats(), cfg)
    worker.begin(scale)
    worker.run_iterations(1, 1)
    return True


class SlotPool:
    """Runs a function over tiles, the tiles of one worker slot in order on that slot's thread (Warp's
    launches, synchronisations and copies release the GIL, so devices run concurrently)."""

    def __init__(self, plan: TilePlan):
        self.plan = plan
        self.pool = concurrent.futures.ThreadPoolExecutor(max_workers=len(plan.devices),
                                                          thread_name_prefix="texstream-tile")

    def map(self, fn, items: list) -> list:
        """[fn(t, items[t]) for each tile t], each slot's tiles on its own thread; results in tile order."""
        by_slot = [[t for t in range(len(items)) if self.plan.slots[t] == s] for s in range(len(self.plan.devices))]

        def run(ts):
            return [(t, fn(t, items[t])) for t in ts]

        out = [None] * len(items)
        for done in self.pool.map(run, [ts for ts in by_slot if ts]):
            for t, r in done:
                out[t] = r
        return out

    def close(self) -> None:
        self.pool.shutdown()


class HaloExchange:
    """Copies, after each iteration, every tile's halo texels' parameters (``state.p``) from the tiles that
    own them: per (owner, receiver) pair one gather launch on the owner's device, one copy (device to
    device, or within one), one scatter launch on the receiver's; no host round trip."""

    def __init__(self, plan: TilePlan, workers: list[TileWorker]):
        self.workers = workers
        self.devices = sorted({w.problem.device for w in workers})
        self.pairs = []
        for u, t, src, dst in halo_pairs(plan):
            wu, wt = workers[u], workers[t]
            dev_u, dev_t = wu.problem.device, wt.problem.device
            dtype = wu.run.state.p.dtype
            self.pairs.append((wu, wt, wp.array(src, dtype=wp.int32, device=dev_u),
                               wp.array(dst, dtype=wp.int32, device=dev_t),
                               wp.empty(src.size, dtype=dtype, device=dev_u),
                               wp.empty(src.size, dtype=dtype, device=dev_t)))

    def _sync(self) -> None:
        for d in self.devices:
            wp.synchronize_device(d)

    def __call__(self) -> None:
        # three phases, each ended by a synchronisation of every device: a copy between two devices runs on
        # one device's stream, not ordered after the other's launches
        self._sync()  # the owners' steps are done
        for wu, wt, src, dst, out_u, in_t in self.pairs:
            wp.launch(gather_rows_kernel, dim=src.shape[0], device=wu.problem.device,
                      inputs=[wu.run.state.p, src], outputs=[out_u])
        self._sync()
        for wu, wt, src, dst, out_u, in_t in self.pairs:
            wp.copy(in_t, out_u)
        self._sync()
        for wu, wt, src, dst, out_u, in_t in self.pairs:
            wp.launch(scatter_rows_kernel, dim=dst.shape[0], device=wt.problem.device,
                      inputs=[in_t, dst], outputs=[wt.run.state.p])
        self._sync()


def run_tiled_fit_with_progress(problem: StreamProblem, cfg: FitConfig, progress: bool, start=None,
                                **kw) -> tuple[FitResult, dict]:
    """:func:`run_tiled_fit` with a tqdm bar over iterations when ``progress``, as an untiled fit shows
    (``kw``: p0, checkpoint, resume)."""
    if not (progress and bars_enabled()):
        return run_tiled_fit(problem, cfg, start, **kw)
    with bar(total=cfg.max_iterations, desc=f"fit {cfg.optimizer}", unit="it") as b:
        b.update(int(kw["resume"]["iteration"]) if kw.get("resume") else 0)
        return run_tiled_fit(problem, cfg, start, progress=lambda it: b.update(1), **kw)


def run_tiled_fit(problem: StreamProblem, cfg: FitConfig, start=None, progress=None, p0: np.ndarray | None = None,
                  checkpoint=None, resume: dict | None = None) -> tuple[FitResult, dict]:
    """Fit ``problem`` in tiles (``cfg.stream.tiles``, ``devices``, ``tile_backend``); returns the result in the
    untiled texel order and a report (tiles, devices, texels and photos per tile, set-up and fit times).

    ``start``: :func:`~texstream.fit.optim.fitter.fit_start`'s start (or its arrays) over all texels when already
    streamed; ``p0``, ``checkpoint`` and ``resume``: as :func:`~texstream.fit.optim.fitter.run_fit`'s (the
    starting parameters; the checkpoint, in the untiled texel order, so a fit on other tiles or untiled resumes
    it; threads only)."""
    if cfg.stream.tile_backend == "ray":
        if p0 is not None or checkpoint is not None or resume is not None:
            raise ConfigError("a fit on Ray actors takes no starting parameters and keeps no checkpoint",
                              fix="set stream.tile_backend threads, or fit.checkpoint off")
        return run_ray_tiled_fit(problem, cfg, start, progress)
    t0 = time.perf_counter()
    guess, counts = start_arrays(start, problem, cfg)
    if p0 is not None:  # as FitRun: the counts of ``start``, the parameters given
        guess = np.asarray(p0, dtype=np.float64)
    t_guess = time.perf_counter()
    plan = plan_tiles(problem, cfg)
    t_plan = time.perf_counter()
    tcfg = tile_config(problem, cfg)
    mean_sq = exposure_mean_square(problem.photos)
    pool = SlotPool(plan)
    try:
        def make(t, _):
            b, e = plan.bounds[t]
            return TileWorker(tile_problem(problem, plan, t, tcfg), tcfg, tile_start(plan, t, guess, counts),
                              mean_sq, own=int(e - b), checkpointed=checkpoint is not None,
                              resume=tile_resume(resume, plan.texels(t)))

        # tile 0 first, alone: building launches kernels (Warp's first launch of a kernel is not thread-safe)
        first = make(0, None)
        workers = pool.map(lambda t, _: first if t == 0 else make(t, _), list(range(len(plan.bounds))))
        t_setup = time.perf_counter() - t0
        exchange = HaloExchange(plan, workers) if any(h.size for h in plan.halo) else None
        # with a halo exchange (other calls, other kernels) tile 0 still goes first alone (lockstep)
        warmed = exchange is None and len(workers) > 1 and warm_up(problem, first, tcfg, guess, counts, mean_sq)
        t_warm = time.perf_counter() - t0 - t_setup
        sums, times, it_done, _ = lockstep(workers, pool.map, cfg, np.concatenate, progress, first_in_order=not warmed,
                                           exchange=exchange, checkpoint=checkpoint, resume=resume)
        parts = pool.map(lambda t, w: w.params(), workers)
    finally:
        pool.close()
    result = assemble(problem, cfg, counts, parts, sums, times, it_done)
    report = {**plan.report(problem.photos.n), "backend": "threads", "tile_setup_s": t_setup,
              "tile_setup_phases_s": {"initial_guess": t_guess - t0, "plan": t_plan - t_guess,
                                      "tile_problems": t_setup - (t_plan - t0)},
              "warm_up": {"texels": WARM_UP_TEXELS if warmed else 0, "seconds": t_warm},
              "halo_texels": [int(h.size) for h in plan.halo],
              "fit_s": times[-1]}
    return result, report
