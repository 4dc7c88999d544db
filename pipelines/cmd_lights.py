"""``texstream lights CAPTURE -o OUT``: light position / direction from mirror-ball photos."""

from __future__ import annotations

import argparse
from pathlib import Path

from texstream.calib.lights import LightsConfig, estimate_lights
from texstream.core.outputs import OutputTarget
from texstream.pipelines.cli import add_config_arguments, config_from_args


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("capture", help="posed capture folder (capture.json with camera poses) holding the ball photos")
    parser.add_argument("-o", "--out", required=True,
                        help="output folder: lights.json (for 'texstream ingest --lights'), lights_report.json")
    add_config_arguments(parser, LightsConfig)


def output_target(args: argparse.Namespace) -> OutputTarget:
    return OutputTarget(Path(args.out))


def run(args: argparse.Namespace) -> int:
    res = estimate_lights(Path(args.capture), Path(args.out), config_from_args(LightsConfig, args))
    s = res.summary
    lt = s["light"]
    if s["kind"] == "point":
        where = "position " + " ".join(f"{x:.4g}" for x in lt["position"])
        quality = f"rays meet within {s['rms_ray_distance']:.3g} (RMS), parallax {s['parallax_deg']:.1f} deg"
    else:
        where = "direction " + " ".join(f"{x:.4f}" for x in lt["direction"])
        quality = f"rays within {s['spread_deg']:.2f} deg of their mean"
    print(f"{s['kind']} light from {s['views']} ball view(s): {where}; {quality}")
    for sk in s["skipped"]:
        print(f"  skipped: {sk['frame']} ({sk['reason']})")
    print(f"wrote {res.output / 'lights.json'}")
    return 0
