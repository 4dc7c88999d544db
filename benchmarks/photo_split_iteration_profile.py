"""Kernel times of an LM iteration on one GPU and with the photos split over two (fit/photo_split.py), then the
set-up's upload variants (switch interval, copy threads, chunk size) and whole pageable photos copied straight to
the devices; writes JSON and prints a log.

    python benchmarks/photo_split_iteration_profile.py OUT_DIR [--iterations-only]   # on a machine with two CUDA GPUs

``--iterations-only`` stops after the iterations.
"""

import collections
import concurrent.futures
import json
import os
import sys
import time

import warp as wp

import texstream.fit.stream.photo_set as P
from photo_split_scene import OrnamentAt4x
from texstream.fit.optim.fitter import FitConfig, FitRun
from texstream.fit.stream.config import StreamConfig
from texstream.fit.stages.stage import build_problem

wp.config.quiet = True
wp.init()

out = {}
scene = OrnamentAt4x("cuda:0")
mesh, frames, images, masks, bake = scene.mesh, scene.frames, scene.images, scene.masks, scene.bake
photoset = scene.photoset
# A: kernel times per LM iteration
for name, extra in (("one", {}), ("split", dict(devices="cuda:0,cuda:1", device_split="photos"))):
    cfg = FitConfig(
        optimizer="lm",
        max_iterations=10,
        rel_tol=0.0,
        stream=StreamConfig(image_precision="fp16", photo_residency="device", **extra),
    )
    pr = build_problem(mesh, bake, frames, images, masks, cfg, "cuda:0")
    run = FitRun(pr, cfg)
    run.begin()
    run.iterate(1)
    wp.synchronize()
    t = time.perf_counter()
    wp.timing_begin(cuda_filter=wp.TIMING_ALL)
    for it in (2, 3):
        run.iterate(it)
    res = wp.timing_end()
    wall = (time.perf_counter() - t) / 2
    tot = collections.defaultdict(float)
    for r in res:
        tot[(str(r.device), r.name[:60])] += r.elapsed / 2
    rows = sorted(tot.items(), key=lambda kv: -kv[1])[:14]
    out["iteration_" + name] = {"wall_ms": wall * 1e3, "kernels_ms": [[d, n, v] for (d, n), v in rows]}
    print(name, "iteration wall %.1f ms" % (wall * 1e3), flush=True)
    for (d, n), v in rows:
        print("   %-8s %-60s %7.2f ms" % (d, n, v), flush=True)
    del run, pr
if "--iterations-only" in sys.argv:
    with open(os.path.join(sys.argv[1], "iteration_profile.json"), "w") as fh:
        json.dump(out, fh, indent=1)
    sys.exit(0)
ps = photoset("cuda:0")
# B1: pinned allocation
for mb in (16, 64):
    t = time.perf_counter()
    bufs = [wp.empty(mb << 20 >> 2, dtype=float, device="cpu", pinned=True) for _ in range(4)]
    out[f"pinned_alloc_4x{mb}MB_s"] = time.perf_counter() - t
    print("pinned alloc 4 x %d MB %.3f s" % (mb, out[f"pinned_alloc_4x{mb}MB_s"]), flush=True)
    del bufs
n, half = len(frames), len(frames) // 2


def variant(tag, switch=None, chunk=None, **kw):
    old_sw, old_chunk = sys.getswitchinterval(), P.UPLOAD_CHUNK_BYTES
    if switch:
        sys.setswitchinterval(switch)
    if chunk:
        P.UPLOAD_CHUNK_BYTES = chunk
    try:
        res = {}
        for what in ("one", "halves2"):
            best = None
            for _ in range(2):
                t = time.perf_counter()
                if what == "one":
                    s = photoset("cuda:0", **kw)
                    tm = [s.timings]
                else:
                    with concurrent.futures.ThreadPoolExecutor(2) as ex:
                        a = ex.submit(photoset, "cuda:0", 0, half, **kw)
                        b = ex.submit(photoset, "cuda:1", half, n, **kw)
                        tm = [a.result().timings, b.result().timings]
                wp.synchronize()
                dt = time.perf_counter() - t
                if best is None or dt < best[0]:
                    best = (dt, [round(x["upload"], 3) for x in tm])
            res[what] = best
        out["variant_" + tag] = res
        print(
            "variant %-28s one %.3f s (upload %s)   halves on 2 GPUs %.3f s (uploads %s)"
            % (tag, res["one"][0], res["one"][1], res["halves2"][0], res["halves2"][1]),
            flush=True,
        )
    finally:
        sys.setswitchinterval(old_sw)
        P.UPLOAD_CHUNK_BYTES = old_chunk


variant("default")
variant("switch_0.1ms", switch=1e-4)
variant("threads4", decode_threads=4)
variant("threads4_switch_0.1ms", switch=1e-4, decode_threads=4)
variant("chunk16MB", chunk=16 << 20)
variant("chunk16MB_threads4_switch", chunk=16 << 20, switch=1e-4, decode_threads=4)
variant("threads16_switch", switch=1e-4, decode_threads=16)


# B4: pageable whole photos straight to the device (no host staging)
def direct(dev, lo, hi):
    dst = wp.empty((hi - lo, 430, 430), dtype=wp.vec3, device=dev)
    for k in range(lo, hi):
        im = images[k]
        src = wp.array(ptr=im.ctypes.data, shape=(430, 430), dtype=wp.vec3, device="cpu")
        wp.copy(dst, src, (k - lo) * 430 * 430, 0, 430 * 430)
    wp.synchronize_device(dev)
    return dst


for tag, jobs in (
    ("one", [("cuda:0", 0, n)]),
    ("halves2", [("cuda:0", 0, half), ("cuda:1", half, n)]),
    (
        "quarters2",
        [
            ("cuda:0", 0, n // 4),
            ("cuda:0", n // 4, half),
            ("cuda:1", half, 3 * n // 4),
            ("cuda:1", 3 * n // 4, n),
        ],
    ),
):
    best = None
    for _ in range(2):
        t = time.perf_counter()
        with concurrent.futures.ThreadPoolExecutor(len(jobs)) as ex:
            rs = [ex.submit(direct, *j) for j in jobs]
            [r.result() for r in rs]
        dt = time.perf_counter() - t
        best = dt if best is None else min(best, dt)
    out["direct_pageable_" + tag] = best
    print(
        "pageable whole photos straight to the device, %s: %.3f s (%.1f GB/s)"
        % (tag, best, n * 430 * 430 * 12 / best / 1e9),
        flush=True,
    )
json.dump(out, open(os.path.join(sys.argv[1], "iteration_profile.json"), "w"), indent=1, default=str)
