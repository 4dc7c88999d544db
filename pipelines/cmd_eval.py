"""``texstream eval MODEL CAPTURE``: PSNR / APE of a fitted model on any capture (e.g. held-out views)."""

from __future__ import annotations

import argparse

from texstream.core.devices import DEVICE_HELP
from texstream.fit.stages.stage import eval_stage


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("model", help="model folder written by texstream fit")
    parser.add_argument("capture", help="capture folder to evaluate on")
    parser.add_argument("--device", default="auto", help=DEVICE_HELP + " (default: auto)")
    parser.add_argument("--holdout-every", dest="holdout_every", type=int, default=0,
                        help="score only the frames a fit with this --holdout-every held out (default: 0 = every frame)")
    parser.add_argument("-o", "--out", default=None, help="JSON report (default: MODEL/eval_<capture>.json)")


def run(args: argparse.Namespace) -> int:
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    res = eval_stage(args.model, args.capture, device=args.device, out_json=args.out, holdout_every=args.holdout_every)
    s = res.summary
    print(f"{s['frames']} frames: pooled PSNR {s['pooled_psnr_db']:.2f} dB, worst view {s['worst_psnr_db']:.2f} dB "
          f"({s['worst_view']}), mean of views {s['mean_psnr_db']:.2f} dB, mean APE {s['mean_ape_percent']:.2f}%; "
          f"report {res.output}")
    return 0
