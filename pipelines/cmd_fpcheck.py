"""``texstream fpcheck [--device cpu|cuda:0] [--dtype float16|float32|float64] [-o DIR]``: floating-point error
of the device's operations as Warp compiles them (the dissertation's appendix A; fit/diagnostics/fpcheck.py)."""

from __future__ import annotations

import argparse
from pathlib import Path

from texstream.core.outputs import OutputTarget
from texstream.fit.diagnostics.fpcheck import FpcheckConfig, fpcheck, write_report
from texstream.pipelines.cli import add_config_arguments, config_from_args


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("-o", "--out", default=None,
                        help="output folder for fpcheck.json and fpcheck.md (default: fpcheck-DEVICE)")
    add_config_arguments(parser, FpcheckConfig)


def output_target(args: argparse.Namespace) -> OutputTarget:
    device = getattr(args, "device", FpcheckConfig.device)
    return OutputTarget(Path(args.out) if args.out else Path(f"fpcheck-{device.replace(':', '')}"))


def run(args: argparse.Namespace) -> int:
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING  # Warp 1.19: the init banner and module loads are info
    cfg = config_from_args(FpcheckConfig, args)
    out = output_target(args).path
    result = fpcheck(cfg)
    json_path, md_path = write_report(result, out)
    print(f"wrote {json_path} and {md_path}")
    return 0
