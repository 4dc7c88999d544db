"""How busy the GPU is during `texstream fit` with its defaults: Warp's CUDA activity timing (kernels and copies)
over one run in this process, against the run's wall time and its phases (model.json ``timings_s``); and the
process's start: the seconds to import Warp, to start its runtime (CUDA's driver and context) and to import the
fit command. Writes JSON.

    python benchmarks/fit_gpu_activity.py --capture CAPTURE --mesh ATLAS --out DIR [-- fit options]

Run it after a warm-up fit (a warm kernel cache): the timing is of the fit, not of compiling. Kernel time that is
small beside the wall time means the run waits on the host (Python, launches, synchronisations), not the GPU.
"""

from __future__ import annotations

import collections
import json
import platform
import sys
import time
from pathlib import Path

from fit_cli_timeline import capture_arguments


def main() -> None:
    ap, argv, extra = capture_arguments(__doc__, sys.argv[1:])
    a = ap.parse_args(argv)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    start = {}
    t = time.perf_counter()
    import warp as wp

    start["import_warp_s"] = time.perf_counter() - t
    wp.config.quiet = True
    t = time.perf_counter()
    wp.init()
    start["warp_init_s"] = time.perf_counter() - t
    t = time.perf_counter()
    wp.get_device("cuda:0").context  # noqa: B018 - the primary context's creation, when init deferred it
    start["cuda_context_s"] = time.perf_counter() - t
    t = time.perf_counter()
    from texstream.pipelines import cli, cmd_fit  # noqa: F401 - the import a `texstream fit` makes

    start["import_fit_command_s"] = time.perf_counter() - t
    model = out / "model"
    cmd = ["fit", a.capture, "--mesh", a.mesh, "-o", str(model), *extra]
    wp.timing_begin(cuda_filter=wp.TIMING_KERNEL | wp.TIMING_MEMCPY | wp.TIMING_MEMSET)
    t = time.perf_counter()
    code = cli.main(cmd)
    wall = time.perf_counter() - t
    records = wp.timing_end()
    by_name = collections.defaultdict(lambda: [0, 0.0])
    for r in records:
        key = r.name.split("_", 1)[0] if r.filter != wp.TIMING_KERNEL else r.name[:60]
        by_name[key][0] += 1
        by_name[key][1] += r.elapsed / 1000.0  # ms -> s
    kernels = sum(v[1] for k, v in by_name.items())
    manifest = model / "model.json"
    timings = json.loads(manifest.read_text()).get("timings_s") if manifest.is_file() else None
    doc = {"command": " ".join(["python benchmarks/fit_gpu_activity.py", *sys.argv[1:]]), "machine": platform.node(),
           "exit_code": code, "start": start, "fit_wall_s": wall, "gpu_activity_s": kernels,
           "activity_records": len(records), "timings_s": timings,
           "top": sorted(([k, v[0], round(v[1], 4)] for k, v in by_name.items()), key=lambda r: -r[2])[:40]}
    (out / "fit_gpu_activity.json").write_text(json.dumps(doc, indent=1))
    print(json.dumps({k: doc[k] for k in ("start", "fit_wall_s", "gpu_activity_s", "timings_s")}, indent=1))
    for row in doc["top"][:25]:
        print(f"  {row[2]:8.4f} s  {row[1]:6d}x  {row[0]}")


if __name__ == "__main__":
    main()
