"""Error against wall time for SD, CG, L-BFGS and LM on the synthetic ornament (writes JSON + plot).

    python benchmarks/fit_error_vs_time.py --scale 0.05 --device cpu --out out/bench_cpu
    python benchmarks/fit_error_vs_time.py --scale 1.0 --device cuda:0 --out $OUT   # GPU machine

Renders the scene in memory (render_scene: no OpenImageIO needed), builds one StreamProblem per
optimizer and records the per-iteration trace. Byte counting for bandwidth: each pass reads the
photo stack once per visible (texel, photo) sample at most; we report photo-stack bytes per pass
divided by the pass time as an upper bound of streamed bandwidth, and say so.
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scene", default="ornament")
    ap.add_argument("--scale", type=float, default=0.05)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--optimizers", default="sd,cg,lbfgs,lm")
    ap.add_argument("--iterations", type=int, default=60)
    ap.add_argument("--out", default="out/bench")
    a = ap.parse_args()
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    from texstream.capture.synth import SynthConfig, render_scene
    from texstream.fit.fitter import FitConfig, run_fit
    from texstream.fit.stage import build_problem

    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    sc = render_scene(a.scene, SynthConfig(scale=a.scale, device=a.device, progress=False))
    t_render = time.perf_counter() - t0
    results = {"scene": a.scene, "scale": a.scale, "device": a.device, "photos": len(sc.images),
               "image_size": list(sc.images[0].shape[:2]), "texels": int(sc.bake.covered.sum()),
               "render_s": t_render, "machine": platform.node(), "runs": {}}
    if a.device.startswith("cuda"):
        results["gpu"] = wp.get_device(a.device).name
    for opt in a.optimizers.split(","):
        cfg = FitConfig(optimizer=opt, max_iterations=a.iterations, sync_every=1000)
        t0 = time.perf_counter()
        prob = build_problem(sc.mesh, sc.bake, sc.frames, sc.images, sc.masks, cfg, a.device)
        t_setup = time.perf_counter() - t0
        run_fit(prob, FitConfig(optimizer=opt, max_iterations=1))  # compile / warm up
        prob.passes = 0
        res = run_fit(prob, cfg)
        t_fit = res.trace[-1]["time_s"]
        results["runs"][opt] = {"setup_s": t_setup, "fit_s": t_fit, "passes": res.passes,
                                "pass_ms": 1000 * t_fit / max(res.passes, 1),
                                "photo_bytes_per_pass": prob.photos.image_bytes,
                                "upper_bound_GBps": prob.photos.image_bytes * res.passes / max(t_fit, 1e-9) / 1e9,
                                "trace": res.trace}
        print(opt, f"{t_fit:.2f}s", res.passes, "passes", f"psnr {res.trace[-1]['psnr_db']:.2f}", flush=True)
    (out / "fit_error_vs_time.json").write_text(json.dumps(results, indent=1))
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(6, 4))
        for opt, r in results["runs"].items():
            ax.plot([x["time_s"] for x in r["trace"]], [x["psnr_db"] for x in r["trace"]], "o-", ms=2, label=opt)
        ax.set_xlabel("wall time (s)")
        ax.set_ylabel("sample PSNR (dB)")
        ax.set_title(f"{a.scene} x{a.scale} on {a.device}")
        ax.legend()
        fig.tight_layout()
        fig.savefig(out / "fit_error_vs_time.png", dpi=110)
    except ImportError:
        pass


if __name__ == "__main__":
    main()
