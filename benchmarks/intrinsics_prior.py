"""Registration from photos whose EXIF focal length is 5-8x too long, the way raw converters export them (JSON).

    python benchmarks/intrinsics_prior.py --out out/intrinsics_prior

Renders the ``textured_sphere`` scene (24 photos, two rings) and writes JPEGs with a full-frame body's EXIF
(:func:`texstream.capture.synthetic.exif_capture.write_exif_capture`): the focal-plane resolution and pixel
dimensions of the full sensor on a resized export, so FocalLength x FocalPlaneXResolution is ``ratio`` times the
true focal length. Cases: ``checked`` (all tags: ingest scales the stale tags by the image width over
PixelXDimension and cross-checks them with the body's sensor width), ``uncaught`` (PixelXDimension, Make and
Model left out: ingest passes the wrong prior on and registration must notice). Each runs ``ingest`` and
``register`` (no cameras given) and records the registered photos and the focal length's error against the
renderer's.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import time
from pathlib import Path

from gitinfo import commit


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="out/intrinsics_prior")
    ap.add_argument("--width", type=int, default=480, help="photo width (height: 2/3 of it)")
    ap.add_argument("--ratios", default="6,8", help="naive focal length over the true one, per case")
    args = ap.parse_args()

    from texstream.calib.ingest import ingest
    from texstream.calib.register import RegisterConfig, register
    from texstream.capture.capture_json import read_capture
    from texstream.capture.synthetic.exif import CameraBody
    from texstream.capture.synthetic.exif_capture import write_exif_capture

    out = Path(args.out)
    shutil.rmtree(out, ignore_errors=True)
    size = (args.width, args.width * 2 // 3)
    result = {"commit": commit(), "machine": f"{platform.node()} ({os.cpu_count()} cores)", "size": list(size),
              "cases": []}
    for ratio in (float(r) for r in args.ratios.split(",")):
        body = CameraBody(sensor_px=(int(round(ratio * size[0])), int(round(ratio * size[1]))))
        for case, drop in (("checked", ()), ("uncaught", ("Exif:PixelXDimension", "Exif:PixelYDimension", "Make", "Model"))):
            root = out / f"{case}_{ratio:g}x"
            made = write_exif_capture(root / "photos", size=size, photos=24, body=body, drop_tags=drop,
                                      cameras={"distance": 4.0})
            t0 = time.perf_counter()
            ing = ingest(made["photos"], root / "capture")
            t1 = time.perf_counter()
            reg = register(root / "capture", root / "registered", RegisterConfig(photometric="off"))
            t2 = time.perf_counter()
            fx = read_capture(root / "registered").frames[0].intrinsics.fx
            rep = json.loads((root / "registered" / "registration_report.json").read_text())
            row = {"case": case, "ratio": ratio, "true_focal_px": made["focal_px"], "naive_focal_px": made["naive_focal_px"],
                   "ingest_prior_px": read_capture(root / "capture").frames[0].intrinsics.fx,
                   "ingest_decision": ing.summary["focal_prior"], "registered": len(reg.summary["registered"]),
                   "photos": 24, "focal_px": fx, "focal_error": fx / made["focal_px"] - 1,
                   "register_focal_prior": rep.get("focal_prior"), "ingest_s": t1 - t0, "register_s": t2 - t1}
            result["cases"].append(row)
            print(f"{case} {ratio:g}x: prior {row['ingest_prior_px']:.0f} px, registered {row['registered']}/24, "
                  f"focal {fx:.1f} px (true {made['focal_px']:.1f}, error {100 * row['focal_error']:+.2f}%)", flush=True)
    (out / "intrinsics_prior.json").write_text(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
