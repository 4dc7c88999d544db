"""Light field mapping: held-out error against wall time for streaming CG / SD / L-BFGS and for PCA / NMF
(including their gathering and resampling), and memory as the photo count grows (writes JSON + PNG).

    python benchmarks/lfm_error_vs_time.py --scene star --scale 0.1 --device cpu --out out/lfm_cpu
    python benchmarks/lfm_error_vs_time.py --scene star --scale 1.0 --device cuda:0 --out $OUT/gpu   # GPU machine
    python benchmarks/lfm_error_vs_time.py --plot-only out/lfm_cpu/lfm_error_vs_time.json             # replot

Renders the scene in memory (render_scene: no OpenImageIO; the built-in ``star`` is procedural, so no
xatlas either), holds out every ``--holdout-every``-th photo, builds the photo set once (set-up: photo
upload, depth maps; timed apart) and then, per K and method, a fresh LFMProblem:

- stream methods (``cg``, ``sd``, ``lbfgs``; ``sd`` is the dissertation's: backtracking, no gauge
  balancing): the time starts before the diffuse pass and every ``--sync-every`` iterations the
  held-out photos are rendered and scored (foreground pixels: the render's coverage and the photo's
  mask). The scoring time is excluded from the wall time.
- ``pca``, ``nmf`` (fit/lfm_baselines.py): one point, the time of diffuse + gathering + resampling +
  factorization.

Scores per point: pooled held-out PSNR (peak 1) and APE (%), as ``texstream eval``. Per run: the time to
come within 0.1 dB of the run's own best held-out PSNR ("converged"), and for streaming the time of the
diffuse pass plus the fit (every photo streamed through each pass).

Memory (``--memory-fractions``): for subsets of the fitted photos, the device bytes the streaming fit holds
(the problem's buffers and the optimizer's model-sized vectors: O(model), the same for any photo count)
against what PCA holds on the host (every sample gathered: photos x texels, float64; the resampled matrices:
ring slots x view directions), measured by running both on each subset; and the photos on the device, which
both read.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import platform
import time
from pathlib import Path

import numpy as np

STREAM = {"cg": dict(optimizer="cg", step="hessian"),
          "cg_jacobi": dict(optimizer="cg", step="hessian", precondition="jacobi"),
          "lbfgs": dict(optimizer="lbfgs", step="hessian"),
          "lbfgs_unit": dict(optimizer="lbfgs", step="backtrack"),
          "sd": dict(optimizer="sd", step="backtrack", balance_every=0)}
BASELINES = ("pca", "nmf")


def heldout_scores(renderer_factory, params, held, held_images, held_masks) -> dict:
    """Pooled PSNR, worst view PSNR and APE over the held-out photos' foreground pixels."""
    from texstream.fit.common.model_folder import image_metrics, pooled_psnr

    render = renderer_factory(params)
    rows, abs_err, abs_ref = [], 0.0, 0.0
    for f, photo, mask in zip(held, held_images, held_masks):
        image, cover = render(f)
        m = cover & (mask if mask is not None else True)
        rows.append(image_metrics(image, photo, m))
        d = np.abs(image[m] - photo[m]).astype(np.float64)
        abs_err += float(d.sum())
        abs_ref += float(np.abs(photo[m]).sum())
    pooled = pooled_psnr(rows)
    return {"psnr_db": pooled["pooled_psnr_db"], "worst_psnr_db": pooled["worst_psnr_db"],
            "ape_percent": 100.0 * abs_err / max(abs_ref, 1e-300)}


def converged_time(trace: list, tol_db: float = 0.1):
    best = max(r["psnr_db"] for r in trace)
    hit = next(r for r in trace if r["psnr_db"] >= best - tol_db)
    return hit["time_s"], hit["iteration"]


def plot(results: dict, out: Path) -> None:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib missing: no PNG (the JSON has every number)")
        return
    fig, ax = plt.subplots(1, 2, figsize=(12, 4.4))
    colors = {"cg": "C0", "lbfgs": "C1", "lbfgs_unit": "C4", "sd": "C2", "pca": "C3", "nmf": "C5"}
    for name, r in results["runs"].items():
        c = colors.get(r["method"], "k")
        ls = "-" if r["terms"] == 1 else "--"
        if r["trace"]:
            ax[0].plot([max(x["time_s"], 1e-3) for x in r["trace"]], [x["psnr_db"] for x in r["trace"]], ls, color=c,
                       marker="o", ms=2, label=f"{r['method']} K={r['terms']}")
        else:
            ax[0].plot([r["total_s"]], [r["heldout"]["psnr_db"]], "s" if r["terms"] == 1 else "D", color=c, ms=7,
                       label=f"{r['method']} K={r['terms']}")
    ax[0].set_xscale("log")
    ax[0].set_xlabel("wall time (s), diffuse pass + fit (PCA/NMF: + gathering and resampling)")
    ax[0].set_ylabel("held-out pooled PSNR (dB)")
    ax[0].legend(fontsize=7, ncol=2)
    mem = results.get("memory", [])
    if mem:
        p = [m["photos"] for m in mem]
        for key, lab in (("stream_state_bytes", "streaming state (device)"), ("pca_samples_bytes", "PCA: all samples"),
                         ("pca_matrix_bytes", "PCA: resampled matrices"), ("photo_bytes", "photos on the device (both)")):
            ax[1].plot(p, [m[key] / 2 ** 20 for m in mem], "o-", label=lab)
        ax[1].set_xlabel("fitted photos")
        ax[1].set_ylabel("MiB")
        ax[1].legend(fontsize=8)
    fig.suptitle(f"LFM {results['scene']} x{results['scale']}: {results['photos_fitted']} photos, "
                 f"{results['texels']} texels, {results['triangles']} triangles on {results['device']} "
                 f"({results.get('gpu') or results['machine']})", fontsize=9)
    fig.tight_layout()
    fig.savefig(out / "lfm_error_vs_time.png", dpi=110)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", default="star")
    ap.add_argument("--scale", type=float, default=0.1)
    ap.add_argument("--photos", type=int, default=0, help="photo count (0: the scene's x scale)")
    ap.add_argument("--image-size", type=int, default=0, help="photo side in pixels (0: the scene's x sqrt(scale))")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--methods", default="cg,lbfgs,sd,pca,nmf",
                    help=f"comma list of {sorted(STREAM)} and {list(BASELINES)}")
    ap.add_argument("--terms", default="1,2", help="comma list of K")
    ap.add_argument("--view-res", type=int, default=8)
    ap.add_argument("--iterations", type=int, default=100, help="stream iteration cap (sd: --sd-iterations)")
    ap.add_argument("--sd-iterations", type=int, default=250)
    ap.add_argument("--rel-tol", type=float, default=1e-7, help="LFMConfig.rel_tol (stream stopping test)")
    ap.add_argument("--sync-every", type=int, default=5, help="iterations between held-out scores")
    ap.add_argument("--nmf-iterations", type=int, default=200)
    ap.add_argument("--holdout-every", type=int, default=8)
    ap.add_argument("--render-views", default="point",
                    help="comma list of LFMConfig.render_view values each final model is scored with (the first one "
                         "is the primary score): point (the interpolated view, Chen et al.'s renderer) and/or vertex "
                         "(each vertex's own view direction, what the fit assumes)")
    ap.add_argument("--memory-fractions", default="0.25,0.5,1", help="fitted-photo fractions for the memory sweep "
                                                                    "('' = none)")
    ap.add_argument("--out", default="out/lfm_error_vs_time")
    ap.add_argument("--plot-only", default=None, help="replot an existing JSON")
    a = ap.parse_args()
    if a.plot_only:
        p = Path(a.plot_only)
        plot(json.loads(p.read_text()), p.parent)
        return
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    from texstream.capture.synthetic.synth import SynthConfig, render_scene
    from texstream.fit.optim.fitter import FitConfig
    from texstream.fit.models.lfm.problem import LFMConfig, LFMProblem, PhotoSamples, fit_lfm
    from texstream.fit.models.lfm.baselines import fit_nmf, fit_pca
    from texstream.fit.models.lfm.model_folder import LFMRenderer, lfm_geometry
    from texstream.fit.stages.stage import build_problem, split_holdout

    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    methods = [m for m in a.methods.split(",") if m]
    render_views = [v for v in a.render_views.split(",") if v]
    for m in methods:
        if m not in STREAM and m not in BASELINES:
            raise SystemExit(f"unknown method {m!r}: use {sorted(STREAM)} or {list(BASELINES)}")
    t0 = time.perf_counter()
    sc = render_scene(a.scene, SynthConfig(scale=a.scale, device=a.device, progress=False, photos=a.photos,
                                                  image_size=a.image_size))
    t_render = time.perf_counter() - t0
    index = {id(f): i for i, f in enumerate(sc.frames)}
    frames, held = split_holdout(sc.frames, a.holdout_every)
    images = [sc.images[index[id(f)]] for f in frames]
    masks = [sc.masks[index[id(f)]] for f in frames]
    held_images = [sc.images[index[id(f)]] for f in held]
    held_masks = [sc.masks[index[id(f)]] for f in held]
    fit_cfg = FitConfig(model="radiance")
    t0 = time.perf_counter()
    sp = build_problem(sc.mesh, sc.bake, frames, images, masks, fit_cfg, a.device)
    geom = lfm_geometry(sc.mesh, sc.bake, sp.texels)
    wp.synchronize_device(a.device)
    t_setup = time.perf_counter() - t0
    grid_index = np.asarray(sp.texels.grid_index, np.int64)
    photo_bytes = int(sp.photos.images.capacity + sp.photos.depth.capacity + sp.photos.shadow.capacity)
    results = {"scene": a.scene, "scale": a.scale, "device": a.device, "machine": platform.node(),
               "photos_fitted": len(frames), "photos_held_out": len(held), "image_size": list(sc.images[0].shape[:2]),
               "texels": int(geom.n_texels), "welded_vertices": int(geom.n_vertices),
               "triangles": int(sc.mesh.n_faces), "view_res": a.view_res, "render_s": t_render, "setup_s": t_setup,
               "photo_bytes": photo_bytes, "runs": {}, "memory": []}
    if a.device.startswith("cuda"):
        results["gpu"] = wp.get_device(a.device).name
    print(f"{a.scene} x{a.scale}: {len(frames)} photos fitted, {len(held)} held out, {geom.n_texels} texels, "
          f"{geom.n_vertices} vertices; render {t_render:.1f}s, set-up {t_setup:.1f}s", flush=True)

    def problem(cfg: LFMConfig, fr=frames, p=sp) -> LFMProblem:
        return LFMProblem(geom, PhotoSamples(p, fr), cfg, a.device)

    def renderer_factory(cfg):
        def make(params):
            r = LFMRenderer(sc.mesh, sc.bake, geom, params, cfg, grid_index, a.device)
            return lambda f: r.render_frame(f)
        return make

    # compile / warm up every kernel once (a 1-iteration fit of each optimizer, a render)
    for m in {m for m in methods if m in STREAM}:
        warm = problem(LFMConfig(terms=1, view_res=a.view_res, iterations=2, **STREAM[m]))
        heldout_scores(renderer_factory(warm.cfg), fit_lfm(warm).params, held[:1], held_images[:1], held_masks[:1])

    for K in [int(k) for k in a.terms.split(",")]:
        for m in methods:
            name = f"{m}_K{K}"
            if m in STREAM:
                iters = a.sd_iterations if m == "sd" else a.iterations
                cfg = LFMConfig(terms=K, view_res=a.view_res, iterations=iters, rel_tol=a.rel_tol,
                                sync_every=a.sync_every, render_view=render_views[0], **STREAM[m])
                pr = problem(cfg)
                scoring = [0.0]
                objective = [0.0]
                trace = []
                make = renderer_factory(cfg)

                def snapshot(it, G, H, pr=pr, trace=trace, scoring=scoring, make=make, objective=objective):
                    ts = time.perf_counter()
                    trace.append({"iteration": it, "time_s": ts - t_start - scoring[0], "objective": objective[0],
                                  **heldout_scores(make, pr.params(G, H), held, held_images, held_masks)})
                    scoring[0] += time.perf_counter() - ts

                wp.synchronize_device(a.device)
                t_start = time.perf_counter()
                pr.compute_diffuse()
                wp.synchronize_device(a.device)
                t_diffuse = time.perf_counter() - t_start
                res = fit_lfm(pr, callback=lambda it, obj, o=objective: o.__setitem__(0, obj), snapshot=snapshot)
                total = time.perf_counter() - t_start - scoring[0]
                final_params = res.params
                final = trace[-1]
                t_conv, it_conv = converged_time(trace)
                run = {"method": m, "terms": K, "total_s": total, "diffuse_s": t_diffuse, "fit_s": res.fit_s,
                       "iterations": res.iterations, "passes": res.passes, "pass_ms": 1000 * total / max(res.passes, 1),
                       "state_bytes": res.state_bytes, "heldout": {k: final[k] for k in ("psnr_db", "worst_psnr_db",
                                                                                        "ape_percent")},
                       "best_psnr_db": max(r["psnr_db"] for r in trace), "converged_s": t_conv,
                       "converged_iteration": it_conv, "trace": trace}
            else:
                cfg = LFMConfig(terms=K, view_res=a.view_res, diffuse="mean" if m == "pca" else "min",
                                nmf_iterations=a.nmf_iterations, render_view=render_views[0])
                pr = problem(cfg)
                wp.synchronize_device(a.device)
                t_start = time.perf_counter()
                final_params, info = fit_pca(pr) if m == "pca" else fit_nmf(pr, a.nmf_iterations)
                total = time.perf_counter() - t_start
                final = heldout_scores(renderer_factory(cfg), final_params, held, held_images, held_masks)
                run = {"method": m, "terms": K, "total_s": total, "info": info, "heldout": final,
                       "best_psnr_db": final["psnr_db"], "converged_s": total, "trace": []}
            run["heldout_by_render_view"] = {
                v: (run["heldout"] if i == 0 else heldout_scores(
                    renderer_factory(dataclasses.replace(cfg, render_view=v)), final_params, held, held_images,
                    held_masks)) for i, v in enumerate(render_views)}
            results["runs"][name] = run
            h = run["heldout"]
            print(f"{name}: {total:.2f}s, held-out {h['psnr_db']:.2f} dB (worst {h['worst_psnr_db']:.2f}), "
                  f"APE {h['ape_percent']:.2f}%, converged (within 0.1 dB of its best) at {run['converged_s']:.2f}s",
                  flush=True)
            del pr
            (out / "lfm_error_vs_time.json").write_text(json.dumps(results, indent=1))  # a cut-short run keeps these

    for frac in [float(x) for x in a.memory_fractions.split(",") if x]:
        n = max(1, int(round(frac * len(frames))))
        sub = build_problem(sc.mesh, sc.bake, frames[:n], images[:n], masks[:n], fit_cfg, a.device)
        pr = problem(LFMConfig(terms=1, view_res=a.view_res, iterations=1), frames[:n], sub)
        stream_bytes = fit_lfm(pr).state_bytes
        pr = problem(LFMConfig(terms=1, view_res=a.view_res), frames[:n], sub)
        _, info = fit_pca(pr)
        row = {"photos": n, "stream_state_bytes": stream_bytes, "pca_samples_bytes": info["samples_bytes"],
               "pca_matrix_bytes": info["matrix_bytes"], "pca_s": info["total_s"],
               "photo_bytes": int(sub.photos.images.capacity + sub.photos.depth.capacity + sub.photos.shadow.capacity)}
        results["memory"].append(row)
        print("memory", row, flush=True)
        del sub, pr
    (out / "lfm_error_vs_time.json").write_text(json.dumps(results, indent=1))
    plot(results, out)
    print(json.dumps({k: v for k, v in results.items() if k not in ("runs", "memory")}, indent=1))
    for name, r in results["runs"].items():
        print(name, {k: (round(v, 4) if isinstance(v, float) else v) for k, v in r.items()
                     if k not in ("trace", "info", "heldout_by_render_view")}, r["heldout_by_render_view"])


if __name__ == "__main__":
    main()
