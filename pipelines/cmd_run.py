"""``texstream run``: the main job. With no input it generates the built-in synthetic capture set
(``--scene``, default the ornament at a small ``--scale``), writes previews, fits the per-texel
Lafortune model with the streaming Warp backend and writes the model folder (maps, trace,
error-against-time plot, fitted renders beside held-out photos). The photos-to-model path
(ingest, register, mesh, atlas, fit) chains the same stage functions (later issue).
"""

from __future__ import annotations

import argparse
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", default="out/demo", help="output folder (default: out/demo)")
    parser.add_argument("--scene", default="ornament", help="built-in synthetic scene (default: ornament)")
    parser.add_argument("--scale", type=float, default=0.1,
                        help="scene scale (default: 0.1: 176 photos of 136x136, 154 fitted and 22 held out; under a "
                             "minute on 2 CPU cores after the one-off kernel compile)")
    parser.add_argument("--device", default="cpu", help="Warp device (default: cpu)")
    parser.add_argument("--optimizer", default="lm", choices=("sd", "cg", "lbfgs", "lm"), help="fit method (default: lm)")
    parser.add_argument("--iterations", type=int, default=30, help="iteration cap (default: 30)")
    parser.add_argument("--smooth", type=float, default=0.0,
                        help="LM lobe-shape smoothness between neighbouring texels (default: 0 = independent texels)")


def run(args: argparse.Namespace) -> int:
    import warp as wp

    from texstream.capture.synth import SynthConfig, synthesize
    from texstream.fit.fitter import FitConfig
    from texstream.fit.penalties import PenaltyConfig
    from texstream.fit.stage import FitStageConfig, fit_stage

    wp.config.log_level = wp.LOG_WARNING
    out = Path(args.out)
    cap = out / "capture"
    print(f"[1/2] synthetic capture set '{args.scene}' at scale {args.scale} -> {cap}", flush=True)
    s = synthesize(args.scene, cap, SynthConfig(scale=args.scale, device=args.device)).summary
    print(f"      {s['photos']} photos {s['image_width']}x{s['image_height']}, {s['covered_texels']} texels; "
          f"previews in {cap}/previews", flush=True)
    print(f"[2/2] fit ({args.optimizer}) -> {out / 'model'}", flush=True)
    cfg = FitStageConfig(device=args.device, holdout_every=8,
                         fit=FitConfig(optimizer=args.optimizer, max_iterations=args.iterations,
                                       penalties=PenaltyConfig(smooth_weight=args.smooth if args.optimizer == "lm" else 0.0)))
    res = fit_stage(cap, cap / "ground_truth", out / "model", cfg)
    r = res.summary
    print(f"done: {r['iterations']} iterations in {r['time_s']:.1f} s, sample PSNR {r['psnr_db']:.2f} dB; "
          f"model {out / 'model'} (error_vs_time.png, renders/)")
    for e in r["render_eval"]:
        print(f"  {e['frame']}{' (held out)' if e['held_out'] else ''}: render PSNR {e['psnr_db']:.2f} dB")
    return 0
