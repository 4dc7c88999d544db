"""Tiled fits: the atlas's texels split into tiles, each fitted over only the photos that see it, on one
device or several (one thread per device), or as Ray actors (fit/tiles_ray.py).

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
import dataclasses
import time

import numpy as np
import warp as wp

from texstream.core.errors import ConfigError

from texstream.fit.optim.fitter import (FitConfig, FitResult, FitRun, converged, start_arrays, robust_scale_from_stats, stop_test_due,
                     trace_rows)
from texstream.fit.kernels.tiles import gather_rows_kernel, scatter_rows_kernel, tile_visibility_kernel, tile_visibility_radiance_kernel
from texstream.fit.stream.photo_set import MAX_LAUNCH_THREADS
from texstream.fit.stream.problem import StreamProblem, exposure_mean_square
from texstream.fit.stream.texels import TexelSet


@dataclasses.dataclass
class TilePlan:
    """How a fit is split: per tile its texel range, device slot and photos.

    Attributes:
        bounds: (T, 2) int64 [begin, end) compact texel indices of each tile.
        devices: the device of each worker slot (a device may appear twice: two threads on it).
        slots: (T,) int64 worker slot of each tile (tile t on slot t mod the slot count).
        photos: per tile, the (P_t,) int64 indices of the photos that see it, ascending.
        halo: per tile, the (H_t,) int64 texels of other tiles its own texels' smoothness reads
            (ascending; empty without smoothness). A tile's problem holds its own texels, then these.
    """

    bounds: np.ndarray
    devices: list[str]
    slots: np.ndarray
    photos: list[np.ndarray]
    halo: list[np.ndarray]

    def texels(self, t: int) -> np.ndarray:
        """Tile t's texels (global indices) in its problem's order: its own range, then its halo."""
        b, e = self.bounds[t]
        return np.concatenate([np.arange(b, e, dtype=np.int64), self.halo[t]])

    def report(self, n_photos: int) -> dict:
        """A plain summary for model.json and benchmarks."""
        return {"tiles": int(len(self.bounds)), "devices": list(self.devices),
                "texels_per_tile": [int(e - b) for b, e in self.bounds],
                "photos_per_tile": [int(p.size) for p in self.photos],
                "photos_streamed_per_tile": [int(tile_photos(self, t, n_photos).size) for t in range(len(self.photos))],
                "photos": int(n_photos)}


def parse_devices(devices: str, default: str) -> list[str]:
    """The worker devices of ``StreamConfig.devices`` ("cuda:0,cuda:1"; empty: ``default``)."""
    names = [d.strip() for d in str(devices).split(",") if d.strip()]
    if not names:
        return [default]
    for d in names:
        if d != "cpu" and not d.startswith("cuda"):
            raise ConfigError(f"device {d!r} in stream.devices unknown", fix="use cpu or cuda:N, comma separated")
        try:
            wp.get_device(d)
        except Exception as e:  # warp raises RuntimeError / ValueError for a device it lacks
            raise ConfigError(f"device {d!r} in stream.devices is not available ({e})",
                              fix="list devices this machine has (warp.get_cuda_device_count())") from None
    return names


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


def check_tileable(cfg: FitConfig) -> None:
    """Refuse options that couple texels across tiles without a halo exchange (LM's smoothness has one),
    naming the option."""
    coupled = []
    if cfg.penalties.laplacian_weight > 0:
        coupled.append("penalties.laplacian_weight (the Laplacian over neighbouring texels)")
    if cfg.stream.model_lookup == "bilinear":
        coupled.append("stream.model_lookup bilinear (neighbours' held values)")
    if cfg.linesearch.acceptance == "global":
        coupled.append("linesearch.acceptance global (one step for all texels)")
    if coupled:
        raise ConfigError("a tiled fit needs texels that are fitted independently (or LM's smoothness, whose "
                          "halo the threads exchange), and " + "; ".join(coupled) + " couple them",
                          fix="set stream.tiles to 0 with one device, or turn those options off")


def split_texels(n: int, tiles: int) -> np.ndarray:
    """(T, 2) [begin, end) ranges of ``tiles`` near-equal runs of consecutive texels (fewer when n < tiles)."""
    tiles = max(1, min(int(tiles), max(n, 1)))
    edges = np.linspace(0, n, tiles + 1).round().astype(np.int64)
    return np.stack([edges[:-1], edges[1:]], axis=1)


def texel_range(texels: TexelSet, begin: int, end: int) -> TexelSet:
    """Texels begin..end-1 as a TexelSet of their own (:func:`texel_subset`)."""
    return texel_subset(texels, np.arange(begin, end, dtype=np.int64))


def texel_subset(texels: TexelSet, indices: np.ndarray) -> TexelSet:
    """Texels ``indices`` (in that order) as a TexelSet of their own: neighbours and padding sources map to
    their positions in ``indices``, or -1 (none) outside it."""
    idx = np.asarray(indices, np.int64)
    where = -np.ones(texels.n + 1, np.int64)  # row n: the -1 of a missing neighbour maps to -1
    where[idx] = np.arange(idx.size)

    def cut(a):
        return None if a is None else np.ascontiguousarray(a[idx])

    def local(ids):
        ids = np.asarray(ids, np.int64)
        return where[np.where(ids >= 0, ids, texels.n)]

    source = None if texels.grid_source is None else local(texels.grid_source)
    return TexelSet(cut(texels.position), cut(texels.normal), cut(texels.tangent), cut(texels.bitangent),
                    cut(texels.grid_index), local(texels.neighbors[idx]).astype(np.int32),
                    texels.width, texels.height, cut(texels.face_normal), cut(texels.normal_jacobian),
                    cut(texels.coordinate_gradients), source)


def halo_texels(texels: TexelSet, begin: int, end: int) -> np.ndarray:
    """The texels outside begin..end-1 that are grid neighbours of texels inside it (ascending)."""
    nb = np.asarray(texels.neighbors[begin:end], np.int64).reshape(-1)
    return np.unique(nb[(nb >= 0) & ((nb < begin) | (nb >= end))])


def tile_photo_visibility(problem: StreamProblem, bounds: np.ndarray) -> np.ndarray:
    """(T, photos) bool: whether photo k has a sample of any texel of tile t (one launch over photos x
    texels per window of photos; the acceptance test of the passes, fit/kernels/tiles.py)."""
    n, dev, photos = problem.n, problem.device, problem.photos
    sizes = (bounds[:, 1] - bounds[:, 0]).astype(np.int64)
    tile_of = wp.array(np.repeat(np.arange(len(bounds), dtype=np.int32), sizes), dtype=wp.int32, device=dev)
    seen = wp.zeros((len(bounds), photos.n), dtype=wp.int32, device=dev)
    kernel = tile_visibility_radiance_kernel if problem.radiance else tile_visibility_kernel
    offset = 0
    step = max(1, MAX_LAUNCH_THREADS // max(n, 1))  # a launch's size stays within Warp's 32-bit bounds
    for images, depth, shadow, infos, b, e in photos.windows():
        for k0 in range(b, e, step):
            wp.launch(kernel, dim=(min(step, e - k0), n), device=dev,
                      inputs=[problem.tex, images, depth, shadow, infos, k0, offset - b, problem.opt, tile_of],
                      outputs=[seen])
        offset += e - b
    return seen.numpy() > 0


def plan_tiles(problem: StreamProblem, cfg: FitConfig) -> TilePlan:
    """Tiles (``StreamConfig.tiles``, 0: one per device), their devices and their photos."""
    check_tileable(cfg)
    devices = parse_devices(cfg.stream.devices, problem.device)
    # streamed photos share one set of window buffers: only one thread on the fit's device may stream them
    if (len(devices) > 1 or devices[0] != problem.device) and problem.photos.residency != "device":
        raise ConfigError(f"fitting on {','.join(devices)} needs the photos resident on the device, and they are "
                          f"{problem.photos.residency} ({problem.photos.residency_reason})",
                          fix="set stream.photo_residency device (and a memory cap that holds them), or fit on "
                              "the one device")
    bounds = split_texels(problem.n, cfg.stream.tiles or len(devices))
    seen = tile_photo_visibility(problem, bounds)
    # a tile no photo sees keeps photo 0: its texels stay unseen (no sample passes the same test), as untiled
    photos = [np.flatnonzero(row) if row.any() else np.zeros(1, np.int64) for row in seen]
    smooth = cfg.penalties.smooth_weight > 0
    halo = [halo_texels(problem.texels, int(b), int(e)) if smooth else np.zeros(0, np.int64) for b, e in bounds]
    return TilePlan(bounds, devices, np.arange(len(bounds)) % len(devices), photos, halo)


ALL_PHOTOS_FRACTION = 0.75
"""a tile that sees at least this fraction of the photos streams them all: the others add only samples the
distribution step rejects (cheaply, at the projection or the depth test), and the tile then needs no copy of
its photos on the parent's device (one device-to-device copy of the arrays elsewhere) instead of a gather
through the host"""


def tile_photos(plan: TilePlan, t: int, n_photos: int) -> np.ndarray:
    """The photos tile t streams: those that see it, or all of them past :data:`ALL_PHOTOS_FRACTION`."""
    idx = plan.photos[t]
    return np.arange(n_photos) if idx.size >= ALL_PHOTOS_FRACTION * n_photos else idx


def tile_problem(problem: StreamProblem, plan: TilePlan, t: int, cfg: FitConfig) -> StreamProblem:
    """Tile ``t``'s StreamProblem on its device: its texels, and its photos (:func:`tile_photos`) with their
    maps (the parent's own when it takes every photo on the parent's device, else a copy,
    :meth:`PhotoSet.subset`)."""
    dev = plan.devices[plan.slots[t]]
    idx = tile_photos(plan, t, problem.photos.n)
    photos = problem.photos
    if dev != problem.device or not np.array_equal(idx, np.arange(photos.n)):
        photos = photos.subset(idx, device=dev)
    return StreamProblem(texel_subset(problem.texels, plan.texels(t)), photos, problem.layout, cfg.stream,
                         device=dev)


def tile_start(plan: TilePlan, t: int, guess: np.ndarray, counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Tile t's starting (parameters, sample counts): its halo starts where its owners do, counted as unseen
    (never stepped, never in the trace's sums)."""
    idx = plan.texels(t)
    c = counts[idx].copy()
    c[plan.bounds[t][1] - plan.bounds[t][0]:] = 0
    return guess[idx], c


def tile_config(problem: StreamProblem, cfg: FitConfig) -> FitConfig:
    """The tiles' config: the accumulate precision resolved for all the photos (a tile sees fewer, and
    ``auto`` would pick by its own count) and the untiled problem's photo groups (automatic groups follow
    the texel count; the same groups over the same photos sum each texel in the same order)."""
    return dataclasses.replace(cfg, stream=dataclasses.replace(cfg.stream, accumulate=problem.accumulate,
                                                                groups=problem.groups))


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


def lockstep(workers, pool_map, cfg: FitConfig, combine_stats, progress=None, first_in_order: bool = True,
             exchange=None):
    """Drive tile workers (:class:`TileWorker` or look-alikes) through the fit in lockstep: a segment of
    iterations up to each stopping test on every worker (``pool_map(fn, workers)`` runs them, concurrently
    where it can), then one test on the summed trace. ``combine_stats``: the tiles' scale-pass statistics
    into one array in the untiled texel order (np.concatenate for tiles of consecutive texels). ``exchange()``, when given, runs after every
    iteration's step on every worker, before their trace rows (a halo exchange: segments of one iteration).
    ``first_in_order``: tile 0 starts, and steps its first iteration, alone before the others (Warp builds a
    kernel's code at its first launch, which two threads must not do at once; every kernel of the fit is
    launched by then). Returns (summed trace rows, times, last iteration, robust scale)."""
    t0 = time.time()  # the tiles' trace rows carry time.time() stamps (comparable across processes)

    def first_map(fn, items):
        """pool_map, tile 0 first on its own when ``first_in_order`` (its launches build every kernel)."""
        if not first_in_order:
            return pool_map(fn, items)
        first = fn(0, items[0])
        return pool_map(lambda t, w: first if t == 0 else fn(t, w), items)

    scale = None
    if workers and pool_map(lambda t, w: w.needs_scale_pass(), workers)[0]:
        stats = first_map(lambda t, w: w.scale_pass_stats(), workers)
        scale = robust_scale_from_stats(combine_stats(stats), cfg)
    rows0 = first_map(lambda t, w: w.begin(scale), workers)
    sums = np.zeros((cfg.max_iterations + 1, 8))
    sums[0] = np.sum(rows0, axis=0)
    times = [max(s[0] for s in pool_map(lambda t, w: w.stamps(0, 0), workers)) - t0]
    last_obj, it, it_done = None, 1, 0
    while it <= cfg.max_iterations:
        end = it
        while not stop_test_due(end, cfg):
            end += 1
        if exchange is not None:
            per_iteration = []
            for k in range(it, end + 1):
                step_map = first_map if k == 1 else pool_map
                step_map(lambda t, w: w.step(k), workers)
                exchange()
                per_iteration.append(step_map(lambda t, w: w.finish(k), workers))
            rows = [np.stack([r[t] for r in per_iteration]) for t in range(len(workers))]
        elif it == 1 and first_in_order:  # tile 0's first iteration alone, then the rest concurrently
            first = workers[0].run_iterations(1, 1)
            rows = pool_map(lambda t, w: w.run_iterations(1, end) if t else
                            np.concatenate([first, w.run_iterations(2, end) if end > 1 else first[:0]]), workers)
        else:
            rows = pool_map(lambda t, w: w.run_iterations(it, end), workers)
        sums[it:end + 1] = np.sum(rows, axis=0)
        # an iteration's time: when its last tile recorded it
        stamps = pool_map(lambda t, w: w.stamps(it, end), workers)
        times.extend(np.max(stamps, axis=0) - t0)
        now = times[-1]
        if progress is not None:
            for k in range(it, end + 1):
                progress(k)
        it_done = end
        obj = float(sums[end, 0])
        if converged(last_obj, obj, cfg):
            break
        last_obj = obj
        if cfg.time_budget_s > 0 and now >= cfg.time_budget_s:
            break
        it = end + 1
    return sums[:it_done + 1], times, it_done, scale


class TileWorker:
    """One tile's fit (a :class:`~texstream.fit.optim.fitter.FitRun`) behind the calls :func:`lockstep` makes;
    the same object runs on a local thread or inside a Ray actor."""

    def __init__(self, problem: StreamProblem, cfg: FitConfig, start: tuple[np.ndarray, np.ndarray],
                 view_mean_sq: float, own: int | None = None):
        """``own``: the tile's own texels, the first of the problem's (the rest: its halo; None: all)."""
        self.problem, self.cfg, self.view_mean_sq = problem, cfg, view_mean_sq
        self.own = problem.n if own is None else int(own)
        self.run = FitRun(problem, cfg, start=start)

    def needs_scale_pass(self) -> bool:
        return self.run.needs_scale_pass()

    def scale_pass_stats(self) -> np.ndarray:
        """The scale pass's per-texel statistics of the tile's own texels."""
        return self.run.scale_pass_stats()[:self.own]

    def stamps(self, first: int, last: int) -> list[float]:
        """The wall-clock times (time.time) trace rows first..last were recorded."""
        return [self.run.stamps[row] for row in range(first, last + 1)]

    def step(self, it: int) -> None:
        """Iteration ``it``'s step (its trace row comes from :meth:`finish`, after a halo exchange)."""
        self.run.step(it)

    def finish(self, it: int) -> np.ndarray:
        """Iteration ``it``'s trace row, the reported objective recomputed with the exchanged halo."""
        self.run.refresh_totals()
        self.run.record(it)
        return self.run.trace_buf.numpy()[it]

    def begin(self, robust_scale: float | None) -> np.ndarray:
        """Start the fit; returns trace row 0 (8 sums over this tile's texels)."""
        self.run.begin(robust_scale, self.view_mean_sq)
        return self.run.trace_buf.numpy()[0]

    def run_iterations(self, first: int, last: int) -> np.ndarray:
        """Iterations first..last; returns their trace rows ((last - first + 1, 8) sums over this tile)."""
        for it in range(first, last + 1):
            self.run.iterate(it)
        return self.run.trace_buf.numpy()[first:last + 1]

    def halo_values(self, rows: np.ndarray) -> np.ndarray:
        """Parameters (``state.p``) of the tile's texels ``rows``, that another tile holds as halo (through
        the host: the Ray backend's exchange)."""
        return self.run.state.p.numpy()[rows]

    def set_halo(self, rows: np.ndarray, values: np.ndarray) -> None:
        """Write ``values`` into ``state.p`` at the halo texels ``rows`` (one upload and a scatter launch)."""
        p = self.run.state.p
        wp.launch(scatter_rows_kernel, dim=len(rows), device=p.device,
                  inputs=[wp.array(values, dtype=p.dtype, device=p.device),
                          wp.array(np.asarray(rows, np.int32), dtype=wp.int32, device=p.device)], outputs=[p])

    def params(self) -> tuple[np.ndarray, int, float]:
        """(fitted (N_t, n_params) parameters, passes streamed, robust scale)."""
        return (self.run.state.params_numpy()[:self.own], int(self.problem.passes),
                float(self.problem.robust_scale))


def halo_pairs(plan: TilePlan) -> list[tuple[int, int, np.ndarray, np.ndarray]]:
    """(owner u, receiver t, rows of u's texels, rows of t's halo) for every pair of tiles with a halo between
    them: what an exchange copies, in the tiles' problems' texel order."""
    owner = np.searchsorted(plan.bounds[:, 1], np.arange(plan.bounds[-1, 1]), side="right")
    pairs = []
    for t, halo in enumerate(plan.halo):
        own_t = int(plan.bounds[t, 1] - plan.bounds[t, 0])
        for u in np.unique(owner[halo]):
            pick = np.flatnonzero(owner[halo] == u)
            pairs.append((int(u), t, (halo[pick] - plan.bounds[u, 0]).astype(np.int32),
                          (own_t + pick).astype(np.int32)))
    return pairs


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


def run_tiled_fit(problem: StreamProblem, cfg: FitConfig, start=None,
                  progress=None) -> tuple[FitResult, dict]:
    """Fit ``problem`` in tiles (``cfg.stream.tiles``, ``devices``, ``tile_backend``); returns the result in the
    untiled texel order and a report (tiles, devices, texels and photos per tile, set-up and fit times).

    ``start``: :func:`~texstream.fit.optim.fitter.fit_start`'s start (or its arrays) over all texels when already streamed."""
    if cfg.stream.tile_backend == "ray":
        from texstream.fit.multi.tiles_ray import run_ray_tiled_fit

        return run_ray_tiled_fit(problem, cfg, start, progress)
    t0 = time.perf_counter()
    guess, counts = start_arrays(start, problem, cfg)
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
                              mean_sq, own=int(e - b))

        # tile 0 first, alone: building launches kernels (Warp's first launch of a kernel is not thread-safe)
        first = make(0, None)
        workers = pool.map(lambda t, _: first if t == 0 else make(t, _), list(range(len(plan.bounds))))
        t_setup = time.perf_counter() - t0
        exchange = HaloExchange(plan, workers) if any(h.size for h in plan.halo) else None
        sums, times, it_done, _ = lockstep(workers, pool.map, cfg, np.concatenate, progress, exchange=exchange)
        parts = pool.map(lambda t, w: w.params(), workers)
    finally:
        pool.close()
    result = assemble(problem, cfg, counts, parts, sums, times, it_done)
    report = {**plan.report(problem.photos.n), "backend": "threads", "tile_setup_s": t_setup,
              "tile_setup_phases_s": {"initial_guess": t_guess - t0, "plan": t_plan - t_guess,
                                      "tile_problems": t_setup - (t_plan - t0)},
              "halo_texels": [int(h.size) for h in plan.halo],
              "fit_s": times[-1]}
    return result, report


def assemble(problem: StreamProblem, cfg: FitConfig, counts: np.ndarray, parts: list, sums: np.ndarray,
             times: list, it_done: int) -> FitResult:
    """The tiles' (parameters, passes, robust scale) as one FitResult in the untiled texel order."""
    passes = max(p[1] for p in parts)
    problem.passes += passes  # the passes each photo streamed through, as an untiled fit counts them
    return FitResult(params=np.concatenate([p[0] for p in parts]), samples=counts,
                     trace=trace_rows(sums, times[:it_done + 1], cfg), layout=problem.layout, passes=problem.passes,
                     robust_loss=cfg.loss(problem.layout), robust_scale=parts[0][2])
