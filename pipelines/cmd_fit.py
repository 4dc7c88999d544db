"""``texstream fit CAPTURE --mesh MESH -o MODEL``: fit a per-texel appearance model (Warp).

MESH is an atlas folder (``texstream atlas`` output or a synthetic set's ``ground_truth/``) or a
mesh file (baked at ``--texture-size``; given an xatlas atlas if it has no UVs). Example:

    texstream fit out/sphere --mesh out/sphere/ground_truth -o out/sphere_model --optimizer lm

Single view, many lights (photometric-stereo style; fit/stages/single_view.py): ``--normals``
instead of ``--mesh`` fits every pixel of one camera's photos as a texel, geometry from a normal
map (PNG RGB-encoded, or float EXR / NPY), no mesh or atlas:

    texstream fit out/bust --normals out/bust/normals.exr -o out/bust_model --model diffuse

Both take part in the automatic model choice (``--model auto``, the default) and the shared materials.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from texstream.core.config import Number
from texstream.core.errors import InputError
from texstream.core.outputs import OutputTarget
from texstream.core.progress import reporting
from texstream.fit.common.shading_normals import NormalsConfig
from texstream.fit.models.materials import MaterialConfig
from texstream.fit.optim.fitter import FitConfig
from texstream.fit.stages.choice import ModelChoiceConfig
from texstream.fit.stages.single_view import SingleViewConfig, fit_single_view_stage
from texstream.fit.stages.stage import FitStageConfig, fit_stage
from texstream.core.devices import DEVICE_HELP
from texstream.pipelines.cli import add_config_arguments, config_from_args
from texstream.pipelines.estimates import fit_bytes


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("capture", help="capture folder (capture.json with per-frame lights)")
    parser.add_argument("--mesh", help="atlas folder (mesh.obj + bake.npz) or mesh file (multi-view fits)")
    parser.add_argument("--normals", help="normal map (.png RGB-encoded, .exr, .npy) of a single-view capture: "
                        "fit per pixel, no mesh (give --mesh or --normals)")
    parser.add_argument("--normal-space", dest="normal_space", default="opengl",
                        choices=("opengl", "opencv", "world"),
                        help="frame of --normals: opengl camera axes (x right, y up, z to the viewer), opencv "
                             "camera axes or world (default: opengl)")
    parser.add_argument("--depth", type=Number.of(SingleViewConfig, "depth", "--depth"), default=1.0,
                        help="with --normals: nominal camera depth of the texels when the capture has no depth map "
                             "(irrelevant for directional lights; default: 1.0)")
    parser.add_argument("-o", "--out", required=True, help="model folder to write (replaced if it exists)")
    parser.add_argument("--device", default="auto", help=DEVICE_HELP + " (default: auto)")
    parser.add_argument("--texture-size", dest="texture_size", default=256,
                        type=Number.of(FitStageConfig, "texture_size", "--texture-size"),
                        help="atlas side when the mesh has UVs but no bake, 8 to 16384 texels "
                             "(default: 256; 0 = automatic, the power of two whose texels are about --texel-pixels "
                             "of the photos' pixels wide)")
    parser.add_argument("--texel-pixels", dest="texel_pixels",
                        type=Number.of(FitStageConfig, "texel_pixels", "--texel-pixels"),
                        default=3.0,
                        help="--texture-size 0: the texel width to aim at, in photo pixels (default: 3)")
    parser.add_argument("--photo-level", dest="photo_level", default=-1,
                        type=Number.of(FitStageConfig, "photo_level", "--photo-level"),
                        help="pyramid level the fitted photos stream at (L: 2^L x 2^L pixels averaged; default: -1 = "
                             "automatic, the coarsest whose texels stay 2 of its pixels wide; 0 = full resolution)")
    parser.add_argument("--holdout-every", dest="holdout_every", default=0,
                        type=Number.of(FitStageConfig, "holdout_every", "--holdout-every"),
                        help="hold out every k-th photo for evaluation (default: 0 = none)")
    parser.add_argument("--renders", type=Number.of(FitStageConfig, "renders", "--renders"), default=4,
                        help="photos rendered beside the fit (default: 4)")
    parser.add_argument("--min-seen-fraction", dest="min_seen_fraction", default=0.01,
                        type=Number.of(FitStageConfig, "min_seen_fraction", "--min-seen-fraction"),
                        help="fail before fitting when fewer than this fraction of texels is seen (default: 0.01)")
    parser.add_argument("--skip-bad-photos", dest="skip_bad_photos", action="store_true",
                        help="leave out photos that cannot be read (corrupt, truncated, wrong size) instead of "
                             "failing; each is printed and listed in model.json's photos.skipped")
    parser.add_argument("--traced-polish", dest="traced_polish",
                        type=Number.of(FitStageConfig, "traced_polish", "--traced-polish"),
                        default=5,
                        help="Levenberg-Marquardt iterations that end a fit with specular lobes with taps traced to "
                             "the mesh (stream.tap_geometry mesh): highlights narrower than a pixel fitted as the "
                             "photos filtered them (default: 5; 0 = off)")
    parser.add_argument("--traced-polish-rel-tol", dest="traced_polish_rel_tol", default=1e-5,
                        type=Number.of(FitStageConfig, "traced_polish_rel_tol", "--traced-polish-rel-tol"),
                        help="the traced polish stops after an iteration that lowers its objective by less than this, "
                             "relative (default: 1e-5; 0 = every iteration runs)")
    parser.add_argument("--traced-materials", dest="traced_materials", action="store_true",
                        help="with the traced polish and shared materials chosen: polish the per-texel fit on traced "
                             "taps first, and find and fit the materials on traced taps too (helps sub-pixel texels "
                             "that saw narrow highlights; can keep wrong lobes on texels that never saw theirs: "
                             "docs/accuracy.md)")

    add_config_arguments(parser, MaterialConfig, prefix="materials.")  # shared materials (fit/models/materials.py)
    add_config_arguments(parser, ModelChoiceConfig, prefix="choice.")  # --model auto (fit/stages/choice.py)
    add_config_arguments(parser, NormalsConfig, prefix="shading_normals.")  # fit/common/shading_normals.py
    add_config_arguments(parser, FitConfig)  # with the five above: the fields of FitStageConfig
    # the command's default is the model choice (a capture with lights gets its reflectance model, one without
    # its radiance model; with --holdout-every the candidates are judged on the held-out photos)
    parser.set_defaults(model="auto")


def output_target(args: argparse.Namespace) -> OutputTarget:
    """The model folder, with room for the model (and an automatic choice's candidates, estimates.py)."""
    # the automatic choice fits candidates only when photos are held out to judge them (fit/stages/choice.py)
    candidates = getattr(args, "model", "auto") == "auto" and args.holdout_every > 0
    size = fit_bytes(args.capture, args.mesh, args.texture_size, args.renders, candidates)
    return OutputTarget(Path(args.out), estimated_bytes=size, what="the model")


def run(args: argparse.Namespace) -> int:
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    fit_cfg = config_from_args(FitConfig, args)
    if (args.mesh is None) == (getattr(args, "normals", None) is None):
        raise InputError("give exactly one of --mesh (multi-view capture) and --normals (single view)",
                         args.capture, "add --mesh ATLAS_OR_MESH or --normals NORMAL_MAP")
    if args.normals is not None:
        return _run_single_view(args, fit_cfg)

    cfg = FitStageConfig(fit=fit_cfg, materials=config_from_args(MaterialConfig, args, prefix="materials."),
                         choice=config_from_args(ModelChoiceConfig, args, prefix="choice."),
                         shading_normals=config_from_args(NormalsConfig, args, prefix="shading_normals."),
                         **{k: getattr(args, k) for k in ("device", "texture_size", "texel_pixels", "photo_level", "holdout_every",
                                                          "renders", "min_seen_fraction", "skip_bad_photos",
                                                          "traced_polish", "traced_polish_rel_tol", "traced_materials")
                            if hasattr(args, k)})

    # the stage's phase lines, as texstream run prints them
    with reporting(lambda line: print(line, flush=True)):
        res = fit_stage(args.capture, args.mesh, args.out, cfg)
    s = res.summary
    print(f"wrote {res.output}: {s['texels']} texels from {s['photos']} photos, {s['iterations']} iterations in "
          f"{s['time_s']:.1f} s, sample PSNR {s['psnr_db']:.2f} dB")
    for f in s.get("skipped_photos", []):
        print(f"  skipped photo {f}: unreadable (--skip-bad-photos; model.json photos.skipped says why)")
    _print_evaluation(s)
    return 0


def _print_evaluation(s: dict) -> None:
    """The renders' scores, the held-out summary, the model choice's and the materials' reasons and warnings."""
    for e in s["render_eval"]:
        print(f"  {e['frame']}{' (held out)' if e['held_out'] else ''}: render PSNR {e['psnr_db']:.2f} dB, APE {e['ape_percent']:.2f}%")
    h = s.get("heldout") or {}
    if h.get("views"):
        print(f"  held out: {h['views']} views, pooled PSNR {h['pooled_psnr_db']:.2f} dB, worst {h['worst_psnr_db']:.2f} dB")
    if (s.get("selection") or {}).get("reason"):
        print(f"  model: {s['selection']['reason']}")
    m = s.get("materials") or {}
    if m.get("reason"):
        print(f"  materials: {m['reason']}")
    for w in s.get("warnings", []):
        print(f"  warning: {w}")


def _run_single_view(args: argparse.Namespace, fit_cfg) -> int:
    cfg = SingleViewConfig(fit=fit_cfg, materials=config_from_args(MaterialConfig, args, prefix="materials."),
                           choice=config_from_args(ModelChoiceConfig, args, prefix="choice."),
                           **{k: getattr(args, k) for k in ("device", "holdout_every", "renders", "normal_space",
                                                            "depth")})
    with reporting(lambda line: print(line, flush=True)):
        res = fit_single_view_stage(args.capture, args.normals, args.out, cfg)
    s = res.summary
    print(f"wrote {res.output}: {s['texels']} pixel texels ({s['unseen_texels']} unseen) from {s['photos']} photos, "
          f"{s['iterations']} iterations in {s['time_s']:.1f} s, sample PSNR {s['psnr_db']:.2f} dB")
    _print_evaluation(s)
    return 0
