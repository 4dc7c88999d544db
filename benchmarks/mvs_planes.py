"""Dense stereo's points at a pyramid level with the plane count of the rule and with others (issue 40): whether a
coarse level fails for want of planes (writes JSON).

    python benchmarks/mvs_planes.py POSED_CAPTURE --level 2 --depths 160,33 --out OUT.json

POSED_CAPTURE: a capture folder with cameras and masks (a run's ``posed/``). ``--depths``: values of MvsConfig.depths
(the default 160); the planes swept at the level follow geometry/mvs_levels.py ``planes_at_level`` (for 3072x2048
photos at level 2: 160 -> 192 planes; 33 -> 40, the count the rule before gave them).
"""

from __future__ import annotations

import argparse
import json
import platform
import time

from gitinfo import commit


def main() -> None:
    from texstream.capture.capture_json import read_capture
    from texstream.geometry import make_mesh
    from texstream.geometry.hull import load_masks
    from texstream.geometry.mvs import MvsConfig, capture_dense_points

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("capture")
    ap.add_argument("--level", type=int, default=2)
    ap.add_argument("--depths", default="160,33")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--out", required=True)
    a = ap.parse_args()
    cap = read_capture(a.capture)
    masks = load_masks(cap)
    bounds, where = make_mesh._dense_bounds(cap, make_mesh.MeshConfig(device=a.device), masks)
    rows = []
    for spec in a.depths.split(","):
        cfg = MvsConfig(level=a.level, depths=int(spec))
        t = time.perf_counter()
        dp = capture_dense_points(cap, masks, bounds, cfg, a.device)
        rows.append({"depths_option": int(spec), "swept": dp.report["depths"], "points": dp.report["points"],
                     "pixel_points": dp.report["pixel_points"], "seconds": time.perf_counter() - t})
        print(rows[-1], flush=True)
    doc = {"command": "python benchmarks/mvs_planes.py " + " ".join(__import__("sys").argv[1:]), "commit": commit(),
           "machine": platform.node(), "capture": a.capture, "level": a.level, "depth_range_from": where, "rows": rows}
    with open(a.out, "w") as f:
        json.dump(doc, f, indent=1)


if __name__ == "__main__":
    main()
