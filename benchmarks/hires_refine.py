"""The refine stage alone on the 6-megapixel photos of ``textured_sphere_6mp`` (11 photos of 3072x2048, their true
mesh and 1024x512 atlas), at the resolution it needs (JSON: wall and CPU seconds, the levels it ran and why).

    python benchmarks/hires_refine.py --capture out/hires/truth --out out/hires_refine [--full on]

The capture is the one benchmarks/hires_run.py renders. ``--full on`` also runs the refinement as before issue 40:
every blur level on the full-resolution photos (``photo_level 0``, ``pyramid off``, ``min_move 0``).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import time
from pathlib import Path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--capture", required=True)
    ap.add_argument("--out", default="out/hires_refine")
    ap.add_argument("--full", default="off", choices=("on", "off"))
    ap.add_argument("--device", default="cpu")
    args = ap.parse_args()

    import warp as wp

    from texstream.geometry.refine import RefineConfig, refine_stage

    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=Path(__file__).parent).stdout.strip()
    wp.config.quiet = True
    out, cap = Path(args.out), Path(args.capture)
    result = {"capture": str(cap), "device": args.device, "commit": commit,
              "machine": f"{platform.node()} ({os.cpu_count()} cores)",
              "command": f"python benchmarks/hires_refine.py --capture {cap} --out {out} --full {args.full}"}
    runs = [("needed", RefineConfig())]
    if args.full == "on":
        runs.append(("full", RefineConfig(photo_level=0, pyramid=False, min_move=0.0)))
    for label, cfg in runs:
        load, t0, c0 = os.getloadavg(), time.perf_counter(), time.process_time()
        s = refine_stage(cap, cap / "ground_truth", out / label, cfg, device=args.device).summary
        result[label] = {"seconds": time.perf_counter() - t0, "cpu_seconds": time.process_time() - c0,
                         "loadavg_before": [round(x, 2) for x in load],
                         "loadavg_after": [round(x, 2) for x in os.getloadavg()],
                         "resolution": s["resolution"], "levels": s["levels"],
                         "residual_before": s["residual_before"], "residual_after": s["residual_after"],
                         "camera_rotation_deg": s["camera_rotation_deg"]}
        out.mkdir(parents=True, exist_ok=True)
        (out / "hires_refine.json").write_text(json.dumps(result, indent=2, default=str))
        print(label, json.dumps(result[label], default=str), flush=True)


if __name__ == "__main__":
    main()
