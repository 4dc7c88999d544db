"""``texstream fit CAPTURE --mesh MESH -o MODEL``: fit a per-texel appearance model (Warp).

MESH is an atlas folder (``texstream atlas`` output or a synthetic set's ``ground_truth/``) or a
mesh file (baked at ``--texture-size``; given an xatlas atlas if it has no UVs). Example:

    texstream fit out/sphere --mesh out/sphere/ground_truth -o out/sphere_model --optimizer lm
"""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from texstream.fit.fitter import FitConfig
    from texstream.pipelines.cli import add_config_arguments

    parser.add_argument("capture", help="capture folder (capture.json with per-frame lights)")
    parser.add_argument("--mesh", required=True, help="atlas folder (mesh.obj + bake.npz) or mesh file")
    parser.add_argument("-o", "--out", required=True, help="model folder to write (replaced if it exists)")
    parser.add_argument("--device", default="cpu", help="Warp device: cpu or cuda:N (default: cpu)")
    parser.add_argument("--texture-size", dest="texture_size", type=int, default=256,
                        help="atlas side when the mesh has UVs but no bake (default: 256)")
    parser.add_argument("--holdout-every", dest="holdout_every", type=int, default=0,
                        help="hold out every k-th photo for evaluation (default: 0 = none)")
    parser.add_argument("--renders", type=int, default=4, help="photos rendered beside the fit (default: 4)")
    add_config_arguments(parser, FitConfig)  # with the four above: the fields of FitStageConfig


def run(args: argparse.Namespace) -> int:
    import warp as wp

    from texstream.fit.fitter import FitConfig
    from texstream.fit.stage import FitStageConfig, fit_stage
    from texstream.pipelines.cli import config_from_args

    wp.config.log_level = wp.LOG_WARNING
    fit_cfg = config_from_args(FitConfig, args)
    cfg = FitStageConfig(fit=fit_cfg, **{k: getattr(args, k) for k in ("device", "texture_size", "holdout_every", "renders")
                                         if hasattr(args, k)})
    res = fit_stage(args.capture, args.mesh, args.out, cfg)
    s = res.summary
    print(f"wrote {res.output}: {s['texels']} texels from {s['photos']} photos, {s['iterations']} iterations in "
          f"{s['time_s']:.1f} s, sample PSNR {s['psnr_db']:.2f} dB")
    for e in s["render_eval"]:
        print(f"  {e['frame']}{' (held out)' if e['held_out'] else ''}: render PSNR {e['psnr_db']:.2f} dB, APE {e['ape_percent']:.2f}%")
    return 0
