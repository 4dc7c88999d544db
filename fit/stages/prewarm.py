"""On a cold kernel cache, build the default run's Warp modules at once, in parallel, before the fit launches any.

Warp compiles a module at its first launch, so a cold ``texstream run`` compiled ~25 modules one after another
(issue 40: 27 of the README demo's 31.6 s on an H200). Warp's own compile runs unlocked in threads (only the
Python code generation is serialised), so the first fit on a device whose marker is missing
(fit/kernels/build_notice.py) loads every module the default run will launch there in one batch, one thread
per CPU core, and the run's launches find them built. A module's hash covers its generic kernels' overloads,
so those are declared when each kernel is made (fit/kernels/overloads.py): the hash built here is the hash
launched, in this process and in later ones. A warm cache (the marker there) skips all of it.

The lists are explicit, one per group of models a run fits together (:data:`KERNEL_GROUPS`: the default run's
reflectance models; the radiance models a run of photos under an unknown light compares), each with its own
marker (a run of real photos first, then the README demo: each builds its own group ahead).
tests/test_fit_prewarm.py fails when a run of a group launches a module its list lacks, or one whose hash it did
not build. Not every module texstream imported: most of the fit's modules are made per pass kind by factories
only when a fit asks for them, and on a 2-core CPU each unneeded module is a compile the run would wait for.
"""

from __future__ import annotations

import os
import time
from concurrent.futures import ThreadPoolExecutor

import warp as wp

from texstream.core.progress import say
from texstream.fit.kernels import accumulate, highlights, lfm, optim_kernels, stream, tiles, view_error
from texstream.fit.kernels.build_notice import kernel_build_line, kernels_cold
from texstream.fit.kernels.overloads import declare_param_counts
from texstream.fit.models.lafortune import gltf_core_kernel
from texstream.fit.stream import photo_stream
from texstream.fit.stream.config import StreamConfig
from texstream.geometry import bake, refine_kernels, refine_normal_kernels
from texstream.render import kernels as render_kernels
from texstream.render import visibility

DEFAULT_KINDS = ("lafortune", "diffuse")
"""the models of the default run (the README's ``texstream run``: Lafortune, diffuse beside it)"""
RADIANCE_KINDS = ("radiance", "view_radiance", "lfm")
"""the models a run compares under one fixed, unknown light (fit/models/radiance/choice.py)"""
RADIANCE_PARAM_COUNTS = (3, 18)
"""parameters per texel of the radiance models: radiance (RGB) and view_radiance (RGB and 5 view terms per
channel), declared before the group's first launch (fit/kernels/overloads.py ``declare_param_counts``); LFM's
kernels are not generic over it"""
KERNEL_GROUPS = {"default": DEFAULT_KINDS, "unknown_light": RADIANCE_KINDS}
"""the groups built ahead, each with its marker; a fit of another kind builds only :func:`shared_modules` ahead
and the rest at its launches"""
MAX_REGISTERS = 168
"""the accumulation kernels' register cap of layouts of at most 9 parameters (``stream.cuda_max_registers``
-1, fit/stream/problem.py): part of their names, so of their modules"""


def shared_modules() -> list:
    """(module, block_dim) of every fit: photo streaming and depth maps, the plain optimizer kernels, the
    renderer of the held-out renders and the report."""
    plain = [photo_stream.to_half_kernel, visibility.depth_maps_kernel, optim_kernels.guess_from_samples_kernel,
             render_kernels.render_kernel]
    return [(k.module, None) for k in plain]


def default_run_modules(device: str) -> list:
    """(module, block_dim) of every module the default run's fit, export and report launch on ``device``
    (None: the launch's default block size; the accumulation passes run at ``stream.cuda_block_dim``)."""
    passes = StreamConfig().cuda_block_dim
    per_pass = [accumulate.accumulate_lm_kernel(1, 0, MAX_REGISTERS),  # Lafortune's LM
                accumulate.accumulate_lm_kernel(1, 0, MAX_REGISTERS, False, True),  # its traced polish
                accumulate.accumulate_kernel(1, 0, False, False, False, False, MAX_REGISTERS),  # its scores
                accumulate.accumulate_lm_kernel(0, 0, MAX_REGISTERS)]  # diffuse's LM
    generic = [stream.initial_guess_kernel_for(False), *optimizer_modules()]
    plain = [view_error.view_error_rows_kernel, highlights.highlight_samples_kernel,
             gltf_core_kernel.core_material_kernel]
    if not str(device).startswith("cuda"):
        generic.append(tiles.tile_visibility_kernel)  # the CPU's fit in threads over tiles of texels
    return (shared_modules() + [(k.module, passes) for k in per_pass]
            + [(k.module, None) for k in generic + plain])


def radiance_run_modules(device: str) -> list:
    """(module, block_dim) of every module a run under one unknown light launches on ``device``: the radiance
    and view_radiance fits (the radiance model's Cauchy loss, radiance/__init__.py; at most 9 parameters capped
    at :data:`MAX_REGISTERS`, as fit/stream/problem.py does), LFM's passes, the optimizer's kernels with the
    group's parameter counts declared."""
    passes = StreamConfig().cuda_block_dim
    per_pass = [accumulate.accumulate_lm_kernel(0, 0, MAX_REGISTERS, radiance=1, robust=accumulate.ROBUST_CAUCHY),
                accumulate.accumulate_lm_kernel(0, 0, 0, radiance=2)]  # view_radiance: 18 parameters, no cap
    generic = [stream.initial_guess_kernel_for(True), *optimizer_modules()]
    plain = [lfm.slot_pass_batch_kernel]
    if not str(device).startswith("cuda"):
        generic.append(tiles.tile_visibility_kernel)  # the CPU's fit in threads over tiles of texels
    return (shared_modules() + [(k.module, passes) for k in per_pass]
            + [(k.module, None) for k in generic + plain])


def optimizer_modules() -> list:
    """The plain optimizer's kernels (one module each, generic over the declared parameter counts)."""
    return [optim_kernels.start_point_kernel, optim_kernels.trial_kernel, optim_kernels.lm_solve_kernel,
            optim_kernels.lm_accept_kernel, optim_kernels.chunk_sums_kernel, optim_kernels.centred_prior_kernel,
            optim_kernels.centred_prior_diag_kernel, accumulate.reduce_partials_kernel]


def kernel_group(kind: str) -> str | None:
    """The group of :data:`KERNEL_GROUPS` that model ``kind`` belongs to (None: none)."""
    return next((group for group, kinds in KERNEL_GROUPS.items() if kind in kinds), None)


def declare_group_overloads(kind: str) -> None:
    """Before a fit of ``kind`` builds or launches a kernel: its group's parameter counts (the same in every
    process that fits the group, so a cold build is what later runs launch)."""
    if kernel_group(kind) == "unknown_light":
        declare_param_counts(RADIANCE_PARAM_COUNTS)


def build_threads() -> int:
    """One compile per CPU core this process may use."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def later_stage_modules() -> list:
    """(module, None) of the stages between the mesh and the fit: the atlas's texel bake and the refinement's passes
    (none generic: built ahead, they are what those stages launch; the temple's cold refine waited 3.0 s for them).
    The mesh stage's own modules are left to it: it launches them at once."""
    return [(wp.get_module(m.__name__), None) for m in (bake, refine_kernels, refine_normal_kernels)]


def group_modules(group: str | None, device: str) -> list:
    """(module, block_dim) of the modules ``group`` builds ahead on ``device`` (another kind: the shared ones)."""
    return {"default": default_run_modules, "unknown_light": radiance_run_modules}.get(
        group, lambda d: shared_modules())(device)


def _build(modules: list, device: str, threads: int) -> float:
    """Load (compile) ``modules`` on ``threads`` threads at once; the seconds it took."""
    t0 = time.perf_counter()
    with ThreadPoolExecutor(threads) as pool:
        for done in [pool.submit(wp.force_load, device=device, modules=[m], block_dim=b, max_workers=0)
                     for m, b in modules]:
            done.result()
    return time.perf_counter() - t0


_AHEAD: dict = {}
"""(device, precision, group) -> (the build started by :func:`build_kernels_ahead`, its module count)"""


def build_kernels_ahead(stage: str, device: str, kind: str, precision: str = "fp32", now: list = (),
                        later_stages: bool = True) -> None:
    """A run on a GPU with a cold kernel cache: build ``now`` (the modules the next stage launches, e.g. the mesh
    stage's) and :func:`shared_modules` at once, in parallel, then start the fit's modules for ``kind``'s group and
    the atlas's and refinement's (:func:`later_stage_modules`) on a thread of their own, so they compile while those
    stages run (the temple's cold run on an H200 waited 10.5 s of its fit stage for them); the fit waits for that
    build (:func:`build_kernels_if_cold`). The caller declared the fit's precision and group overloads first (the
    modules' hashes depend on them). Nothing loads a module from two threads at once: what the stages launch first
    is built before they start. ``later_stages``: whether the atlas and refine stages will run (their modules are
    built too). The CPU builds at the fit, as before: its cores are the stages' own."""
    group = kernel_group(kind)
    if not str(device).startswith("cuda") or group is None or not kernels_cold(device, precision, group):
        return
    first = [(m, None) for m in now] + shared_modules()
    skip = {id(m) for m, _ in first}
    later = later_stage_modules() if later_stages else []  # a run given its atlas makes none and refines nothing
    modules = [(m, b) for m, b in later + group_modules(group, device) if id(m) not in skip]
    wp.init()  # here, not in the build threads: a first init marks every module modified under their loads
    threads = min(build_threads(), len(first) + len(modules))
    what = "the atlas's, the refinement's and the fit's" if later_stages else "the fit's"
    say(stage, kernel_build_line(device, f"{len(first)} Warp modules now, {len(modules)} more ({what}) on {threads} "
                                         "threads while the stages before the fit run"))
    say(stage, f"kernels built: {len(first)} Warp modules in {_build(first, device, threads):.1f} s")
    pool = ThreadPoolExecutor(1, thread_name_prefix="texstream-kernels")
    _AHEAD[(device, precision, group)] = (pool.submit(_build, modules, device, threads), len(modules))
    pool.shutdown(wait=False)


def build_kernels_if_cold(stage: str, device: str, kind: str, precision: str = "fp32") -> None:
    """The first fit on ``device`` with a cold kernel cache: say so, build the default run's modules (those
    every fit launches for another ``kind``) in parallel, and say how long it took; a build started ahead
    (:func:`build_kernels_ahead`) is waited for instead. Warm: nothing. ``precision``: the fit's compute
    precision, whose overloads the caller declared (fit/kernels/overloads.py ``declare_precision``), so the
    modules built hold them."""
    group = kernel_group(kind)
    ahead = _AHEAD.pop((device, precision, group), None)
    if ahead is not None:
        t0 = time.perf_counter()
        seconds = ahead[0].result()  # a build error is raised here, as it would be at a launch
        say(stage, f"kernels built ahead: {ahead[1]} Warp modules in {seconds:.1f} s, "
                   f"{time.perf_counter() - t0:.1f} s of it waited for here")
        return
    if not kernels_cold(device, precision, group):
        return
    modules = group_modules(group, device)
    wp.init()  # here, not in the build threads: a first init marks every module modified under their loads
    threads = min(build_threads(), len(modules))
    say(stage, kernel_build_line(device, f"{len(modules)} Warp modules at once on {threads} threads"))
    say(stage, f"kernels built: {len(modules)} Warp modules in {_build(modules, device, threads):.1f} s")
