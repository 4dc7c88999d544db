"""Tiled fits on a Ray cluster (``StreamConfig.tile_backend`` ray; the optional ``texstream[distributed]``).

Each tile is a Ray actor that builds its own problem: its texels (shipped, small) and its photos read
from the capture's files (paths on storage every worker reads), cropped, with their depth and shadow
maps made on the actor's device, as the one-process set-up makes them photo by photo (same crops, same
rays: the same values). The driver plans the tiles (fit/multi/tiles.py: visibility from its own set-up) and
drives the actors in lockstep (:func:`texstream.fit.multi.lockstep.lockstep`), so a Ray fit gives the
one-process fit's parameters to the last bit under the conditions of fit/multi/tiles.py. Ray is imported
here only: ``texstream.fit`` itself still imports only numpy and warp.

The cluster: the one this process is connected to (``ray.init`` called before), else ``RAY_ADDRESS``'s,
else a local one. An actor takes one GPU (``num_gpus=1``, its device cuda:0 of those Ray gives it) when
the fit's device is CUDA, else one CPU; with more tiles than the cluster has, a share of one, so that every
actor is placed at once (the lockstep waits for all of them).
"""

from __future__ import annotations

import dataclasses
import os
import time

import numpy as np

from texstream.core.errors import ConfigError, TexstreamError

from texstream.fit.optim.fitter import start_arrays
from texstream.fit.stream.problem import StreamProblem, exposure_mean_square
from texstream.fit.multi.lockstep import TileWorker, lockstep
from texstream.fit.multi.tile_plan import (assemble, check_tileable, halo_pairs, plan_tiles, texel_subset, tile_config,
                                           tile_photos, tile_start)
from texstream.fit.stream.photo_set import PhotoSet


class TileActor:
    """A tile's :class:`~texstream.fit.multi.lockstep.TileWorker`, built inside the actor's process from ``spec``
    (frames, photo files, mesh arrays, texels, layout, config, start, device)."""

    def __init__(self, spec: dict):
        import warp as wp

        wp.config.quiet = True
        wp.init()
        self.error = None
        try:
            dev = spec["device"]
            mesh_points, mesh_faces, mesh_normals, mesh_uvs = spec["mesh"]
            cfg = spec["config"]
            photos = PhotoSet(spec["frames"], spec["files"], mesh_points, mesh_faces, config=cfg.stream, device=dev,
                              mesh_normals=mesh_normals, mesh_uvs=mesh_uvs)
            problem = StreamProblem(spec["texels"], photos, spec["layout"], cfg.stream, device=dev)
            self.worker = TileWorker(problem, cfg, spec["start"], spec["view_mean_sq"], own=spec["own"])
        except TexstreamError as e:  # e.g. a photo this worker cannot read: raised by the first call, as itself
            self.error = e

    def call(self, name: str, *args):
        if self.error is not None:
            raise self.error
        return getattr(self.worker, name)(*args)


class RemoteWorker:
    """An actor handle that looks like a TileWorker to :func:`lockstep`: each method call returns an ObjectRef."""

    def __init__(self, handle):
        self.handle = handle

    def __getattr__(self, name):
        return lambda *args: self.handle.call.remote(name, *args)


def run_ray_tiled_fit(problem, cfg, start=None, progress=None):
    """:func:`texstream.fit.multi.tiles.run_tiled_fit` with one Ray actor per tile; same result and report."""
    check_tileable(cfg)
    try:
        import ray
    except ImportError:
        raise ConfigError("stream.tile_backend ray needs Ray", fix="pip install 'texstream[distributed]', or set "
                          "stream.tile_backend threads") from None
    photos = problem.photos
    if photos.source is None or photos.mesh is None:
        raise ConfigError("stream.tile_backend ray reads each tile's photos from the capture's files, and this "
                          "fit's photos are arrays in memory", fix="fit a capture folder (texstream fit), or set "
                          "stream.tile_backend threads")
    t0 = time.perf_counter()
    if not ray.is_initialized():
        ray.init(address=os.environ.get("RAY_ADDRESS") or None, log_to_driver=False)
    guess, counts = start_arrays(start, problem, cfg)
    plan = plan_tiles(problem, dataclasses.replace(cfg, stream=dataclasses.replace(cfg.stream, devices=problem.device)))
    tcfg = tile_config(problem, cfg)
    gpu = problem.device.startswith("cuda")
    kind = "GPU" if gpu else "CPU"
    available = float(ray.cluster_resources().get(kind, 0.0))
    if available <= 0:
        raise ConfigError(f"the Ray cluster has no {kind} for the tiles of a fit on {problem.device}",
                          fix="start the cluster's workers with GPUs (ray start --num-gpus) or fit on the CPU")
    # more tiles than GPUs (CPUs): tiles share them (fractional resources), so every actor is placed at once
    share = min(1.0, available / len(plan.bounds))
    share = max(1e-4, float(np.floor(share * 1e4) / 1e4))  # Ray's resource precision
    actor = (ray.remote(num_gpus=share, num_cpus=0)(TileActor) if gpu
             else ray.remote(num_cpus=share)(TileActor))
    mean_sq = exposure_mean_square(photos)
    workers = []
    for t, (b, e) in enumerate(plan.bounds):
        idx = tile_photos(plan, t, photos.n)
        spec = {"device": "cuda:0" if gpu else "cpu", "mesh": photos.mesh_arrays,
                "frames": [photos.frames[k] for k in idx], "files": photos.source.subset(idx),
                "texels": texel_subset(problem.texels, plan.texels(t)), "layout": problem.layout, "config": tcfg,
                "start": tile_start(plan, t, guess, counts), "view_mean_sq": mean_sq, "own": int(e - b)}
        workers.append(RemoteWorker(actor.remote(spec)))
    try:
        def ray_map(fn, items):
            try:
                return ray.get([fn(t, w) for t, w in enumerate(items)])
            except ray.exceptions.RayTaskError as e:  # a user error in an actor: its one line, not Ray's traceback
                if isinstance(getattr(e, "cause", None), TexstreamError):
                    raise e.cause from None
                raise

        ray_map(lambda t, w: w.needs_scale_pass(), workers)  # every actor built before the clock of the fit
        t_setup = time.perf_counter() - t0
        pairs = halo_pairs(plan)

        def exchange():
            """The halos through the object store: every owner's values, then every receiver's update."""
            values = ray.get([workers[u].halo_values(src) for u, t, src, dst in pairs])
            ray.get([workers[t].set_halo(dst, v) for (u, t, src, dst), v in zip(pairs, values)])

        sums, times, it_done, _ = lockstep(workers, ray_map, cfg, np.concatenate, progress,
                                           first_in_order=False,  # one process per actor: no shared kernels
                                           exchange=exchange if pairs else None)
        parts = ray_map(lambda t, w: w.params(), workers)
    finally:
        for w in workers:
            ray.kill(w.handle)
    result = assemble(problem, cfg, counts, parts, sums, times, it_done)
    report = {**plan.report(photos.n), "devices": ["ray:" + ("gpu" if gpu else "cpu")] * len(plan.bounds),
              "backend": "ray", "tile_setup_s": t_setup, "fit_s": times[-1],
              "halo_texels": [int(h.size) for h in plan.halo]}
    return result, report

