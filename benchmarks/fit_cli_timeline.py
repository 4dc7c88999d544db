"""Where `texstream fit` spends its wall time from start to written model folder (writes JSON).

    python benchmarks/fit_cli_timeline.py --capture CAPTURE --mesh ATLAS --out DIR [--runs 3] -- [fit options]

Runs ``texstream fit CAPTURE --mesh ATLAS -o DIR/model_K ...`` ``--runs`` times as a user does (a new
process each time; the first run may compile kernels, so the figures of the later runs are the warm ones)
and stamps every line the command prints with the seconds since the process started, so the JSON holds the
timeline: Python and module imports up to the fit's first phase line, the phases it announces, and the
total. With it, ``model.json``'s ``timings_s`` (inputs and set-up, fit, renders) and ``photos``
(residency). Extra arguments after ``--`` go to ``texstream fit``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

from gitinfo import commit


def timed_run(cmd: list[str]) -> tuple[float, list[tuple[float, str]], int]:
    """(wall seconds, [(seconds since start, line)], exit code) of ``cmd``, stdout and stderr merged."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, bufsize=1,
                            env=dict(os.environ, PYTHONUNBUFFERED="1"))
    lines = []

    def read():
        for line in proc.stdout:
            lines.append((time.perf_counter() - t0, line.rstrip()))

    reader = threading.Thread(target=read)
    reader.start()
    code = proc.wait()
    reader.join()
    return time.perf_counter() - t0, lines, code


def capture_arguments(doc: str, argv: list[str]) -> tuple[argparse.ArgumentParser, list[str], list[str]]:
    """(a parser with --capture, --mesh and --out, the arguments before ``--``, the ``texstream fit`` options after
    it) of a benchmark that runs ``texstream fit`` on a capture folder."""
    extra = argv[argv.index("--") + 1:] if "--" in argv else []
    argv = argv[:argv.index("--")] if "--" in argv else argv
    ap = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    ap.add_argument("--capture", required=True)
    ap.add_argument("--mesh", required=True)
    ap.add_argument("--out", required=True)
    return ap, argv, extra


def main() -> None:
    ap, argv, extra = capture_arguments(__doc__, sys.argv[1:])
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--texstream", default=shutil.which("texstream") or "texstream")
    a = ap.parse_args(argv)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    runs = []
    for k in range(a.runs):
        model = out / f"model_{k}"
        shutil.rmtree(model, ignore_errors=True)
        cmd = [a.texstream, "fit", a.capture, "--mesh", a.mesh, "-o", str(model), *extra]
        wall, lines, code = timed_run(cmd)
        row = {"run": k, "wall_s": wall, "exit_code": code, "lines": lines}
        man = model / "model.json"
        if man.is_file():
            m = json.loads(man.read_text())
            row.update({"timings_s": m.get("timings_s"), "setup_s": m.get("setup_s"),
                        "residency": m.get("photos", {}).get("residency"),
                        "iterations": m.get("final", {}).get("iteration"),
                        "fit_time_s": m.get("final", {}).get("time_s")})
            first = next((t for t, line in lines if line.strip().startswith("fit:")), None)
            row["until_first_phase_line_s"] = first
        runs.append(row)
        print(f"run {k}: wall {wall:.2f} s, exit {code}, timings {row.get('timings_s')}, "
              f"first phase line at {row.get('until_first_phase_line_s')}", flush=True)
    doc = {"command": " ".join(["python benchmarks/fit_cli_timeline.py", *sys.argv[1:]]), "commit": commit(),
           "machine": platform.node(), "cpus": os.cpu_count(), "runs": runs,
           "best_wall_s": min(r["wall_s"] for r in runs) if runs else None}
    (out / "fit_cli_timeline.json").write_text(json.dumps(doc, indent=2))


if __name__ == "__main__":
    main()
