"""Automatic masks' time per photo at 1086 x 724 (the issue's photo size), GrabCut at the working size (what
ingest did before: ``--grabcut-size 1024``) against a downscaled copy (the default), with each mask's IoU
against the renderer's (JSON).

    python benchmarks/mask_speed.py --out out/mask_speed

Photos: the dark glossy ornament of :mod:`texstream.capture.synthetic.dim_room` composited on black (the
object-on-a-plain-background case GrabCut runs on), and the same object in the dim room (the case whose masks
are undone: timed too, its IoU is not the point).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import numpy as np

from gitinfo import commit


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="out/mask_speed")
    ap.add_argument("--photos", type=int, default=4)
    ap.add_argument("--sizes", default="1024,512,384", help="GrabCut sizes (longest side) to time")
    args = ap.parse_args()

    from texstream.calib.masks import MaskConfig, compute_mask, mask_iou
    from texstream.capture.synthetic.dim_room import dim_room_photos

    scene = dim_room_photos(args.photos, (1086, 724))
    cases = {"object_on_black": [np.where(m[..., None], img, 0.02).astype(np.float32)
                                 for img, m in zip(scene.images, scene.masks)],
             "dim_room": scene.images}
    result = {"commit": commit(), "machine": f"{platform.node()} ({os.cpu_count()} cores)", "size": [1086, 724],
              "photos": args.photos, "runs": []}
    for case, images in cases.items():
        for g in (int(x) for x in args.sizes.split(",")):
            cfg = MaskConfig(grabcut_size=g)
            times, ious = [], []
            for img, truth in zip(images, scene.masks):
                t0 = time.perf_counter()
                m, _ = compute_mask(img, cfg, eight_bit_codes=True)
                times.append(time.perf_counter() - t0)
                ious.append(mask_iou(m, truth) if m is not None else 0.0)
            row = {"case": case, "grabcut_size": g, "seconds_per_photo": float(np.median(times)),
                   "iou_min": float(min(ious)), "iou_median": float(np.median(ious))}
            result["runs"].append(row)
            print(f"{case} GrabCut at {g}: {row['seconds_per_photo']:.2f} s/photo (median), IoU min "
                  f"{row['iou_min']:.4f}", flush=True)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "mask_speed.json").write_text(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
