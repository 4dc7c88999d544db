"""The mesh and refine stages alone (``texstream mesh``, ``texstream refine``) on a finished run's folder, under
several option sets: each one's wall time, CPU time (every thread), the load average before and after, and what
it made (dense points, faces; the refine's residuals before and after, camera turn); writes JSON.

    python benchmarks/refine_mesh_stages.py RUN --out DIR [--stages mesh,refine] [--repeats 1]
        [--variant NAME=ARGS ...]

RUN is a ``texstream run`` output folder (its posed/ and atlas/ are the stages' inputs; nothing in it is
written). A variant is a name and the extra arguments of both commands, e.g. ``one=--threads 1`` for refine
(``--mvs.threads 1`` for mesh); the default variants: ``defaults`` and ``one_thread``. Each repeat runs every
variant once, alternating their order, so a machine shared with other jobs loads them alike. Issue 40's
temple numbers came from ``RUN`` = a ``texstream run ../shared/data/middlebury_temple_sparse``.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shlex
import subprocess
import sys
import time
from pathlib import Path

STAGE_ARGS = {
    "mesh": lambda run, out: ["mesh", str(run / "posed"), "-o", str(out), "--device", "cpu"],
    "refine": lambda run, out: ["refine", str(run / "posed"), str(run / "atlas"), "-o", str(out), "--device", "cpu"],
}
DEFAULT_VARIANTS = {"defaults": {"mesh": [], "refine": []},
                    "one_thread": {"mesh": ["--mvs.threads", "1"], "refine": ["--threads", "1"]}}


def made(stage: str, out: Path) -> dict:
    """What the stage wrote, in a few numbers."""
    if stage == "mesh":
        rep = json.loads((out / "mesh_report.json").read_text())
        dense = rep.get("dense", {})
        return {"dense_points": dense.get("points"), "dense_seconds": dense.get("seconds"),
                "faces": rep["clean"]["after"]["faces"], "stage_seconds": rep.get("seconds")}
    s = json.loads((out / "refine.json").read_text())
    return {"residual_before": s["residual_before"], "residual_after": s["residual_after"],
            "camera_rotation_deg_median": s["camera_rotation_deg"]["median"],
            "iterations": s["levels"].get("iterations"), "stage_seconds": s["seconds"]}


def run_once(stage: str, run: Path, out: Path, extra: list[str]) -> dict:
    cmd = [sys.executable, "-m", "texstream.pipelines.cli", *STAGE_ARGS[stage](run, out), *extra]
    load = os.getloadavg()[0]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return {"stage": stage, "command": shlex.join(cmd), "wall_s": round(wall, 2), "cpu_s": round(cpu, 2),
            "load_before": round(load, 2), "load_after": round(os.getloadavg()[0], 2), **made(stage, out)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--stages", default="mesh,refine")
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--variant", action="append", default=[],
                    help="NAME=STAGE:ARGS[;STAGE:ARGS] (e.g. 'coarse_off=refine:--no-coarse-texels')")
    args = ap.parse_args(argv)
    variants = DEFAULT_VARIANTS if not args.variant else {}
    for v in args.variant:
        name, spec = v.split("=", 1)
        variants[name] = {s: [] for s in STAGE_ARGS}
        for part in filter(None, spec.split(";")):
            stage, extra = part.split(":", 1)
            variants[name][stage] = shlex.split(extra)
    rows = []
    names = list(variants)
    for rep in range(args.repeats):
        for name in names if rep % 2 == 0 else names[::-1]:
            for stage in args.stages.split(","):
                row = run_once(stage, args.run, args.out / f"{stage}_{name}_{rep}", variants[name][stage])
                rows.append({"variant": name, "repeat": rep, **row})
                print(json.dumps(rows[-1]), flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "refine_mesh_stages.json").write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
