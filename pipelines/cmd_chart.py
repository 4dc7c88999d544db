"""``texstream chart PHOTOS -o OUT``: the photos' response from a ColorChecker in view (calib/colour_chart.py)."""

from __future__ import annotations

import argparse
from pathlib import Path

from texstream.calib.colour_chart import chart_response
from texstream.core.outputs import OutputTarget


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("photos", help="folder of photos (JPEG, PNG, TIFF as exported), some showing a ColorChecker "
                                       "Classic")
    parser.add_argument("-o", "--out", required=True,
                        help="output folder: response.json (code value to linear radiance, per-photo gains), "
                             "chart_report.json (which photos showed the chart)")


def output_target(args: argparse.Namespace) -> OutputTarget:
    return OutputTarget(Path(args.out))


def run(args: argparse.Namespace) -> int:
    s = chart_response(args.photos, args.out)
    print(f"chart found in {s['charts_found']} of {s['photos']} photos; response from {s['patches_used']} patch "
          f"values, linearised patches within {s['residual_percent']:.2f}% (RMS) of reflectance x gain; "
          f"wrote {args.out}/response.json")
    return 0
