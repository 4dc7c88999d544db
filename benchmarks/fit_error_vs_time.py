"""Error against wall time for SD, CG, L-BFGS and LM on a synthetic scene (writes JSON + plot).

    python benchmarks/fit_error_vs_time.py --scene ornament --scale 0.05 --device cpu --out out/bench_cpu
    python benchmarks/fit_error_vs_time.py --scene ornament --scale 1.0 --device cuda:0 --out $OUT  # GPU machine
    python benchmarks/fit_error_vs_time.py --plot-only out/bench/fit_error_vs_time.json   # replot

Renders the scene in memory (render_scene: no OpenImageIO needed), builds one StreamProblem per
optimizer, warms the kernels up (one iteration), then records the per-iteration trace.

Reported per run: fit time, passes, ms per pass, the time at which the sample PSNR first comes
within 0.1 dB of the best PSNR any run reached, and the first iteration whose objective is at or
below steepest descent's last (``--sd-iterations``, 250 for the seed's comparison).

Bytes per pass (how the bandwidth figure counts): every pass must read each photo, depth map and
shadow map once, and read/write the per-texel state: parameters, and per photo group the partial
objective, gradient (and J^T J for LM, or d^T H d) plus trace statistics, which the reduction reads
back. ``unique_bytes_per_pass`` is that sum: a lower bound of the traffic (texels that share pixels
re-read them, mostly from cache). ``--bandwidth-probe`` times a device-to-device copy of 1 GiB for
the GPU's measured bandwidth; ``bandwidth_fraction`` = unique bytes / pass time / measured. The sum
also counts each photo's background, which no texel reads, so it overstates the bytes a pass must
move; Nsight Compute measured 2.3% of DRAM peak on the filtered gradient pass, most reads served by
L1/L2 (benchmarks/pass_profile.py explains the pass time: benchmarks/results/h200_filtered/README.md).
"""

from __future__ import annotations

import argparse
import itertools
import json
import platform
import time
from pathlib import Path


def measured_bandwidth(device: str, nbytes: int = 1 << 30, reps: int = 10) -> float:
    """Bytes/s of a device-to-device copy (read + write counted)."""
    import warp as wp

    a = wp.zeros(nbytes // 4, dtype=wp.float32, device=device)
    b = wp.zeros_like(a)
    wp.copy(b, a)
    wp.synchronize_device(device)
    t0 = time.perf_counter()
    for _ in range(reps):
        wp.copy(b, a)
    wp.synchronize_device(device)
    return 2 * nbytes * reps / (time.perf_counter() - t0)


def unique_bytes_per_pass(prob, optimizer: str, diag: bool = False) -> int:
    ph = prob.photos
    per_photo = ph.image_bytes + ph.depth.capacity + ph.shadow.capacity
    word = 8 if prob.cfg.accumulate == "fp64" else 4
    npar = prob.layout.n_params  # per-texel vectors are sized to the layout
    # + the Gauss-Newton diagonal (n_params words) of preconditioned sd / cg / lbfgs passes
    partial = word * (1 + npar + (npar * npar if optimizer == "lm" else 1) + (npar if diag else 0)) + 32
    # texel frames (pos, nrm, tan, bit; + face normal and normal Jacobian for point/filtered sampling)
    frames = 4 * (12 + (12 if prob.cfg.photo_sampling != "bilinear" else 0))
    state = prob.n * (word * prob.layout.n_params + 2 * prob.groups * partial + partial + frames)
    return int(per_photo + state)


def summarise(results: dict, sd_key: str = "sd") -> None:
    runs = results["runs"]
    best = max(max(r["psnr_db"] for r in run["trace"]) for run in runs.values())
    results["best_psnr_db"] = best
    sd_obj = runs[sd_key]["trace"][-1]["objective"] if sd_key in runs else None
    if not runs:
        return
    for name, run in runs.items():
        tr = run["trace"]
        hit = next((r for r in tr if r["psnr_db"] >= best - 0.1), None)
        run["time_to_best_minus_0p1dB_s"] = None if hit is None else hit["time_s"]
        run["iterations_to_best_minus_0p1dB"] = None if hit is None else hit["iteration"]
        if sd_obj is not None:
            it = next((r["iteration"] for r in tr if r["objective"] <= sd_obj), None)
            run["iterations_to_sd_final_objective"] = it
    if sd_obj is not None:
        results["sd_final"] = {"iterations": runs[sd_key]["trace"][-1]["iteration"], "objective": sd_obj}


def plot(results: dict, out: Path) -> None:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return
    fig, ax = plt.subplots(1, 2, figsize=(11, 4))
    for opt, r in results["runs"].items():
        t = [x["time_s"] for x in r["trace"]]
        ax[0].plot(t, [x["psnr_db"] for x in r["trace"]], "o-", ms=2, label=opt)
        ax[1].semilogy([x["iteration"] for x in r["trace"]], [max(x["objective"], 1e-300) for x in r["trace"]], "-",
                       label=opt)
    ax[0].set_xlabel("wall time (s)")
    ax[0].set_ylabel("sample PSNR (dB)")
    ax[1].set_xlabel("iteration")
    ax[1].set_ylabel("objective")
    for a in ax:
        a.legend()
    fig.suptitle(f"{results['scene']} x{results['scale']} on {results['device']} "
                 f"({results.get('gpu') or results.get('machine')})")
    fig.tight_layout()
    fig.savefig(out / "fit_error_vs_time.png", dpi=110)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scene", default="ornament")
    ap.add_argument("--scale", type=float, default=0.05)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--optimizers", default="sd,cg,lbfgs,lm")
    ap.add_argument("--iterations", type=int, default=60)
    ap.add_argument("--sd-iterations", type=int, default=0, help="iterations for sd (0 = --iterations)")
    ap.add_argument("--image-precision", default="fp32", choices=("fp32", "fp16"))
    ap.add_argument("--precondition", default=None, choices=("none", "jacobi"),
                    help="sd/cg/lbfgs preconditioner (default: FitConfig's)")
    ap.add_argument("--photo-sampling", default="filtered", choices=("filtered", "point", "bilinear"))
    ap.add_argument("--model-lookup", default="texel", choices=("texel", "bilinear"), help="StreamConfig.model_lookup")
    ap.add_argument("--tap-geometry", default="plane", choices=("plane", "mesh"), help="StreamConfig.tap_geometry")
    ap.add_argument("--lookup-relaxations", default="1", help="FitConfig.lookup_relaxation values to run (comma list)")
    ap.add_argument("--lobe-albedo-max", type=float, default=None, help="FitConfig.lobe_albedo_max (0 = no energy bound)")
    ap.add_argument("--accumulate", default="fp32", choices=("fp32", "fp64"), help="StreamConfig.accumulate")
    ap.add_argument("--storage", default="fp32", choices=("fp16", "fp32", "fp64"), help="StreamConfig.storage")
    ap.add_argument("--block-dim", type=int, default=None, help="StreamConfig.cuda_block_dim (CUDA threads per block)")
    ap.add_argument("--bandwidth-probe", action="store_true")
    ap.add_argument("--out", default="out/bench")
    ap.add_argument("--plot-only", default=None, help="replot an existing JSON")
    a = ap.parse_args()
    if a.plot_only:
        p = Path(a.plot_only)
        plot(json.loads(p.read_text()), p.parent)
        return
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    from texstream.capture.synthetic.synth import SynthConfig, render_scene
    from texstream.fit.optim.fitter import FitConfig, run_fit
    from texstream.fit.stream.config import StreamConfig
    from texstream.fit.stages.stage import build_problem

    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    sc = render_scene(a.scene, SynthConfig(scale=a.scale, device=a.device, progress=False))
    t_render = time.perf_counter() - t0
    results = {"scene": a.scene, "scale": a.scale, "device": a.device, "photos": len(sc.images),
               "precondition": a.precondition or FitConfig().precondition,
               "lobe_albedo_max": FitConfig().lobe_albedo_max if a.lobe_albedo_max is None else a.lobe_albedo_max,
               "image_size": list(sc.images[0].shape[:2]), "texels": int(sc.bake.covered.sum()),
               "image_precision": a.image_precision, "accumulate": a.accumulate, "storage": a.storage, "photo_sampling": a.photo_sampling,
               "model_lookup": a.model_lookup, "tap_geometry": a.tap_geometry,
               "block_dim": a.block_dim or StreamConfig().cuda_block_dim, "render_s": t_render, "machine": platform.node(), "runs": {}}
    if a.device.startswith("cuda"):
        results["gpu"] = wp.get_device(a.device).name
    if a.bandwidth_probe:
        results["measured_bandwidth_GBps"] = measured_bandwidth(a.device) / 1e9
    relaxations = [float(x) for x in a.lookup_relaxations.split(",")]
    for opt, relax in itertools.product(a.optimizers.split(","), relaxations):
        name = opt if len(relaxations) == 1 else f"{opt}_relax{relax:g}"
        iters = a.sd_iterations if (opt == "sd" and a.sd_iterations > 0) else a.iterations
        cfg = FitConfig(optimizer=opt, max_iterations=iters, sync_every=100000, lookup_relaxation=relax,
                        stream=StreamConfig(image_precision=a.image_precision, photo_sampling=a.photo_sampling,
                                            accumulate=a.accumulate, storage=a.storage, model_lookup=a.model_lookup,
                                            tap_geometry=a.tap_geometry))
        if a.block_dim is not None:
            cfg.stream.cuda_block_dim = a.block_dim
        if a.precondition is not None:
            cfg.precondition = a.precondition
        if a.lobe_albedo_max is not None:
            cfg.lobe_albedo_max = a.lobe_albedo_max
        t0 = time.perf_counter()
        prob = build_problem(sc.mesh, sc.bake, sc.frames, sc.images, sc.masks, cfg, a.device)
        t_setup = time.perf_counter() - t0
        run_fit(prob, FitConfig(optimizer=opt, max_iterations=1, stream=cfg.stream, precondition=cfg.precondition,
                                lobe_albedo_max=cfg.lobe_albedo_max))  # compile / warm up
        prob.passes = 0
        res = run_fit(prob, cfg)
        t_fit = res.trace[-1]["time_s"]
        ub = unique_bytes_per_pass(prob, opt, diag=opt != "lm" and cfg.precondition == "jacobi")
        pass_s = t_fit / max(res.passes, 1)
        run = {"block_dim": prob.block_dim, "max_registers": prob.max_registers, "setup_s": t_setup, "fit_s": t_fit, "iterations": res.trace[-1]["iteration"], "passes": res.passes,
               "pass_ms": 1000 * pass_s, "unique_bytes_per_pass": ub, "unique_GBps": ub / pass_s / 1e9,
               "trace": res.trace}
        if "measured_bandwidth_GBps" in results:
            run["bandwidth_fraction"] = run["unique_GBps"] / results["measured_bandwidth_GBps"]
        results["runs"][name] = run
        print(name, f"{t_fit:.2f}s", res.passes, "passes", f"{1000 * pass_s:.1f} ms/pass",
              f"psnr {res.trace[-1]['psnr_db']:.2f}", flush=True)
        del prob
        summarise(results)  # written after every run: a run cut short by a time limit keeps the others
        (out / "fit_error_vs_time.json").write_text(json.dumps(results, indent=1))
    plot(results, out)
    print(json.dumps({k: v for k, v in results.items() if k != "runs"}, indent=1))
    for name, r in results["runs"].items():
        print(name, {k: (round(v, 4) if isinstance(v, float) else v) for k, v in r.items() if k != "trace"})


if __name__ == "__main__":
    main()
