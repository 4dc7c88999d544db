"""``texstream run [PHOTOS] -o OUT``: the main job.

With PHOTOS (a folder of photos, a capture folder, a nerfstudio ``transforms.json`` folder or a
COLMAP model folder) it runs the end-to-end pipeline of :mod:`texstream.pipelines.run`: ingest,
register, mesh, atlas, fit, export and report, leaving out what the scene does not need.
With no input it renders the built-in synthetic capture set (``--scene``, default the ornament at
a small ``--scale``) and runs the same pipeline on it with its true cameras and mesh.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from texstream.capture.synthetic.synth import SynthConfig, synthesize
from texstream.calib.ingest import IngestConfig
from texstream.core.config import Number
from texstream.core.devices import DEVICE_HELP, resolve_device
from texstream.core.errors import ConfigError
from texstream.core.outputs import OutputTarget
from texstream.fit.optim.fitter import FitConfig
from texstream.geometry.atlas import AtlasConfig
from texstream.geometry.make_mesh import MeshConfig
from texstream.core.toml import read_toml
from texstream.pipelines.estimates import run_bytes
from texstream.pipelines.run import (LFM_CANDIDATE, RunConfig, STAGES, model_choices, run_config_from_dict,
                                     run_pipeline)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("photos", nargs="?", default=None,
                        help="photos, capture, transforms.json or COLMAP folder (default: the built-in synthetic set)")
    parser.add_argument("-o", "--out", default="out/demo", help="output folder (default: out/demo)")
    parser.add_argument("--config", default=None, help="run options as TOML (OUT/run_config.toml of an earlier run)")
    parser.add_argument("--from", dest="from_stage", default=None, choices=STAGES, help="rerun from this stage on")
    parser.add_argument("--model", default=None, choices=model_choices(), help="appearance model (default: auto)")
    parser.add_argument("--lfm", default=None, choices=LFM_CANDIDATE,
                        help="fixed unknown lighting, model auto: also fit light field mapping when view dependence "
                             "matters (auto, the default), always, or never")
    parser.add_argument("--relightable", action=argparse.BooleanOptionalAction, default=None,
                        help="fixed unknown lighting, model auto: also fit the relightable env_diffuse model (the light "
                             "estimated; texstream relight) and keep it within relightable_margin_db (1 dB) of the best "
                             "model on the validation photos (default: off)")
    parser.add_argument("--mesh-file", dest="mesh_file", default=None, help="use this mesh instead of one from the photos")
    parser.add_argument("--colocated-light", dest="colocated_light", default=None,
                        type=Number.of(IngestConfig, "colocated_light", "--colocated-light"),
                        help="photos lit by a flash at the camera: its irradiance at the object (the albedos' scale)")
    parser.add_argument("--no-flash", dest="no_flash", default=None, metavar="GLOB",
                        help="photos taken with the flash off, a file-name glob (texstream ingest --no-flash; a photos "
                             "folder's run: a capture's capture.json marks them itself); default: the EXIF Flash tag")
    parser.add_argument("--lights", default=None, help="lights file (JSON) for the photos (texstream ingest --lights)")
    parser.add_argument("--response", default=None, metavar="FILE|auto|srgb",
                        help="how the photos' codes become linear radiance (texstream ingest --response; default srgb)")
    parser.add_argument("--mirror-ball", dest="mirror_ball", default=None, metavar="X,Y,Z,R",
                        help="a mirror ball at X,Y,Z with radius R in the capture's world frame (more balls: "
                             "X,Y,Z,R,X,Y,Z,R): the run estimates the light from the ball photos and fits the "
                             "reflectance model under it")
    parser.add_argument("--mirror-ball-frames", dest="mirror_ball_frames", default=None, metavar="NAME,NAME",
                        help="the photos that show the ball (names or stems), left out of the fit (default: every "
                             "photo shows it beside the object)")
    parser.add_argument("--progress", action=argparse.BooleanOptionalAction, default=None,
                        help="progress bars on a terminal (default: on)")
    parser.add_argument("--device", default=None, help=DEVICE_HELP + " (default: auto)")
    parser.add_argument("--iterations", type=Number.of(FitConfig, "max_iterations", "--iterations"), default=None,
                        help="fit iteration cap (default: 30)")
    parser.add_argument("--optimizer", default=None, choices=("sd", "cg", "lbfgs", "lm"), help="fit method (default: lm)")
    parser.add_argument("--scene", default="ornament", help="built-in synthetic scene without PHOTOS (default: ornament)")
    parser.add_argument("--scale", type=Number.of(SynthConfig, "scale", "--scale"), default=0.1,
                        help="synthetic scene scale (default: 0.1: 176 photos of 136x136, 154 fitted and 22 held out)")


def _config(args: argparse.Namespace):
    import dataclasses

    if args.config:
        try:
            cfg = run_config_from_dict(read_toml(args.config))
        except ConfigError as e:
            raise ConfigError(e.message, e.path or args.config, e.fix) from None
    else:
        cfg = RunConfig()
    if args.config is None:
        cfg.fit.fit = dataclasses.replace(cfg.fit.fit, max_iterations=30)
    top = {k: getattr(args, k) for k in ("model", "lfm", "relightable", "device", "mesh_file", "progress")
           if getattr(args, k, None) is not None}
    fit = {k: v for k, v in (("max_iterations", args.iterations), ("optimizer", args.optimizer)) if v is not None}
    cfg = dataclasses.replace(cfg, **top)
    ingest = {k: getattr(args, k) for k in ("colocated_light", "lights", "response", "no_flash")
              if getattr(args, k) is not None}
    if ingest:
        cfg.ingest = dataclasses.replace(cfg.ingest, **ingest)
    if fit:
        cfg.fit.fit = dataclasses.replace(cfg.fit.fit, **fit)
    lights = {}
    if args.mirror_ball is not None:
        try:
            ball = tuple(float(x) for x in args.mirror_ball.replace(" ", "").split(",") if x)
        except ValueError:
            ball = ()
        if not ball or len(ball) % 4:
            raise ConfigError(f"--mirror-ball {args.mirror_ball!r} is not X,Y,Z,R (four numbers per ball)",
                              fix="write it as --mirror-ball 0,0,0,0.25")
        lights["sphere"] = ball
    if args.mirror_ball_frames is not None:
        lights["frames"] = tuple(x for x in args.mirror_ball_frames.split(",") if x)
    if lights:
        cfg.lights = dataclasses.replace(cfg.lights, **lights)
    if cfg.fit.fit.max_iterations < 1:
        raise ConfigError(f"--iterations {cfg.fit.fit.max_iterations} must be at least 1", fix="pass --iterations 30")
    return cfg


def output_target(args: argparse.Namespace) -> OutputTarget:
    """The run's folder (its stages' folders inside it), with room for every stage's output (estimates.py)."""
    size = run_bytes(args.photos, AtlasConfig.resolution, MeshConfig.faces)
    return OutputTarget(Path(args.out), estimated_bytes=size, what="the run")


def run(args: argparse.Namespace) -> int:
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    cfg = _config(args)
    out = Path(args.out)
    source = args.photos
    if source is None:
        source = out / "capture"
        print(f"[synth] built-in synthetic capture set '{args.scene}' at scale {args.scale} -> {source}", flush=True)
        s = synthesize(args.scene, source, SynthConfig(scale=args.scale, device=resolve_device(cfg.device))).summary
        print(f"        {s['photos']} photos {s['image_width']}x{s['image_height']}, {s['covered_texels']} texels",
              flush=True)
        if cfg.mesh_file is None:
            import dataclasses

            cfg = dataclasses.replace(cfg, mesh_file=str(source / "ground_truth"))
    summary = run_pipeline(source, out, cfg, from_stage=args.from_stage, log=lambda m: print(m, flush=True))
    h = summary["heldout"] or {}
    print("\nsummary")
    for st in summary["stages"]:
        print(f"  {st['name']:<9} {st['status']:<8} {st['seconds']:6.1f} s  {st['reason']}")
    if h.get("views"):
        print(f"  held-out views: {h['views']}, pooled PSNR {h['pooled_psnr_db']:.2f} dB, worst view "
              f"{h['worst_psnr_db']:.2f} dB ({h.get('worst_view')})")
    print(f"  model ({summary['model']}): {out / 'model'}")
    for name, path in (("glTF", out / "export" / "model.glb"), ("report", out / "report" / "index.html")):
        if path.exists():
            print(f"  {name}: {path}")
    print(f"  total {summary['total_s']:.1f} s")
    for w in summary.get("warnings", []):
        print(f"  warning: {w}")
    return 0
