"""``texstream preview CAPTURE [-o sheet.png]``: contact sheet of a capture folder."""

from __future__ import annotations

import argparse
from pathlib import Path

from texstream.capture.preview import write_contact_sheet
from texstream.core.config import Number
from texstream.core.errors import ConfigError
from texstream.core.outputs import OutputTarget


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("capture", help="capture folder (capture.json or nerfstudio transforms.json)")
    parser.add_argument("-o", "--out", default=None,
                        help="output PNG (default: CAPTURE/contact_sheet.png)")
    parser.add_argument("--max-images", type=Number(int, "--max-images", min=1, max=10000), default=64,
                        help="at most this many frames, evenly spaced (1 to 10000)")
    parser.add_argument("--thumb", type=Number(int, "--thumb", min=8, max=4096), default=160,
                        help="thumbnail size in pixels (8 to 4096)")
    parser.add_argument("--exposure", default="auto",
                        help="'auto' (99th percentile -> 0.9) or a linear scale for the sheet")
    parser.add_argument("--no-labels", action="store_true", help="do not draw frame indices")
    parser.add_argument("--no-masks", action="store_true", help="do not dim masked-out pixels")


def output_target(args: argparse.Namespace) -> OutputTarget:
    cap = Path(args.capture)
    return OutputTarget(Path(args.out) if args.out else (cap if cap.is_dir() else cap.parent) / "contact_sheet.png",
                        folder=False)


def run(args: argparse.Namespace) -> int:
    exposure: float | str = args.exposure
    if exposure != "auto":
        try:
            exposure = float(exposure)
        except ValueError:
            raise ConfigError(f"--exposure {args.exposure!r} is neither 'auto' nor a number",
                              fix="pass --exposure auto or e.g. --exposure 2") from None
    cap = Path(args.capture)
    out = output_target(args).path
    path = write_contact_sheet(cap, out, max_images=args.max_images, thumb=args.thumb, exposure=exposure,
                               label=not args.no_labels, show_masks=not args.no_masks)
    print(f"wrote {path}")
    return 0
