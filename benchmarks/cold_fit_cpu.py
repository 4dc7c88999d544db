"""`texstream fit` with an empty Warp kernel cache, each module's compile time from Warp's own log (issue 40's
cold-start figures on the CPU: the optimiser module rebuilt once per new parameter layout, before and after a
module per generic kernel).

    python benchmarks/cold_fit_cpu.py fit CAPTURE --mesh CAPTURE/ground_truth -o OUT --holdout-every 4 --device cpu

The capture of docs/scale.md: `texstream synth ornament -o CAPTURE --scale 0.02 --photos 24 --image-size 160`.
Prints each module's compiles and their total milliseconds, then the command's seconds.
"""

from __future__ import annotations

import collections
import io
import re
import sys
import tempfile
import time
from contextlib import redirect_stdout

import warp as wp

wp.config.kernel_cache_dir = tempfile.mkdtemp(prefix="texstream-cold-cache-")  # empty: every module compiles
wp.config.verbose = True
wp.LOG_WARNING = getattr(wp, "LOG_INFO", 20)  # the CLI lowers Warp's log to warnings: keep its module lines

from texstream.pipelines.cli import main  # noqa: E402  (after Warp's cache is set)

MODULE_LINE = re.compile(r"^Module (\S+) \S+ load on device '\S+' took ([0-9.]+) ms")


if __name__ == "__main__":
    log = io.StringIO()
    t0 = time.perf_counter()
    with redirect_stdout(log):
        rc = main(sys.argv[1:])
    seconds = time.perf_counter() - t0
    per = collections.defaultdict(list)
    for line in log.getvalue().splitlines():
        m = MODULE_LINE.match(line)
        if m:
            per[m.group(1)].append(float(m.group(2)))
    for name, ms in sorted(per.items(), key=lambda kv: -sum(kv[1])):
        print(f"{name:55s} {len(ms):3d} compiles {sum(ms):9.0f} ms")
    print(f"all compiles {sum(sum(v) for v in per.values()) / 1000:.1f} s; the command {seconds:.1f} s (exit {rc})")
    sys.exit(rc)
