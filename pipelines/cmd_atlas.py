"""``texstream atlas MESH -o OUT``: UV atlas (xatlas) and texel bake for fitting."""

from __future__ import annotations

import argparse
from pathlib import Path

from texstream.geometry.atlas import AtlasConfig, atlas_stage
from texstream.core.devices import DEVICE_HELP, resolve_device
from texstream.core.outputs import OutputTarget
from texstream.pipelines.cli import add_config_arguments, config_from_args
from texstream.pipelines.estimates import atlas_bytes


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("mesh", help="input mesh (OBJ, PLY, STL, GLB or glTF)")
    parser.add_argument("-o", "--out", required=True, help="output folder")
    parser.add_argument("--capture", default=None,
                        help="capture folder: texel density follows how large each face appears in its photos")
    parser.add_argument("--device", default="auto", help=DEVICE_HELP + " (default: auto)")
    parser.add_argument("--force", action="store_true", help="recompute even if OUT is up to date")
    add_config_arguments(parser, AtlasConfig)


def output_target(args: argparse.Namespace) -> OutputTarget:
    resolution = getattr(args, "resolution", AtlasConfig.resolution)
    return OutputTarget(Path(args.out), estimated_bytes=atlas_bytes(args.mesh, resolution), what="the atlas")


def run(args: argparse.Namespace) -> int:
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING  # Warp 1.19: the init banner is info; one line on an error
    config = config_from_args(AtlasConfig, args)
    res = atlas_stage(args.mesh, args.out, config, device=resolve_device(args.device), force=args.force, capture=args.capture)
    s = res.summary
    if res.skipped:
        print(f"atlas: skipped, {res.reason} ({res.output})")
        return 0
    print(f"atlas: {s['width']}x{s['height']} texels, {s['n_charts']} charts ({s['source']}: {s['reason']}), "
          f"utilization {100 * s['utilization']:.1f}%, {s['n_covered']} covered texels, "
          f"{s['faces_without_texels']} faces without texels, {s.get('seam_edges', 0)} seam edges -> {res.output}")
    if "texel_size_px" in s:
        t = s["texel_size_px"]
        print(f"texel size in the photos: median {t['median']:.2f} px, p90/p10 {t['p90_over_p10']:.2f}")
    return 0
