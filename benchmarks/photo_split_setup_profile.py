"""Where the photos' set-up goes with two GPUs (photos split, fit/photo_split.py): host crops by thread count,
pinned host-to-device copies, the upload pipeline, two halves set up at once (on two GPUs and on one), and one
LM pass per half; writes JSON and prints a log.

    python benchmarks/photo_split_setup_profile.py OUT_DIR     # on a machine with two CUDA GPUs
"""

import concurrent.futures
import json
import math
import os
import sys
import time

import warp as wp

import texstream.fit.stream.photo_set as P
from texstream.fit.kernels import accumulate
from photo_split_scene import OrnamentAt4x
from texstream.fit.optim.fitter import FitConfig, FitRun
from texstream.fit.stream.photo_stream import PhotoLoader
from texstream.fit.stream.config import StreamConfig
from texstream.fit.stages.stage import build_problem

wp.config.quiet = True
wp.init()

out = {}
scene = OrnamentAt4x("cuda:0")
mesh, frames, images, masks, bake = scene.mesh, scene.frames, scene.images, scene.masks, scene.bake
photoset = scene.photoset
for rep in range(3):
    t = time.perf_counter()
    ps = photoset("cuda:0")
    wp.synchronize()
    out.setdefault("photoset_one_gpu", []).append([time.perf_counter() - t, ps.timings])
print("one gpu", out["photoset_one_gpu"][-1], flush=True)
print(
    "crop",
    ps.hmax,
    ps.wmax,
    "photos",
    ps.n,
    "image shape",
    images[0].shape,
    images[0].dtype,
    images[0].flags["C_CONTIGUOUS"],
    "mask",
    None if masks[0] is None else (masks[0].shape, masks[0].dtype),
    flush=True,
)
out["crop"] = [ps.hmax, ps.wmax]
crops, sizes = ps.crops, ps.sizes
n = ps.n
# host crops only, into a pageable and a pinned buffer, with 4/8/16/32 threads
for pinned in (False, True):
    buf = wp.empty((n, ps.hmax, ps.wmax), dtype=wp.vec3, device="cpu", pinned=pinned)
    mb = wp.empty((n, ps.hmax, ps.wmax), dtype=wp.uint8, device="cpu", pinned=pinned)
    arr, marr = buf.numpy(), mb.numpy()
    for threads in (1, 4, 8, 16, 32):
        ld = PhotoLoader(images, masks, crops, sizes, threads)
        ld.fill(range(n), arr, marr)  # touch
        t = time.perf_counter()
        ld.fill(range(n), arr, marr)
        dt = time.perf_counter() - t
        ld.close()
        out[f"host_crop_pinned{int(pinned)}_t{threads}"] = dt
        print(
            "host crop pinned",
            pinned,
            "threads",
            threads,
            "%.3f s  %.1f GB/s written" % (dt, arr.nbytes / dt / 1e9),
            flush=True,
        )
    del buf, mb, arr, marr
# H2D from pinned, 64 MB chunks, one GPU and both at once
chunk = wp.empty(64 << 20 >> 2, dtype=float, device="cpu", pinned=True)
dst = {d: wp.empty(64 << 20 >> 2, dtype=float, device=d) for d in ("cuda:0", "cuda:1")}
for devs in (["cuda:0"], ["cuda:1"], ["cuda:0", "cuda:1"]):
    for d in devs:
        wp.copy(dst[d], chunk)
    wp.synchronize()
    t = time.perf_counter()
    for _ in range(30):
        for d in devs:
            wp.copy(dst[d], chunk)
    wp.synchronize()
    dt = time.perf_counter() - t
    out["h2d_" + "+".join(devs)] = 30 * len(devs) * 64 / 1024 / dt
    print("H2D", devs, "%.1f GB/s total" % (30 * len(devs) * (64 << 20) / dt / 1e9), flush=True)
# the upload pipeline instrumented: time waiting for fills vs the rest
waits = []
orig_wait = P.wait


def timed_wait(fs):
    t = time.perf_counter()
    r = orig_wait(fs)
    waits.append(time.perf_counter() - t)
    return r


P.wait = timed_wait
for threads in (8, 16):
    waits.clear()
    t = time.perf_counter()
    ps = photoset("cuda:0", decode_threads=threads)
    wp.synchronize()
    dt = time.perf_counter() - t
    out[f"pipeline_t{threads}"] = [dt, ps.timings, sum(waits), len(waits)]
    print(
        "pipeline threads",
        threads,
        "%.3f" % dt,
        ps.timings,
        "waiting for fills %.3f s in %d" % (sum(waits), len(waits)),
        flush=True,
    )
P.wait = orig_wait
# two halves at once, on two GPUs and on one, and each alone
half = n // 2
for devs in (("cuda:0", "cuda:1"), ("cuda:0", "cuda:0")):
    for rep in range(2):
        t = time.perf_counter()
        with concurrent.futures.ThreadPoolExecutor(2) as ex:
            a = ex.submit(photoset, devs[0], 0, half)
            b = ex.submit(photoset, devs[1], half, n)
            pa, pb = a.result(), b.result()
        wp.synchronize()
        dt = time.perf_counter() - t
    out["halves_" + "+".join(devs)] = [dt, pa.timings, pb.timings]
    print("halves at once", devs, "%.3f" % dt, pa.timings, pb.timings, flush=True)
for d, lo, hi in (("cuda:0", 0, half), ("cuda:1", half, n)):
    t = time.perf_counter()
    p1 = photoset(d, lo, hi)
    wp.synchronize()
    dt = time.perf_counter() - t
    out[f"half_alone_{d}_{lo}"] = [dt, p1.timings]
    print("half alone", d, lo, "%.3f" % dt, p1.timings, flush=True)
# balance of the split passes: each part's LM pass alone
cfg = FitConfig(
    optimizer="lm",
    stream=StreamConfig(
        image_precision="fp16", photo_residency="device", devices="cuda:0,cuda:1", device_split="photos"
    ),
)
pr = build_problem(mesh, bake, frames, images, masks, cfg, "cuda:0")

run = FitRun(pr, cfg)
run.begin()
st = run.state
for name, prob in (("part0", pr), ("part1", pr.peers[0])):
    ins = {
        "params": st.storage if prob is pr else pr._to_peers(params=st.storage)[0]["params"],
        "active": None,
    }

    kernel = accumulate.accumulate_lm_kernel(
        pr.layout.n_lobes,
        int(pr.layout.anisotropic),
        pr.max_registers,
        pr.lookup,
        pr.traced,
        pr.radiance,
        pr.robust,
    )
    wp.synchronize()
    ts = []
    for _ in range(5):
        t = time.perf_counter()
        images_, depth, shadow, infos, b, e = next(iter(prob.own_photos.windows()))
        if prob.pm is None:
            prob.pm = wp.zeros((prob.rows, prob.n), dtype=prob.mat, device=prob.device)
        wp.launch(
            kernel,
            dim=(prob.groups, prob.n),
            device=prob.device,
            block_dim=prob.block_dim,
            inputs=[
                prob.tex,
                ins["params"],
                prob.all_active,
                images_,
                depth,
                shadow,
                infos,
                b,
                e,
                math.ceil((e - b) / prob.groups),
                prob.opt,
                prob.like,
                prob.like_m,
                prob.one,
            ],
            outputs=[prob.pf, prob.pg, prob.pm, prob.pst],
        )
        wp.synchronize_device(prob.device)
        ts.append(time.perf_counter() - t)
    out["pass_" + name] = ts
    print("LM pass", name, ["%.1f ms" % (x * 1e3) for x in ts], flush=True)
ts = []
for _ in range(5):
    wp.synchronize()
    t = time.perf_counter()
    pr.evaluate_lm(st.storage, st.f_trial, st.g_trial, run.opt.jtj_trial, st.stats_trial)
    wp.synchronize()
    ts.append(time.perf_counter() - t)
out["pass_split"] = ts
print("LM pass split", ["%.1f ms" % (x * 1e3) for x in ts], flush=True)
json.dump(out, open(os.path.join(sys.argv[1], "setup_profile.json"), "w"), indent=1, default=str)
