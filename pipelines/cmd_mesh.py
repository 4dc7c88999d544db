"""``texstream mesh [CAPTURE] -o OUT [--from scan.obj | sfm | hull] [--faces N]``: make, clean, simplify the mesh.

Without a capture it only cleans and simplifies the given mesh. The stage is
:func:`texstream.geometry.make_mesh.make_mesh`; this module parses and prints.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from texstream.core.outputs import OutputTarget
from texstream.geometry.make_mesh import MeshConfig, make_mesh
from texstream.pipelines.cli import add_config_arguments, config_from_args
from texstream.pipelines.estimates import mesh_stage_bytes


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("capture", nargs="?", default=None, help="capture folder (optional with --from MESH)")
    parser.add_argument("-o", "--out", required=True, help="output folder (mesh.ply, mesh_report.json)")
    parser.add_argument("--from", dest="from_", default="auto", metavar="SOURCE",
                        help="a mesh file (OBJ/PLY/STL/GLB), 'sfm' (Poisson of the SfM points), 'hull' "
                             "(visual hull of the masks) or 'auto' (choose from what the capture has)")
    add_config_arguments(parser, MeshConfig)


def output_target(args: argparse.Namespace) -> OutputTarget:
    given = None if args.from_ in ("auto", "sfm", "hull") else args.from_
    faces = getattr(args, "faces", MeshConfig.faces)
    return OutputTarget(Path(args.out), estimated_bytes=mesh_stage_bytes(given, faces), what="the mesh")


def run(args: argparse.Namespace) -> int:
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING  # Warp 1.19: the init banner is info; one line on an error
    overrides = {}
    if args.from_ in ("auto", "sfm", "hull"):
        if args.from_ != "auto":
            overrides["source"] = args.from_
    else:
        overrides["mesh"] = args.from_
    cfg = config_from_args(MeshConfig, args, **overrides)
    res = make_mesh(args.capture, args.out, cfg)
    s = res.summary
    if "triangulation" in s:
        t = s["triangulation"]
        print(f"triangulated {t['points']} SfM points from the known cameras in {t['seconds']['total']:.1f} s "
              f"(median reprojection error {t['median_reprojection_error_px']:.2f} px)")
    if "dense" in s:
        d = s["dense"]
        masked = d.get("masks", "the capture's") == "the capture's"
        print(f"dense stereo: {d['points']} points ({d['pixel_points']} consistent depths) from "
              f"{len(d['views'])} photos, mean fill {100 * d['mean_fill']:.0f}% of the "
              f"{'masks' if masked else 'matched regions'}, {d['seconds']['total']:.1f} s"
              + ("" if masked else f"; masks {d['masks']}; depth range from {d['depth_range_from']}")
              + ("" if d["used"] else f"; {d['fallback']}"))
    print(f"mesh from {s['source']} ({s['reason']}): {s['summary']}; wrote {res.output / 'mesh.ply'} "
          f"in {s['seconds']:.1f} s")
    return 0
