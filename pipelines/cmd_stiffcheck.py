"""``texstream stiffcheck [--device cpu|cuda:0] [--size ci|full] [--cases a,b] [-o DIR]``: the stiff and extreme
fitting suite (fit/diagnostics/stiffcheck.py): each case fitted in the fit's own precision and in float64, with
convergence, the shortfall against float64, NaN/Inf and out-of-bounds counts and the safeguard named."""

from __future__ import annotations

import argparse
from pathlib import Path

from texstream.core.outputs import OutputTarget
from texstream.fit.diagnostics.stiffcheck import StiffcheckConfig, run_suite, select_cases, write_report
from texstream.pipelines.cli import add_config_arguments, config_from_args


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("-o", "--out", default=None,
                        help="output folder for stiffcheck.json and stiffcheck.md (default: stiffcheck-DEVICE-SIZE)")
    add_config_arguments(parser, StiffcheckConfig)


def output_target(args: argparse.Namespace) -> OutputTarget:
    device, size = getattr(args, "device", StiffcheckConfig.device), getattr(args, "size", StiffcheckConfig.size)
    return OutputTarget(Path(args.out) if args.out else Path(f"stiffcheck-{device.replace(':', '')}-{size}"))


def run(args: argparse.Namespace) -> int:
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING  # Warp 1.19: the init banner and module loads are info
    cfg = config_from_args(StiffcheckConfig, args)
    select_cases([n.strip() for n in cfg.cases.split(",") if n.strip()])  # unknown names fail before any work
    out = output_target(args).path  # checked by the CLI before the suite runs (a folder, writable)

    def log(r: dict) -> None:
        verdict = "ok" if r["ok"] else "FAILED: " + "; ".join(r["failures"])
        short = (f"E rel. error {r['rel_error_E_auto']:.1e} ({r['auto_choice']})" if r["kind"] == "accumulation"
                 else f"shortfall {r['shortfall_db']:+.3f} dB")
        print(f"{r['name']:24s} {short:34s} NaN/Inf {r['nonfinite']}  {r['wall_s']:.1f} s  {verdict}", flush=True)

    result = run_suite(cfg, log)
    json_path, md_path = write_report(result, out)
    print(f"wrote {json_path} and {md_path}")
    return 0 if result["ok"] else 1
