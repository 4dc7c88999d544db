"""``texstream ingest PHOTOS -o CAPTURE``: a raw photo folder to a capture folder."""

from __future__ import annotations

import argparse
from pathlib import Path

from texstream.calib.ingest import IngestConfig, ingest
from texstream.core.outputs import OutputTarget
from texstream.pipelines.cli import add_config_arguments, config_from_args


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("photos", help="folder of photos (JPEG/PNG/TIFF/EXR; optional masks/ inside)")
    parser.add_argument("-o", "--out", required=True, help="capture folder to write")
    add_config_arguments(parser, IngestConfig)


def output_target(args: argparse.Namespace) -> OutputTarget:
    return OutputTarget(Path(args.out))


def run(args: argparse.Namespace) -> int:
    cfg = config_from_args(IngestConfig, args)
    res = ingest(Path(args.photos), Path(args.out), cfg)
    s = res.summary
    print(f"found {s['found']} file(s): {s['frames']} frame(s) ({s['brackets']} merged bracket(s)), "
          f"{s['masks']} mask(s), cameras {', '.join(s['camera_sizes'])}, intrinsics: {s['intrinsics_source']}")
    for d in s["dropped"]:
        print(f"  dropped: {d['image']} ({d['reason']})")
    for line in s.get("focal_prior", []):
        print(f"  focal length: {line}")
    print(f"  masks: {s['auto_masks']['decision']}")
    if cfg.response != "srgb":
        print(f"  photo response: {s['response']['why']}")
    print(f"wrote {res.output}")
    return 0
