"""``texstream eval MODEL CAPTURE``: PSNR / APE of a fitted model on any capture (e.g. held-out views)."""

from __future__ import annotations

import argparse

from pathlib import Path

from texstream.core.config import Number
from texstream.core.devices import DEVICE_HELP
from texstream.core.outputs import OutputTarget
from texstream.fit.stages.stage import eval_stage


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("model", help="model folder written by texstream fit")
    parser.add_argument("capture", help="capture folder to evaluate on")
    parser.add_argument("--device", default="auto", help=DEVICE_HELP + " (default: auto)")
    parser.add_argument("--holdout-every", dest="holdout_every", default=0,
                        type=Number(int, "--holdout-every", min=0),
                        help="score only the frames a fit with this --holdout-every held out (default: 0 = every frame)")
    parser.add_argument("-o", "--out", default=None, help="JSON report (default: MODEL/eval_<capture>.json)")


def output_target(args: argparse.Namespace) -> OutputTarget | None:
    """The JSON report (eval_stage's default name inside the model folder); a small file. None for the default
    name of a model folder that is not there: the stage says so, and no folder is made for the lock."""
    if args.out is None and not Path(args.model).is_dir():
        return None
    out = Path(args.out) if args.out else Path(args.model) / f"eval_{Path(args.capture).resolve().name}.json"
    return OutputTarget(out, folder=False, estimated_bytes=1 << 20, what="the evaluation report")


def run(args: argparse.Namespace) -> int:
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    res = eval_stage(args.model, args.capture, device=args.device, out_json=args.out, holdout_every=args.holdout_every)
    s = res.summary
    print(f"{s['frames']} frames: pooled PSNR {s['pooled_psnr_db']:.2f} dB, worst view {s['worst_psnr_db']:.2f} dB "
          f"({s['worst_view']}), mean of views {s['mean_psnr_db']:.2f} dB, mean APE {s['mean_ape_percent']:.2f}%; "
          f"report {res.output}")
    return 0
