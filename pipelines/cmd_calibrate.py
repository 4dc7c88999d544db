"""``texstream calibrate BOARD_PHOTOS --board chessboard:9x6:SIZE -o CALIB``: camera intrinsics."""

from __future__ import annotations

import argparse
from pathlib import Path

from texstream.calib.intrinsics import CalibrateConfig, calibrate
from texstream.core.outputs import OutputTarget
from texstream.pipelines.cli import add_config_arguments, config_from_args


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("photos", help="folder of board photos")
    parser.add_argument("-o", "--out", default=None,
                        help="output folder for intrinsics.json and the report (default: PHOTOS_calib)")
    add_config_arguments(parser, CalibrateConfig)


def output_target(args: argparse.Namespace) -> OutputTarget:
    photos = Path(args.photos)
    return OutputTarget(Path(args.out) if args.out else photos.parent / f"{photos.name}_calib")


def run(args: argparse.Namespace) -> int:
    cfg = config_from_args(CalibrateConfig, args)
    photos = Path(args.photos)
    out = output_target(args).path
    res = calibrate(photos, out, cfg)
    s = res.summary
    for c in s["cameras"]:
        print(f"camera {c['w']}x{c['h']}: fx={c['fl_x']:.2f} fy={c['fl_y']:.2f} cx={c['cx']:.2f} cy={c['cy']:.2f} "
              f"RMS={c['rms']:.3f} px")
    print(f"board found in {s['found']} photo(s); rejected {len(s['rejected'])}; "
          f"no board: {len(s['not_found'])}; unreadable: {len(s['unreadable'])}")
    for name in s["not_found"]:
        print(f"  no board: {name}")
    for name in s["unreadable"]:
        print(f"  unreadable: {name}")
    print(f"wrote {out / 'intrinsics.json'}")
    return 0
