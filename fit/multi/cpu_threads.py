"""A fit on the CPU on every core: Warp runs a CPU kernel on the thread that launches it (one core), and its
launches release the GIL (a ctypes call of the kernel's compiled entry point), so the atlas's texels split
into tiles (fit/multi/tiles.py), one worker thread each on the ``cpu`` device, keep every core busy. The tiled
fit gives the untiled fit's parameters to the last bit (tests/test_fit_tiles.py), so a fit on one thread
and on several write the same model.

The threads share the process: the photos and their maps stay in one copy (a tile that sees at least 3/4 of
them streams the parent's arrays), and the host work between launches (numpy on small arrays, the stopping
test) holds the GIL, the part that does not scale (benchmarks/cpu_threads.py measures both)."""

from __future__ import annotations

import dataclasses

from texstream.geometry.cpu_threads import usable_cpus  # one definition, a layer below
from texstream.fit.optim.fitter import FitConfig
from texstream.fit.multi.tiles import split_photos, tiled
from texstream.fit.stream.problem import StreamProblem

MAX_AUTO_THREADS = 8
"""the most threads ``cpu_threads`` 0 picks: each tile costs a visibility launch and its own set-up, and the
shared host work between launches serialises the threads (untested beyond 2 cores)"""
MIN_TEXELS_PER_THREAD = 2000
"""the fewest texels per thread ``cpu_threads`` 0 gives a thread: below, a tile's launches are too short to pay
for the thread hand-offs (the demo's 176 photos and ~6,000 texels take two)"""


def cpu_threads(problem: StreamProblem, cfg: FitConfig) -> tuple[int, str]:
    """(worker threads, why) for the fit of ``problem`` with ``cfg`` (``StreamConfig.cpu_threads``): more than
    one only on the CPU, for a fit that asked for no tiles or devices of its own, with its photos resident,
    and with options a tiled fit takes. A checkpoint and a warm start do not matter: the tiled fit keeps the
    untiled fit's checkpoint (in the untiled texel order, so either resumes the other's) and takes its starting
    parameters."""
    s = cfg.stream
    if str(problem.device) != "cpu":
        return 1, f"the fit runs on {problem.device}"
    if s.cpu_threads == 1:
        return 1, "stream.cpu_threads 1"
    if tiled(cfg) or split_photos(cfg):
        return 1, "stream.tiles or stream.devices given"
    if problem.photos.residency != "device":
        return 1, f"the photos are streamed from {problem.photos.residency} (the threads would share one window)"
    if s.model_lookup == "bilinear" or cfg.penalties.laplacian_weight > 0 or cfg.linesearch.acceptance == "global":
        return 1, "options that couple the texels (bilinear model_lookup, the Laplacian, a global line search)"
    if s.cpu_threads > 1:
        return min(s.cpu_threads, max(problem.n, 1)), "stream.cpu_threads"
    n = min(usable_cpus(), MAX_AUTO_THREADS, problem.n // MIN_TEXELS_PER_THREAD)
    return max(n, 1), (f"{usable_cpus()} CPU cores, {problem.n:,} texels ({MIN_TEXELS_PER_THREAD:,} or more a "
                       "thread)")


def threaded_config(cfg: FitConfig, threads: int) -> FitConfig:
    """``cfg`` with its texels in ``threads`` tiles, one thread each on the CPU (tile t on thread t)."""
    return dataclasses.replace(cfg, stream=dataclasses.replace(cfg.stream, tiles=threads,
                                                                devices=",".join(["cpu"] * threads)))
