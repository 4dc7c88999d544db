"""`texstream fit` on the CPU with one worker thread and with several (``--stream.cpu-threads``,
fit/multi/cpu_threads.py): the command's wall time, the core fit loop's, how much of the loop's CPU time
runs inside Warp's kernels (the part threads share out: the launches release the GIL) and whether the models
are equal to the bit; writes JSON.

    python benchmarks/cpu_threads.py --scale 0.1 --modes off,defaults --threads 1,auto --repeats 2 --out DIR

writes DIR/cpu_threads.json (``--summarise FILE`` recomputes a file's summary). ``--threads``: the counts
given as ``--stream.cpu-threads N``, ``auto`` for none given (the default, 0: one per core, capped; the run
records the threads it took). In benchmarks/results/cpu_threads_cpu/: ``quiet_off.json`` and
``quiet_defaults.json`` (the 2-core box with no other job running, ``--threads 1,2``),
``loaded_off_defaults.json`` (the same box with other jobs holding about one core), ``default_auto.json``
(``--threads 1,auto`` once the threads were the default, on the loaded box).

The demo capture (``texstream synth ornament --scale S``, 176 photos of 136x136 at 0.1) is made under
``--work`` unless ``--capture`` names one. Each repeat runs every thread count once per materials mode,
alternating the order (1, 2, then 2, 1), so a machine shared with other jobs loads them alike; every run
records the load average before and after it (``os.getloadavg``), because on a busy machine a second thread
finds no idle core.

Each run is a child process (``--child``: the command in-process with two probes): the time and the CPU time
(all threads) of the core fit (``_core_fit`` of fit/models/per_texel/fit.py, the tiles' set-up included),
and the CPU time each thread spends inside Warp's CPU kernel calls (``warp._src.context.invoke``). From the
one-thread run's kernel share f of the loop's CPU time, ``amdahl_speedup_2`` = 1 / ((1 - f) + f / 2) is the
loop's speed-up two idle cores would give with perfectly balanced tiles (the host work between launches holds
the GIL); ``loop_cores_used`` = CPU time / wall time says how many cores a run actually got.
``same_maps_to_the_bit``: every EXR map of the model folder (pixel arrays) and the trace's objectives against
the one-thread run of the same mode.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import threading
import time
from pathlib import Path

from gitinfo import commit

HERE = Path(__file__).resolve().parent


def child(out_json: str, argv: list[str]) -> int:
    """Run ``texstream`` with ``argv`` in this process, probing the core fit and the kernel calls; writes
    the probes to ``out_json``."""
    import warp._src.context as wctx

    from texstream.fit.models.per_texel import fit as per_texel_fit
    from texstream.pipelines import cli

    kernel_cpu: dict[int, float] = {}
    launches: dict[int, int] = {}
    lock = threading.Lock()
    invoke = wctx.invoke

    def timed_invoke(*a, **kw):
        c0 = time.thread_time()
        try:
            return invoke(*a, **kw)
        finally:
            dt = time.thread_time() - c0
            me = threading.get_ident()
            with lock:
                kernel_cpu[me] = kernel_cpu.get(me, 0.0) + dt
                launches[me] = launches.get(me, 0) + 1

    probe: dict = {}
    core_fit = per_texel_fit._core_fit

    def timed_core_fit(*a, **kw):
        kernel_cpu.clear()
        launches.clear()
        wctx.invoke = timed_invoke
        w0, c0 = time.perf_counter(), time.process_time()
        try:
            return core_fit(*a, **kw)
        finally:
            wctx.invoke = invoke
            probe.update(loop_wall_s=time.perf_counter() - w0, loop_cpu_s=time.process_time() - c0,
                         kernel_cpu_s_per_thread=sorted(kernel_cpu.values(), reverse=True),
                         launches=sum(launches.values()))

    per_texel_fit._core_fit = timed_core_fit
    t0 = time.perf_counter()
    code = cli.main(argv)
    probe["command_in_process_s"] = time.perf_counter() - t0
    Path(out_json).write_text(json.dumps(probe))
    return code


def read_maps(folder: Path) -> dict:
    """The model folder's EXR maps as pixel arrays (the files' headers may differ), by name."""
    import OpenImageIO as oiio

    return {p.name: oiio.ImageBuf(str(p)).get_pixels() for p in sorted(folder.glob("*.exr"))}


def thread_spec(text: str) -> int | str:
    """A ``--threads`` entry: a count, or ``auto`` (no ``--stream.cpu-threads``: the default)."""
    return "auto" if text.strip() == "auto" else int(text)


def one_run(capture: Path, out: Path, mode: str, threads: int | str, extra: list[str]) -> dict:
    """One `texstream fit` in a child process; its times, probes and load."""
    model = out / f"model_{mode}_t{threads}"
    probe_file = out / f"probe_{mode}_t{threads}.json"
    argv = ["fit", str(capture), "--mesh", str(capture / "ground_truth"), "-o", str(model), "--model", "lafortune",
            *([] if threads == "auto" else ["--stream.cpu-threads", str(threads)]),
            *(["--materials.mode", "off"] if mode == "off" else []), *extra]
    load0 = os.getloadavg()
    r0 = os.times()
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--child", str(probe_file), "--", *argv],
                          capture_output=True, text=True)
    wall = time.perf_counter() - t0
    r1 = os.times()
    if proc.returncode:
        raise SystemExit(f"texstream {' '.join(argv)} failed:\n{proc.stderr[-3000:]}")
    probe = json.loads(probe_file.read_text())
    manifest = json.loads((model / "model.json").read_text())
    kernel = sum(probe["kernel_cpu_s_per_thread"])
    return {"mode": mode, "threads": threads, "command_s": wall,
            "command_cpu_s": (r1.children_user - r0.children_user) + (r1.children_system - r0.children_system),
            "fit_loop_s": probe["loop_wall_s"], "fit_loop_cpu_s": probe["loop_cpu_s"],
            "loop_cores_used": probe["loop_cpu_s"] / max(probe["loop_wall_s"], 1e-9),
            "kernel_cpu_s": kernel, "kernel_share_of_loop_cpu": kernel / max(probe["loop_cpu_s"], 1e-9),
            "kernel_cpu_s_per_thread": probe["kernel_cpu_s_per_thread"], "launches": probe["launches"],
            "timings_s": manifest.get("timings_s"), "tiles": manifest.get("tiles"),
            "threads_taken": len((manifest.get("tiles") or {}).get("devices", [])) or 1,
            "iterations": len(json.loads((model / "trace.json").read_text())) - 1,
            "loadavg_before": load0, "loadavg_after": os.getloadavg(), "model": str(model)}


def compare(a: dict, b: dict) -> dict:
    """Whether run ``b``'s model equals run ``a``'s: maps to the bit, trace objectives exactly."""
    ma, mb = read_maps(Path(a["model"])), read_maps(Path(b["model"]))
    import numpy as np

    same_maps = ma.keys() == mb.keys() and all(np.array_equal(ma[k], mb[k]) for k in ma)
    ta = [r["objective"] for r in json.loads((Path(a["model"]) / "trace.json").read_text())]
    tb = [r["objective"] for r in json.loads((Path(b["model"]) / "trace.json").read_text())]
    rel = max((abs(x - y) / max(abs(x), 1e-300) for x, y in zip(ta, tb)), default=0.0)
    # the trace's sums over texels are added per tile, then across tiles: another order of float64 additions
    return {"same_maps_to_the_bit": bool(same_maps), "maps": sorted(ma), "same_iterations": len(ta) == len(tb),
            "same_trace_objectives": ta == tb, "trace_objective_max_rel_diff": rel}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--capture", help="a capture folder with ground_truth/ (default: synthesise the ornament)")
    ap.add_argument("--scale", type=float, default=0.1, help="the synthesised ornament's scale")
    ap.add_argument("--work", default="/tmp/texstream_cpu_threads", help="where the capture and models go")
    ap.add_argument("--modes", default="off,defaults", help="materials modes: off (--materials.mode off), defaults")
    ap.add_argument("--threads", default="1,auto",
                    help="thread counts to compare (the first is the reference; auto: the default, none given)")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--fit-arg", action="append", default=[], help="an extra `texstream fit` argument (repeatable)")
    ap.add_argument("--out", required=True)
    a = ap.parse_args()
    work = Path(a.work)
    work.mkdir(parents=True, exist_ok=True)
    capture = Path(a.capture) if a.capture else work / f"ornament_{a.scale:g}"
    if not capture.exists():
        subprocess.run([sys.executable, "-m", "texstream.pipelines.cli", "synth", "ornament", "--scale", str(a.scale),
                        "-o", str(capture)], check=True)
    threads = [thread_spec(t) for t in a.threads.split(",")]
    runs, checks = [], []
    for rep in range(a.repeats):
        for mode in [m.strip() for m in a.modes.split(",") if m.strip()]:
            order = threads if rep % 2 == 0 else threads[::-1]
            done = {}
            for n in order:
                done[n] = one_run(capture, work, mode, n, a.fit_arg)
                done[n]["repeat"] = rep
                runs.append(done[n])
                print(json.dumps({k: done[n][k] for k in ("mode", "threads", "threads_taken", "command_s", "fit_loop_s",
                                                          "loop_cores_used", "kernel_share_of_loop_cpu",
                                                          "loadavg_before")}), flush=True)
            for n in threads[1:]:
                checks.append({"mode": mode, "repeat": rep, "threads": n, **compare(done[threads[0]], done[n])})
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    result = {"commit": commit(), "machine": platform.platform(), "cpus": os.cpu_count(),
              "command": " ".join([Path(sys.executable).name, *sys.argv]), "capture": str(capture),
              "args": vars(a), "runs": runs, "checks": checks, "summary": summarise(runs, threads)}
    (out / "cpu_threads.json").write_text(json.dumps(result, indent=1))
    print(json.dumps({"summary": result["summary"], "checks": checks}, indent=1))


def own_core_loop_s(run: dict) -> float:
    """The loop's time were every thread on a core of its own: its CPU time outside the kernels (host work,
    under the GIL: one after another) plus the busiest thread's kernel time."""
    return run["fit_loop_cpu_s"] - run["kernel_cpu_s"] + max(run["kernel_cpu_s_per_thread"], default=0.0)


def summarise(runs: list[dict], threads: list[int]) -> dict:
    """Per materials mode: the fastest command and loop per thread count, their speed-ups over the first
    count, and the speed-ups that cores of their own would give (:func:`own_core_loop_s`, from CPU times:
    what the load of other jobs hides)."""
    summary = {}
    for mode in sorted({r["mode"] for r in runs}):
        by = {n: [r for r in runs if r["mode"] == mode and r["threads"] == n] for n in threads}
        best = {n: {"command_s": min(r["command_s"] for r in by[n]), "fit_loop_s": min(r["fit_loop_s"] for r in by[n])}
                for n in threads}
        f = min(r["kernel_share_of_loop_cpu"] for r in by[threads[0]])
        summary[mode] = {"fastest": best, "kernel_share_of_loop_cpu_one_thread": f,
                         "amdahl_speedup_2": 1.0 / ((1.0 - f) + f / 2.0),
                         "speedup_fit_loop": {n: best[threads[0]]["fit_loop_s"] / best[n]["fit_loop_s"] for n in threads},
                         "speedup_command": {n: best[threads[0]]["command_s"] / best[n]["command_s"] for n in threads},
                         "loop_cpu_s_one_thread": min(r["fit_loop_cpu_s"] for r in by[threads[0]]),
                         "own_core_loop_s": {n: min(own_core_loop_s(r) for r in by[n]) for n in threads},
                         "loadavg_1min": [r["loadavg_before"][0] for r in runs if r["mode"] == mode]}
        own = summary[mode]["own_core_loop_s"]
        summary[mode]["own_core_speedup_fit_loop"] = {n: own[threads[0]] / own[n] for n in threads}
    return summary


if __name__ == "__main__":
    if len(sys.argv) > 2 and sys.argv[1] == "--child":
        sys.exit(child(sys.argv[2], sys.argv[4:]))
    if len(sys.argv) > 2 and sys.argv[1] == "--summarise":  # a JSON of this script's, summarised again
        path = Path(sys.argv[2])
        data = json.loads(path.read_text())
        data["summary"] = summarise(data["runs"], [thread_spec(t) for t in data["args"]["threads"].split(",")])
        path.write_text(json.dumps(data, indent=1))
        print(json.dumps(data["summary"], indent=1))
        sys.exit(0)
    main()
