"""Tile workers stepped in lockstep (fit/multi/tiles.py's threads, fit/multi/tiles_ray.py's Ray actors): a tile's
fit behind the calls the loop makes, and the loop's one stopping test on the trace summed over every tile."""

from __future__ import annotations

import time

import numpy as np
import warp as wp

from texstream.fit.optim.fitter import FitConfig, FitRun, converged, robust_scale_from_stats, stop_test_due
from texstream.fit.kernels.tiles import scatter_rows_kernel
from texstream.fit.stream.problem import StreamProblem


def lockstep(workers, pool_map, cfg: FitConfig, combine_stats, progress=None, first_in_order: bool = True,
             exchange=None, checkpoint=None, resume: dict | None = None):
    """Drive tile workers (:class:`TileWorker` or look-alikes) through the fit in lockstep: a segment of
    iterations up to each stopping test on every worker (``pool_map(fn, workers)`` runs them, concurrently
    where it can), then one test on the summed trace. ``combine_stats``: the tiles' scale-pass statistics
    into one array in the untiled texel order (np.concatenate for tiles of consecutive texels). ``exchange()``, when given, runs after every
    iteration's step on every worker, before their trace rows (a halo exchange: segments of one iteration).
    ``first_in_order``: tile 0 starts, and steps its first iteration, alone before the others (Warp builds a
    kernel's code at its first launch, which two threads must not do at once; every kernel of the fit is
    launched by then). ``checkpoint(state)`` and ``resume``: as :func:`~texstream.fit.optim.fitter.run_fit`'s, the
    state in the untiled texel order (:func:`checkpoint_state`), so any tiling resumes any other's; the workers
    were made with their tiles' share of ``resume``. Returns (summed trace rows, times, last iteration, robust
    scale)."""
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
    if resume is None:
        sums[0] = np.sum(rows0, axis=0)
        times = [max(s[0] for s in pool_map(lambda t, w: w.stamps(0, 0), workers)) - t0]
        last_obj, it, it_done = None, 1, 0
    else:  # the checkpoint's summed trace and times, then this run's (from 0 again, as run_fit's resume)
        it_done = int(resume["iteration"])
        sums[:it_done + 1] = np.asarray(resume["trace"])
        times = [float(x) for x in resume["times"]]
        last_obj = None if not np.isfinite(resume["last_obj"]) else float(resume["last_obj"])
        it, scale = it_done + 1, float(resume["robust_scale"])
    start_it = it  # this run's first iteration: tile 0 steps it alone first (first_in_order)
    while it <= cfg.max_iterations:
        end = it
        while not stop_test_due(end, cfg):
            end += 1
        if exchange is not None:
            per_iteration = []
            for k in range(it, end + 1):
                step_map = first_map if k == start_it else pool_map
                step_map(lambda t, w: w.step(k), workers)
                exchange()
                per_iteration.append(step_map(lambda t, w: w.finish(k), workers))
            rows = [np.stack([r[t] for r in per_iteration]) for t in range(len(workers))]
        elif it == start_it and first_in_order:  # tile 0's first iteration alone, then the rest concurrently
            first = workers[0].run_iterations(it, it)
            rows = pool_map(lambda t, w: w.run_iterations(it, end) if t else
                            np.concatenate([first, w.run_iterations(it + 1, end) if end > it else first[:0]]),
                            workers)
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
        if checkpoint is not None and end < cfg.max_iterations:
            checkpoint(checkpoint_state(workers, pool_map, end, sums, times, last_obj, scale))
        if cfg.time_budget_s > 0 and now >= cfg.time_budget_s:
            break
        it = end + 1
    return sums[:it_done + 1], times, it_done, scale


def checkpoint_state(workers, pool_map, it: int, sums: np.ndarray, times: list, last_obj: float,
                     scale: float | None) -> dict:
    """What ``resume`` takes to continue after iteration ``it``, as an untiled fit's
    (:meth:`~texstream.fit.optim.fitter.FitRun.checkpoint_state`): the tiles' own texels' parameters and LM
    damping in the untiled texel order (tiles of consecutive texels), the summed trace."""
    parts = pool_map(lambda t, w: w.checkpoint_part(), workers)
    return {"iteration": it, "p": np.concatenate([p for p, _, _ in parts]),
            "lam": np.concatenate([lam for _, lam, _ in parts]), "trace": sums[:it + 1].copy(),
            "times": np.asarray(times), "last_obj": last_obj,
            "robust_scale": parts[0][2] if scale is None else float(scale)}


def tile_resume(resume: dict | None, texels: np.ndarray) -> dict | None:
    """Tile's share of an untiled-order checkpoint ``resume``: the parameters and damping of its ``texels``
    (its own, then its halo; :meth:`~texstream.fit.multi.tile_plan.TilePlan.texels`)."""
    if resume is None:
        return None
    return {**resume, "p": np.asarray(resume["p"])[texels], "lam": np.asarray(resume["lam"])[texels]}


class TileWorker:
    """One tile's fit (a :class:`~texstream.fit.optim.fitter.FitRun`) behind the calls :func:`lockstep` makes;
    the same object runs on a local thread or inside a Ray actor."""

    def __init__(self, problem: StreamProblem, cfg: FitConfig, start: tuple[np.ndarray, np.ndarray],
                 view_mean_sq: float, own: int | None = None, checkpointed: bool = False,
                 resume: dict | None = None):
        """``own``: the tile's own texels, the first of the problem's (the rest: its halo; None: all);
        ``checkpointed`` and ``resume`` (the tile's share, :func:`tile_resume`): as :class:`FitRun`'s."""
        self.problem, self.cfg, self.view_mean_sq = problem, cfg, view_mean_sq
        self.own = problem.n if own is None else int(own)
        self.run = FitRun(problem, cfg, start=start, checkpointed=checkpointed, resume=resume)

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

    def checkpoint_part(self) -> tuple[np.ndarray, np.ndarray, float]:
        """(parameters ``state.p``, LM's damping, robust scale) of the tile's own texels: its share of a
        checkpoint."""
        return (self.run.state.p.numpy()[:self.own], self.run.opt.lam.numpy()[:self.own],
                float(self.problem.robust_scale))

    def params(self) -> tuple[np.ndarray, int, float]:
        """(fitted (N_t, n_params) parameters, passes streamed, robust scale)."""
        return (self.run.state.params_numpy()[:self.own], int(self.problem.passes),
                float(self.problem.robust_scale))
