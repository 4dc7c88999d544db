"""``texstream synth SCENE -o DIR``: render a synthetic capture set with ground truth.

SCENE is a built-in scene (sphere, flat_sample, bunny, ornament) or a scene JSON file; see
:mod:`texstream.capture.synthetic.synth` for the scene keys. ``flash_capture`` writes the synthetic flash capture
(:mod:`texstream.capture.synthetic.flash_capture`: 8-bit tone-mapped photos with a colour chart in view; options
--photos, --image-size, --noise, --room-light, --seed, --device, --no-flash-pairs, --object). Example:

    texstream synth ornament -o out/ornament --scale 0.05 --bits 8 --noise 0.005 --save-clean

Under an environment light (no light in capture.json; the map and its SH in ground_truth/):

    texstream synth ornament -o out/ornament_sky --scale 0.05 --env sky
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

from texstream.capture.synthetic.flash_capture import FLASH_CAPTURE, FLASH_SCENES, flash_config, synthesize_flash_capture
from texstream.capture.synthetic.synth import SynthConfig, builtin_scenes, synthesize
from texstream.core.errors import ConfigError
from texstream.core.outputs import OutputTarget
from texstream.pipelines.cli import add_config_arguments, config_from_args


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scene", help=f"built-in scene ({', '.join(builtin_scenes())}), {FLASH_CAPTURE} or a scene "
                                      "JSON path")
    parser.add_argument("-o", "--out", required=True, help="output capture folder (replaced if it exists)")
    add_config_arguments(parser, SynthConfig)
    parser.add_argument("--no-flash-pairs", dest="no_flash_pairs", action="store_true",
                        help=f"{FLASH_CAPTURE} only: each camera also takes a photo with the flash off (a pair)")
    parser.add_argument("--object", choices=FLASH_SCENES, default=None,
                        help=f"{FLASH_CAPTURE} only: the object ({FLASH_SCENES[0]}, the default: 24 cameras, coarser "
                             f"than issue 39 asks; {FLASH_SCENES[1]}: 72 cameras, photos 4x the pixels its fit atlas "
                             "needs; capture/synthetic/flash_capture.py)")


def output_target(args: argparse.Namespace) -> OutputTarget:
    return OutputTarget(Path(args.out))


def run(args: argparse.Namespace) -> int:
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING  # the progress bar and the summary are the output (1.19: not `quiet`)

    config = config_from_args(SynthConfig, args, scene=args.scene)
    for flag, given in (("--no-flash-pairs", args.no_flash_pairs), ("--object", args.object)):
        if given and args.scene != FLASH_CAPTURE:
            raise ConfigError(f"{flag} is an option of {FLASH_CAPTURE}, not of {args.scene}",
                              fix=f"use texstream synth {FLASH_CAPTURE} {flag}")
    if args.scene == FLASH_CAPTURE:
        flash = dataclasses.replace(flash_config(config), no_flash_pairs=args.no_flash_pairs)
        res = synthesize_flash_capture(args.out, dataclasses.replace(flash, scene=args.object or flash.scene))
    else:
        res = synthesize(args.scene, args.out, config)
    s = res.summary
    print(f"wrote {res.output}: {s['photos']} photos of {s['image_width']}x{s['image_height']}, "
          f"{s['triangles']} triangles, {s['covered_texels']} covered texels "
          f"({s['texture_width']}x{s['texture_height']}); ground truth in {res.output}/ground_truth")
    return 0
