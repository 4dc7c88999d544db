"""Light field mapping: time per streaming pass and per kernel of the streaming fit (writes JSON).

    python benchmarks/lfm_pass_profile.py --scene star --scale 0.1 --device cpu --out out/lfm_profile
    python benchmarks/lfm_pass_profile.py --scene star --scale 1.0 --device cuda:0 --out $OUT/lfm_profile

Renders the scene in memory, builds the photo set and one LFMProblem per ``--photo-batch`` and
``--sample-cache`` value, then per value: a warm-up fit (compiles), a timed fit of ``--iterations``
iterations (ms per pass: the fit's wall time over its passes; the diffuse pass apart), and an
instrumented fit of the same length in which every ``wp.launch`` / ``wp.copy`` is bracketed by device
synchronisations, so each kernel's wall time (launch overhead included) is summed by kernel name. The
instrumented times add the synchronisations' cost; the plain time is the one to quote.
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from collections import defaultdict
from pathlib import Path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="star")
    ap.add_argument("--scale", type=float, default=0.1)
    ap.add_argument("--photos", type=int, default=0, help="photo count (0: the scene's x scale)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--terms", type=int, default=1)
    ap.add_argument("--optimizer", default="cg")
    ap.add_argument("--iterations", type=int, default=10)
    ap.add_argument("--photo-batch", default="0", help="comma list of LFMConfig.photo_batch values (0: auto)")
    ap.add_argument("--sample-cache", default="auto", help="comma list of LFMConfig.sample_cache values")
    ap.add_argument("--holdout-every", type=int, default=8)
    ap.add_argument("--out", default="out/lfm_profile")
    a = ap.parse_args()
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    from texstream.capture.synthetic.synth import SynthConfig, render_scene
    from texstream.fit.optim.fitter import FitConfig
    from texstream.fit.models.lfm.problem import LFMConfig, LFMProblem, PhotoSamples, fit_lfm
    from texstream.fit.models.lfm.model_folder import lfm_geometry
    from texstream.fit.stages.stage import build_problem, split_holdout

    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    sc = render_scene(a.scene, SynthConfig(scale=a.scale, device=a.device, progress=False, photos=a.photos))
    index = {id(f): i for i, f in enumerate(sc.frames)}
    frames, _ = split_holdout(sc.frames, a.holdout_every)
    images = [sc.images[index[id(f)]] for f in frames]
    masks = [sc.masks[index[id(f)]] for f in frames]
    sp = build_problem(sc.mesh, sc.bake, frames, images, masks, FitConfig(model="radiance"), a.device)
    geom = lfm_geometry(sc.mesh, sc.bake, sp.texels)
    results = {"scene": a.scene, "scale": a.scale, "device": a.device, "machine": platform.node(),
               "photos_fitted": len(frames), "texels": int(geom.n_texels),
               "welded_vertices": int(geom.n_vertices),
               "terms": a.terms, "optimizer": a.optimizer, "iterations": a.iterations, "runs": []}
    if a.device.startswith("cuda"):
        results["gpu"] = wp.get_device(a.device).name
    print(f"{a.scene} x{a.scale}: {len(frames)} photos, {geom.n_texels} texels, {geom.n_vertices} vertices",
          flush=True)

    real_launch, real_copy = wp.launch, wp.copy

    def timed(fn, name_of, totals, counts):
        def wrapper(*args, **kwargs):
            wp.synchronize_device(a.device)
            t = time.perf_counter()
            r = fn(*args, **kwargs)
            wp.synchronize_device(a.device)
            name = name_of(args, kwargs)
            totals[name] += time.perf_counter() - t
            counts[name] += 1
            return r
        return wrapper

    for batch, cache in [(int(b), c) for c in a.sample_cache.split(",") for b in a.photo_batch.split(",")]:
        cfg = LFMConfig(terms=a.terms, optimizer=a.optimizer, iterations=a.iterations, rel_tol=0.0,
                        sync_every=a.iterations, photo_batch=batch, sample_cache=cache)
        pr = LFMProblem(geom, PhotoSamples(sp, frames), cfg, a.device)
        fit_lfm(pr, max_iterations=2)                       # compile, warm caches
        pr = LFMProblem(geom, PhotoSamples(sp, frames), cfg, a.device)
        pr.compute_diffuse()
        wp.synchronize_device(a.device)
        passes0 = pr.passes
        t = time.perf_counter()
        res = fit_lfm(pr)
        wp.synchronize_device(a.device)
        wall = time.perf_counter() - t
        n_pass = pr.passes - passes0
        totals, counts = defaultdict(float), defaultdict(int)
        kernel_name = lambda args, kw: getattr(args[0] if args else kw["kernel"], "key", "?")  # noqa: E731
        wp.launch = timed(real_launch, kernel_name, totals, counts)
        wp.copy = timed(real_copy, lambda args, kw: "wp.copy", totals, counts)
        try:
            pr2 = LFMProblem(geom, PhotoSamples(sp, frames), cfg, a.device)
            pr2.compute_diffuse()
            totals.clear()
            counts.clear()
            t = time.perf_counter()
            fit_lfm(pr2)
            wp.synchronize_device(a.device)
            wall_instr = time.perf_counter() - t
        finally:
            wp.launch, wp.copy = real_launch, real_copy
        kernels = [{"name": k, "ms_per_pass": 1000 * v / n_pass, "calls": counts[k], "share": v / wall_instr}
                   for k, v in totals.items()]
        kernels.sort(key=lambda r: -r["ms_per_pass"])
        run = {"photo_batch": pr.B, "sample_cache": pr.cache, "passes": n_pass, "fit_s": wall,
               "ms_per_pass": 1000 * wall / n_pass,
               "objective": res.trace[-1]["objective"], "instrumented_s": wall_instr, "kernels": kernels,
               "state_bytes": res.state_bytes}
        results["runs"].append(run)
        print(f"photo_batch {pr.B}, sample cache {pr.cache}: {n_pass} passes, "
              f"{run['ms_per_pass']:.1f} ms/pass, objective {run['objective']:.10g}", flush=True)
        for r in kernels[:10]:
            print(f"   {r['name']:<32} {r['ms_per_pass']:8.2f} ms/pass  {r['calls']:6d} calls  "
                  f"{100 * r['share']:5.1f}%")
        (out / "lfm_pass_profile.json").write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
