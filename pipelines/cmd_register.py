"""``texstream register CAPTURE -o POSED``: camera poses with COLMAP (pycolmap)."""

from __future__ import annotations

import argparse
from pathlib import Path

from texstream.calib.register import RegisterConfig, register
from texstream.core.outputs import OutputTarget
from texstream.geometry.mesh_frame import mesh_alignment
from texstream.pipelines.cli import add_config_arguments, config_from_args


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("capture", help="capture folder from 'texstream ingest', or a folder of photos")
    parser.add_argument("-o", "--out", default=None, help="posed capture folder to write (default: CAPTURE_posed)")
    add_config_arguments(parser, RegisterConfig)


def output_target(args: argparse.Namespace) -> OutputTarget:
    cap = Path(args.capture)
    return OutputTarget(Path(args.out) if args.out else cap.parent / f"{cap.name}_posed")


def run(args: argparse.Namespace) -> int:
    cfg = config_from_args(RegisterConfig, args)
    cap = Path(args.capture)
    out = output_target(args).path
    res = register(cap, out, cfg, mesh_alignment=mesh_alignment)
    s = res.summary
    n_reg, n_un = len(s["registered"]), len(s["unregistered"])
    print(f"registered {n_reg} of {n_reg + n_un} photo(s) (models: {s['models']}); "
          f"{s['points3D']} points, mean reprojection error {s['mean_reprojection_error']:.3f} px")
    if s.get("ring"):
        print(f"  turntable ring: {s['ring']}")
    for name in s.get("placed") or []:
        print(f"  placed on the ring: {name}")
    for name in s["unregistered"]:
        print(f"  unregistered: {name}")
    for d in s["dropped"]:
        print(f"  dropped: {d['image']} ({d['reason']})")
    if s.get("alignment"):
        a = s["alignment"]
        if a.get("kind") == "mesh":
            print(f"aligned to the mesh frame: scale {a['scale']:.4g}, point RMS {a['rms']:.4g} "
                  f"({100 * a['rms_fraction']:.2f}% of the extent)")
        else:
            print(f"aligned to {a['common']} known centres: scale {a['scale']:.4g}, centre RMSE {a['rmse']:.4g}")
    if (s.get("focal_prior") or {}).get("retried"):
        print(f"  {s['focal_prior']['decision']} ({s['focal_prior']['reason']})")
    print(f"wrote {out}")
    return 0
