"""``texstream refine CAPTURE ATLAS -o OUT``: registered cameras and a reconstructed mesh moved until the
photos agree (photometric Gauss-Newton on one shared texture; geometry/refine.py)."""

from __future__ import annotations

import argparse
from pathlib import Path

from texstream.geometry.refine import RefineConfig, refine_stage
from texstream.core.devices import DEVICE_HELP, resolve_device
from texstream.core.outputs import OutputTarget
from texstream.pipelines.cli import add_config_arguments, config_from_args
from texstream.pipelines.estimates import refine_bytes


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("capture", help="posed capture folder (texstream register, import, or a capture.json)")
    parser.add_argument("atlas", help="atlas folder of the mesh (texstream atlas: mesh.obj, bake.npz, seams.npz)")
    parser.add_argument("-o", "--out", required=True,
                        help="output folder: capture.json with refined poses and an atlas folder of the moved mesh, "
                             "to give texstream fit as its capture and --mesh")
    parser.add_argument("--device", default="auto", help=DEVICE_HELP + " (default: auto)")
    add_config_arguments(parser, RefineConfig)


def output_target(args: argparse.Namespace) -> OutputTarget:
    return OutputTarget(Path(args.out), estimated_bytes=refine_bytes(args.capture, args.atlas),
                        what="the refined capture")


def run(args: argparse.Namespace) -> int:
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING  # Warp 1.19: the init banner is info; one line on an error
    config = config_from_args(RefineConfig, args)
    res = refine_stage(args.capture, args.atlas, args.out, config, device=resolve_device(args.device), log=print)
    s = res.summary
    before, after = s["residual_before"], s["residual_after"]
    held = f"; held-out photos aligned {_rms(before, 'align')} -> {_rms(after, 'align')}" if "align_rms" in after else ""
    print(f"refine: photo residual (RMS) {_rms(before, 'fit')} -> {_rms(after, 'fit')}{held}; cameras turned "
          f"{s['camera_rotation_deg']['median']:.3f} deg (median), vertices moved "
          f"{100 * s['displacement']['median_abs']:.3f}% of the diagonal (median) in {s['seconds']:.1f} s -> {res.output}")
    return 0


def _rms(residual: dict, role: str) -> str:
    """A role's RMS residual, or "n/a" where no photo of that role had a sample."""
    value = residual.get(f"{role}_rms")
    return "n/a" if value is None else f"{value:.4f}"
