"""``texstream eval MODEL CAPTURE``: PSNR / APE of a fitted model on any capture (e.g. held-out views)."""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("model", help="model folder written by texstream fit")
    parser.add_argument("capture", help="capture folder to evaluate on")
    parser.add_argument("--device", default="cpu", help="Warp device (default: cpu)")
    parser.add_argument("-o", "--out", default=None, help="JSON report (default: MODEL/eval_<capture>.json)")


def run(args: argparse.Namespace) -> int:
    import warp as wp

    from texstream.fit.stage import eval_stage

    wp.config.log_level = wp.LOG_WARNING
    res = eval_stage(args.model, args.capture, device=args.device, out_json=args.out)
    s = res.summary
    print(f"{s['frames']} frames: mean PSNR {s['mean_psnr_db']:.2f} dB (PSNR of mean MSE {s['psnr_of_mean_mse_db']:.2f} dB), "
          f"mean APE {s['mean_ape_percent']:.2f}%; report {res.output}")
    return 0
