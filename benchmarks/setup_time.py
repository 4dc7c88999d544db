"""Set-up phases, fit loop and peak memory of a fit, per photo residency (writes JSON).

    python benchmarks/setup_time.py --device cpu --scene ornament --scale 0.05 --out out/setup_cpu
    python benchmarks/setup_time.py --device cuda:0 --scene ornament --scale 1.0 --out $OUT   # GPU machine
    python benchmarks/setup_time.py --device cpu --scale 0.1 --source disk --residency device,host,disk --out DIR

Each residency runs in a child process of its own, so its peak host memory (``ru_maxrss``) is its own:

- ``--source memory``: the child renders the scene in memory (``render_scene``; no OpenImageIO) and
  hands the arrays to the fit, as benchmarks/fit_error_vs_time.py does; the rendered photos count in
  its peak memory (reported separately as ``rss_after_inputs_mib``).
- ``--source disk``: the parent writes the capture folder once (float EXR, ``synthesize``; needs
  OpenImageIO), and each child fits it from its files, as ``texstream fit`` does: the photos are
  decoded on the fit's threads, all at set-up (device, host) or a window per pass (disk).

Reported per run (``runs[residency]``): the set-up's phases (``PhotoSet.timings``: upload = filling the
buffers (decode or copy, crop, convert) and host-to-device copies; depth_maps; shadow_maps; other =
per-photo constants, crops, allocation) and the rest of the problem's set-up (texels), each phase
ended by a device synchronisation; the fit loop (LM, ``--iterations``) after a one-iteration warm-up
that compiles the passes; the time to a converged model (set-up + the fit's time to within 0.1 dB of
its best PSNR); peak host RSS and, on CUDA, the peak of Warp's memory pool. Kernels are compiled and
loaded before the timed set-up (a set-up of two photos first), so no figure includes compilation.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path


def rss_mib() -> float:
    """Current resident set size of this process (MiB)."""
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return float("nan")


def peak_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # KiB on Linux


def child(a) -> dict:
    """One residency's set-up and fit, in this process."""
    import numpy as np
    import warp as wp

    wp.config.quiet = True
    wp.init()
    if a.recompute_maps:
        import texstream.fit.stream.photo_set as problem

        problem.keep_maps_on_device = lambda *args, **kw: False
    from texstream.fit.optim.fitter import FitConfig, run_fit
    from texstream.fit.stream.config import StreamConfig
    from texstream.fit.stages.stage import build_problem

    def stream_config(**kw):
        # options the checkout lacks are left out (a reference run on a commit before them)
        known = {f.name for f in dataclasses.fields(StreamConfig)}
        return StreamConfig(**{k: v for k, v in kw.items() if k in known})

    stream = stream_config(image_precision=a.image_precision, photo_residency=a.residency,
                           shadow_map_size=a.shadow_map_size,
                           photos_per_window=a.photos_per_window, memory_limit_mb=a.memory_limit_mb,
                           decode_threads=a.decode_threads)
    cfg = FitConfig(optimizer="lm", max_iterations=a.iterations, sync_every=100000, stream=stream)
    rss_start = rss_mib()
    if a.source == "disk":
        from texstream.capture.capture_json import read_capture
        from texstream.fit.stages.stage import load_geometry, photo_files

        cap_dir = Path(a.capture)
        capture = read_capture(cap_dir)
        mesh, bake = load_geometry(cap_dir / "ground_truth", 256, "cpu")
        frames = capture.frames
        photos, masks = photo_files(capture, frames), None
        warm = photo_files(capture, frames[:2]), None
    else:
        from texstream.capture.synthetic.synth import SynthConfig, render_scene

        sc = render_scene(a.scene, SynthConfig(scale=a.scale, device=a.device, progress=False, photos=a.photos,
                                               image_size=a.image_size))
        mesh, bake, frames, photos, masks = sc.mesh, sc.bake, sc.frames, sc.images, sc.masks
        warm = photos[:2], masks[:2]
    rss_inputs = rss_mib()
    # compile and load every set-up kernel on two photos first
    warm_cfg = FitConfig(optimizer="lm", max_iterations=1, stream=stream_config(
        image_precision=a.image_precision, shadow_map_size=a.shadow_map_size,
        photo_residency="device" if a.residency == "auto" else a.residency,
        photos_per_window=1 if a.residency in ("host", "disk") else 0))
    wprob = build_problem(mesh, bake, frames[:2], warm[0], warm[1], warm_cfg, a.device)
    run_fit(wprob, warm_cfg)
    del wprob
    wp.synchronize_device(a.device)
    cuda = a.device.startswith("cuda")
    # device peak: Warp's memory pool high-water mark (a Warp without the pool queries: the free memory
    # after the fit, a lower bound of the peak)
    pool = cuda and hasattr(wp, "get_mempool_used_mem_high") and wp.is_mempool_enabled(a.device)
    if pool:
        wp.set_mempool_release_threshold(a.device, 0)
    dev_before = wp.get_mempool_used_mem_current(a.device) if pool else 0
    high_before = wp.get_mempool_used_mem_high(a.device) if pool else 0  # the render's and warm-up's, no reset
    free_before = wp.get_device(a.device).free_memory if cuda else 0
    t0 = time.perf_counter()
    prob = build_problem(mesh, bake, frames, photos, masks, cfg, a.device)
    wp.synchronize_device(a.device)
    setup_s = time.perf_counter() - t0
    ph = prob.photos
    phases = dict(getattr(ph, "timings", {}))  # absent before the batched set-up (the reference run)
    phases["texels_and_problem"] = setup_s - sum(phases.values())
    profile = None
    if a.profile:  # a second set-up under cProfile, after the timed one: where the host's time goes
        import cProfile
        import io
        import pstats

        prof = cProfile.Profile()
        prof.enable()
        again = build_problem(mesh, bake, frames, photos, masks, cfg, a.device)
        wp.synchronize_device(a.device)
        prof.disable()
        del again
        text = io.StringIO()
        pstats.Stats(prof, stream=text).sort_stats("cumulative").print_stats(45)
        profile = text.getvalue()
    tw = time.perf_counter()
    # compile the passes (from disk: also the first decoding of every photo, into the photo cache)
    warm_res = run_fit(prob, FitConfig(optimizer="lm", max_iterations=1, stream=stream))
    wp.synchronize_device(a.device)
    warm_s, warm_passes = time.perf_counter() - tw, prob.passes
    prob.passes = 0
    t1 = time.perf_counter()
    res = run_fit(prob, cfg)
    wp.synchronize_device(a.device)
    fit_wall = time.perf_counter() - t1
    tr = res.trace
    best = max(r["psnr_db"] for r in tr)
    hit = next(r for r in tr if r["psnr_db"] >= best - 0.1)
    loader = getattr(ph, "loader", None)
    cache = getattr(loader, "cache", None) if loader is not None else None
    out = {"residency": getattr(ph, "residency", "device"), "residency_reason": getattr(ph, "residency_reason", ""),
           "photo_cache": None if cache is None else {"ready": bool(cache.ready), "bytes": int(cache.nbytes)},
           "photos_per_window": int(ph.window), "photos": int(ph.n), "texels": int(prob.n),
           "stored_photo_size": [int(ph.hmax), int(ph.wmax)],
           "photo_size": [int(frames[0].intrinsics.height), int(frames[0].intrinsics.width)],
           "setup_s": setup_s, "setup_phases_s": phases, "fit_loop_s": fit_wall, "iterations": tr[-1]["iteration"],
           "passes": res.passes, "pass_ms": 1000 * fit_wall / max(res.passes, 1),
           "warmup_fit_s": warm_s, "warmup_passes": int(warm_passes or warm_res.passes),
           "final_psnr_db": tr[-1]["psnr_db"], "final_objective": tr[-1]["objective"],
           "fit_time_to_best_minus_0p1dB_s": hit["time_s"], "iterations_to_best_minus_0p1dB": hit["iteration"],
           "converged_model_s": setup_s + hit["time_s"],
           "profile": profile, "rss_start_mib": rss_start, "rss_after_inputs_mib": rss_inputs, "peak_rss_mib": peak_rss_mib()}
    if cuda:
        if pool:
            high = wp.get_mempool_used_mem_high(a.device)
            out["device_pool_high_before_setup_mib"] = high_before / 2 ** 20
            # the set-up and fit's own peak, when it rose above what came before (else only bounded by it)
            out["device_peak_mib"] = (high - dev_before) / 2 ** 20 if high > high_before else None
        else:
            out["device_in_use_after_fit_mib"] = (free_before - wp.get_device(a.device).free_memory) / 2 ** 20
        out["gpu"] = wp.get_device(a.device).name
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--scene", default="ornament")
    ap.add_argument("--scale", type=float, default=0.05)
    ap.add_argument("--out", default="out/setup_time")
    ap.add_argument("--photos", type=int, default=0, help="SynthConfig.photos (0: the scene's count x scale)")
    ap.add_argument("--image-size", type=int, default=0, help="SynthConfig.image_size (0: the scene's x sqrt(scale))")
    ap.add_argument("--shadow-map-size", type=int, default=512, help="StreamConfig.shadow_map_size")
    ap.add_argument("--source", default="memory", choices=("memory", "disk"))
    ap.add_argument("--residency", default="auto", help="comma list of StreamConfig.photo_residency values")
    ap.add_argument("--photos-per-window", type=int, default=0, help="StreamConfig.photos_per_window")
    ap.add_argument("--memory-limit-mb", type=float, default=0.0, help="StreamConfig.memory_limit_mb")
    ap.add_argument("--image-precision", default="fp16", choices=("fp16", "fp32"))
    ap.add_argument("--iterations", type=int, default=10)
    ap.add_argument("--decode-threads", type=int, default=0, help="StreamConfig.decode_threads (0: its default)")
    ap.add_argument("--capture", default=None, help="(child) the capture folder")
    ap.add_argument("--profile", action="store_true", help="also profile a second set-up (cProfile, cumulative) into "
                                                           "the JSON's profile and OUT/profile_RESIDENCY.txt")
    ap.add_argument("--recompute-maps", action="store_true", help="photos streamed from disk: recompute each window's "
                                                                   "depth and shadow maps even where the device has "
                                                                   "room to keep them (as larger captures must)")
    ap.add_argument("--reuse-capture", action="store_true", help="with --source disk: fit OUT/capture as it is when "
                                                                  "it exists (written by an earlier run)")
    ap.add_argument("--child", action="store_true", help="(internal) run one residency and print its JSON")
    a = ap.parse_args()
    if a.child:
        print("RESULT " + json.dumps(child(a)), flush=True)
        return
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    results = {"scene": a.scene, "scale": a.scale, "photos": a.photos, "image_size": a.image_size,
               "shadow_map_size": a.shadow_map_size, "device": a.device, "source": a.source,
               "image_precision": a.image_precision, "iterations": a.iterations, "machine": platform.node(),
               "command": "python benchmarks/setup_time.py " + " ".join(sys.argv[1:]), "runs": {}}
    sys.path.insert(0, str(Path(__file__).parent))
    from gitinfo import commit

    results["commit"] = commit()
    capture = out / "capture"
    if a.source == "disk" and a.reuse_capture and (capture / "capture.json").is_file():
        results["write_capture_s"] = None  # written by an earlier run
        results["capture_bytes"] = sum(p.stat().st_size for p in (capture / "images").iterdir())
    elif a.source == "disk":
        from texstream.capture.synthetic.synth import SynthConfig, synthesize

        t0 = time.perf_counter()
        synthesize(a.scene, capture, SynthConfig(scale=a.scale, device=a.device, progress=False, preview=False,
                                                 photos=a.photos, image_size=a.image_size))
        results["write_capture_s"] = time.perf_counter() - t0
        results["capture_bytes"] = sum(p.stat().st_size for p in (capture / "images").iterdir())
    names = a.residency.split(",")
    for k, residency in enumerate(names):
        # a residency named again (device,device,device: repeated runs) is keyed device#2, device#3
        key = residency if names.index(residency) == k else f"{residency}#{names[:k + 1].count(residency)}"
        cmd = [sys.executable, __file__, "--child", "--device", a.device, "--scene", a.scene, "--scale", str(a.scale),
               "--source", a.source, "--residency", residency, "--photos-per-window", str(a.photos_per_window),
               "--memory-limit-mb", str(a.memory_limit_mb), "--image-precision", a.image_precision,
               "--iterations", str(a.iterations), "--capture", str(capture), "--photos", str(a.photos),
               "--image-size", str(a.image_size), "--shadow-map-size", str(a.shadow_map_size),
               "--decode-threads", str(a.decode_threads)] + (["--profile"] if a.profile else []) + (
                   ["--recompute-maps"] if a.recompute_maps else [])
        proc = subprocess.run(cmd, capture_output=True, text=True)
        line = next((x for x in proc.stdout.splitlines() if x.startswith("RESULT ")), None)
        if line is None:
            results["runs"][key] = {"error": (proc.stderr or proc.stdout)[-2000:]}
            print(residency, "failed:", (proc.stderr or proc.stdout)[-2000:], flush=True)
        else:
            run = json.loads(line[len("RESULT "):])
            results["runs"][key] = run
            if run.get("profile"):
                (out / f"profile_{key.replace('#', '_')}.txt").write_text(run["profile"])
            ph = run["setup_phases_s"]
            print(f"{residency} -> {run['residency']} ({run['photos_per_window']}/window): "
                  f"set-up {run['setup_s']:.3f} s "
                  f"({', '.join(f'{k} {v:.3f}' for k, v in ph.items())}); fit {run['fit_loop_s']:.3f} s "
                  f"({run['pass_ms']:.1f} ms/pass); converged model {run['converged_model_s']:.3f} s; "
                  f"peak RSS {run['peak_rss_mib']:.0f} MiB" +
                  (f", device {run['device_peak_mib']:.0f} MiB" if run.get("device_peak_mib") else ""), flush=True)
        (out / "setup_time.json").write_text(json.dumps(results, indent=1))
    print(out / "setup_time.json")


if __name__ == "__main__":
    main()
