"""texstream against the tools users would pick instead: held-out error against run time (JSON + PNG).

    python benchmarks/peers/run.py --quick                                   # every CPU peer, toy size
    python benchmarks/peers/run.py --out out/peers_cpu                       # the CPU study (small ornament)
    python benchmarks/peers/run.py --device cuda:0 --out $OUT/peers_h100     # the GPU study (one H100)
    python benchmarks/peers/run.py --plot-only out/peers_cpu/peers.json      # replot
    python benchmarks/peers/run.py --plot-only a/peers.json,b/peers.json --out merged   # merge runs, then replot

Methods (``--methods``; docs/peers.md says what each is and how a stronger version would differ):
``texstream_default`` (``texstream fit`` with the command's defaults, from a folder: model choice, shared
materials, traced polish; a whole fit per check of the stopping rule), ``texstream`` (its core fit: LM,
filtered photo sampling, default FitConfig), ``texstream_bilinear`` (the same fit on
the peers' bilinear samples), ``scipy`` (two-step, MINPACK LM per texel; ``scipy_blocks``: sparse
block-diagonal trf, not in the default list: 16x slower on the toy case, docs/peers.md), ``torch_adam``,
``torch_lbfgs``, ``mitsuba`` (differentiable rendering, principled BSDF).

Data: the synthetic ornament at ``--scale`` with ``--photos`` photos, ``--datasets`` clean (float,
noise-free) and noisy8 (8-bit sRGB, camera noise sigma 0.01), every 8th photo held out and every 8th of
the rest kept back for validation. Each method
runs in its own process (``--worker``; one CPU thread each on the CPU: OMP/MKL threads 1, torch 1
thread, Dr.Jit 1 thread, like Warp's CPU kernels) so its peak host memory (ru_maxrss) and peak device
memory (NVML, the whole GPU above the level at process start) are its own.

Reported per method and data set: the validation and held-out PSNR traces against wall time (set-up that
every method shares, rendering the data and building texstream's photo set, is not timed; resampling, the
initial guess and the fit are; ``texstream_default`` is timed whole, from its folder), where the stopping
rule (common.early_stop: validation views only, the same for every method) stops and the model it hands
back, that model's held-out pooled and worst-view PSNR, the speed ratios against texstream's core fit (to
each one's stop; to the same validation PSNR), the best held-out PSNR anywhere (for reference only) and the
peak memory.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

METHODS = ("texstream_default", "texstream", "texstream_bilinear", "scipy", "torch_adam", "torch_lbfgs", "mitsuba")
QUICK_METHODS = METHODS[1:]
"""--quick (CI) leaves out texstream_default: a whole fit per check is minutes on two cores"""
LABELS = {"texstream_default": "texstream fit (defaults)", "texstream": "texstream core fit (LM, filtered)", "texstream_bilinear": "texstream core fit (LM, bilinear samples)",
          "scipy": "scipy two-step (MINPACK LM per texel)", "scipy_blocks": "scipy two-step (sparse trf blocks)",
          "torch_adam": "PyTorch Adam", "torch_lbfgs": "PyTorch L-BFGS", "mitsuba": "Mitsuba 3 (principled, Adam)"}
# iteration budgets: long enough that the stopping rule stops every method before it (docs/peers.md);
# texstream_default's is the command's own max_iterations
BUDGETS = {"quick": {"texstream": 12, "texstream_bilinear": 12, "scipy": 10, "scipy_blocks": 30, "torch_adam": 40,
                     "torch_lbfgs": 20, "mitsuba": 15, "texstream_default": 100},
           "full": {"texstream": 30, "texstream_bilinear": 30, "scipy": 100, "scipy_blocks": 100, "torch_adam": 1000,
                    "torch_lbfgs": 100, "mitsuba": 100, "texstream_default": 100}}
DEFAULT_CHECKS = {"cpu": (2, 1), "cuda": (6, 4)}
"""texstream_default's checks of --max-iterations (every one up to the first, then this many per doubling): a
doubling on the 2-core CPU, where each whole fit takes minutes; the denser schedule of scipy's runs on a GPU"""


def run_method(method: str, data, device: str, iterations: int, quick: bool, partial: Path | None = None) -> dict:
    if method == "texstream_default":
        import peer_texstream_default

        dense, per_doubling = DEFAULT_CHECKS["cuda" if device.startswith("cuda") else "cpu"]
        return peer_texstream_default.run(data, device, iterations, dense, per_doubling, partial)
    if method in ("texstream", "texstream_bilinear"):
        import peer_texstream

        return peer_texstream.run(data, device, iterations, "filtered" if method == "texstream" else "bilinear")
    if method in ("scipy", "scipy_blocks"):
        import peer_scipy

        if device != "cpu":
            raise SystemExit("the scipy peer runs on the CPU only")
        return peer_scipy.run(data, device, "per_texel" if method == "scipy" else "blocks",
                              batch=256, max_nfev=iterations)
    if method in ("torch_adam", "torch_lbfgs"):
        import peer_torch

        return peer_torch.run(data, device, method.split("_")[1], iterations)
    if method == "mitsuba":
        import peer_mitsuba

        return peer_mitsuba.run(data, device, iterations, views_per_step=4 if quick else 8)
    raise SystemExit(f"unknown method {method!r}: use {', '.join(METHODS)} or scipy_blocks")


def partial_path(worker_out) -> Path:
    """Where a worker whose checks are whole runs (texstream_default) keeps its trace so far."""
    return Path(str(worker_out) + ".partial")


def worker(a) -> None:
    """One method on one data set in this process; writes its JSON to ``a.worker_out``."""
    from common import DeviceMemoryPoller, host_rss_mb, load_data, peak_host_mb

    poller = DeviceMemoryPoller(a.device)
    if a.device == "cpu":
        try:
            import torch

            torch.set_num_threads(1)
        except ImportError:
            pass
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    wp.config.quiet = True
    t0 = time.perf_counter()
    data = load_data(a.dataset, a.scale, a.photos, device=a.device)
    rss_data = host_rss_mb()
    out = run_method(a.worker, data, a.device, a.iterations, a.quick, partial_path(a.worker_out))
    out.update({"method": a.worker, "dataset": a.dataset, "iterations_budget": a.iterations,
                "peak_host_mb": peak_host_mb(), "host_mb_after_data": rss_data,
                "peak_device_mb": poller.result_mb(), "process_s": time.perf_counter() - t0,
                "train_photos": len(data.train_frames), "held_photos": len(data.held_frames),
                "image_size": list(data.train_images[0].shape[:2])})
    Path(a.worker_out).write_text(json.dumps(out))


def run_in_process(results: dict, datasets: list, methods: list, budgets: dict, a) -> None:
    """``--quick``: every method in this process (no per-method memory figures)."""
    import traceback

    import warp as wp

    from common import load_data

    wp.config.log_level = wp.LOG_WARNING
    wp.config.quiet = True
    try:
        import torch

        torch.set_num_threads(1)
    except ImportError:
        pass
    for ds in datasets:
        data = load_data(ds, a.scale, a.photos, device=a.device)
        runs = results["datasets"].setdefault(ds, {})
        for m in methods:
            t0 = time.perf_counter()
            try:
                runs[m] = run_method(m, data, a.device, budgets.get(m, 30), True)
                runs[m]["process_s"] = time.perf_counter() - t0
            except Exception:  # noqa: BLE001  (a peer that fails is reported, the others still run)
                runs[m] = {"error": traceback.format_exc()[-2000:]}
            summarise(results)
            print(f"{ds:7s} {m:20s} {time.perf_counter() - t0:6.1f} s  {stop_line(runs[m])}", flush=True)


def stop_line(r: dict) -> str:
    """One line of progress: where the rule stopped the method and what the model it handed back scores."""
    if "error" in r:
        return f"FAILED: {r['error'][-300:]}"
    s = r.get("summary") or {}
    if s.get("heldout_psnr_at_stop_db") is None:
        return "no finite validation score"
    return (f"stopped at iteration {s['iteration_stopped']} ({s['stopped_by']}) after {s['time_to_stop_s']:.2f} s, "
            f"handed back {s['iteration_handed_back']}: validation {s['val_psnr_at_stop_db']:.2f} dB, held out "
            f"{s['heldout_psnr_at_stop_db']:.2f} / worst {s['worst_view_at_stop_db']:.2f} dB")


def summarise(results: dict) -> None:
    """Each trace through the stopping rule (common.summarise_trace), then the speed ratios against texstream's
    core fit, on CPU time (the time on an idle core: every method runs one thread, and the shared CPU box's load
    inflates wall times unevenly; wall time where a trace has no CPU time, e.g. on the GPU): to each one's stop,
    and to the same validation PSNR (the first check of texstream's core fit at or above the validation PSNR of
    the model the method handed back, against the method's time to that model)."""
    from common import summarise_trace

    for ds, runs in results["datasets"].items():
        for r in runs.values():
            if "trace" in r:
                r["summary"] = summarise_trace(r["trace"])
        ts = runs.get("texstream")
        ts_s = (ts or {}).get("summary") or {}
        for name, r in runs.items():
            s = r.get("summary")
            if not s or s.get("time_to_stop_s") is None or not ts_s.get("time_to_stop_s"):
                continue
            # CPU time on the CPU where both traces have it (a run recorded before CPU times were: wall for both)
            cpu = results["device"] == "cpu" and s.get("cpu_to_stop_s") is not None and ts_s.get("cpu_to_stop_s") is not None
            key = "cpu" if cpu else "time"
            s["ratio_clock"] = "cpu" if cpu else "wall"
            s["texstream_faster_to_stop"] = s[f"{key}_to_stop_s"] / ts_s[f"{key}_to_stop_s"]
            hit = next((x for x in ts["trace"] if x["val_psnr_db"] >= s["val_psnr_at_stop_db"]), None)
            t_hit = None if hit is None else hit["cpu_s" if cpu else "time_s"]
            s["texstream_time_to_this_val_psnr_s"] = t_hit
            s["texstream_faster_to_this_val_psnr"] = None if not t_hit else s[f"{key}_to_handed_back_s"] / t_hit


def table(results: dict) -> str:
    rows = ["| data | method | stopped at (by) | handed back | time to stop: CPU (s) | wall (s) | held-out pooled (dB) "
            "| worst view (dB) | validation (dB) | texstream core faster, to each stop | texstream core's time to this "
            "validation PSNR (s) | texstream core faster, same validation PSNR | best held-out anywhere (dB) "
            "| final held-out (dB) | one validation check, wall (s) | peak host (MB) | peak device (MB) |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    f = lambda x, p=2: "-" if x is None else (f"{x:.{p}f}" if isinstance(x, float) else str(x))  # noqa: E731
    x = lambda v: "-" if v is None else f"{v:.1f}x"  # noqa: E731
    for ds, runs in results["datasets"].items():
        for name, r in runs.items():
            s = r.get("summary")
            if not s or s.get("time_to_stop_s") is None:
                rows.append(f"| {ds} | {LABELS.get(name, name)} | failed: {r.get('error', '?')[:80]} "
                            "| | | | | | | | | | | | | | |")
                continue
            reached = x(s.get("texstream_faster_to_this_val_psnr"))
            if s.get("texstream_time_to_this_val_psnr_s") is None and name != "texstream":
                reached = "not reached"
            final = r["as_is"]["heldout_psnr_db"] if "as_is" in r else s["final_heldout_psnr_db"]
            wall_ratio = " (wall)" if s.get("ratio_clock") == "wall" and results["device"] == "cpu" else ""
            rows.append(f"| {ds} | {LABELS.get(name, name)} | {s['iteration_stopped']} ({s['stopped_by']}) "
                        f"| {s['iteration_handed_back']} | {f(s.get('cpu_to_stop_s'))} | {f(s['time_to_stop_s'])} "
                        f"| {f(s['heldout_psnr_at_stop_db'])} | {f(s['worst_view_at_stop_db'])} "
                        f"| {f(s['val_psnr_at_stop_db'])} | {x(s.get('texstream_faster_to_stop'))}{wall_ratio} "
                        f"| {f(s.get('texstream_time_to_this_val_psnr_s'))} | {reached}{wall_ratio} "
                        f"| {f(s['oracle_best_heldout_psnr_db'])} | {f(final)} "
                        f"| {f(r.get('val_check_s'), 3)} | {f(r.get('peak_host_mb'), 0)} | {f(r.get('peak_device_mb'), 0)} |")
    return "\n".join(rows)


def plot(results: dict, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from common import early_stop

    ds_names = list(results["datasets"])
    cpu = results["device"] == "cpu"  # CPU seconds where the trace has them (the time on an idle core)
    when = lambda row: row["cpu_s"] if cpu and row.get("cpu_s") is not None else row["time_s"]  # noqa: E731
    fig, axes = plt.subplots(2, len(ds_names), figsize=(6.5 * len(ds_names), 8.5), squeeze=False, sharex="col")
    for col, ds in enumerate(ds_names):
        for k, (name, r) in enumerate(results["datasets"][ds].items()):
            if "trace" not in r:
                continue
            c = f"C{k}"
            t = [max(when(x), 1e-3) for x in r["trace"]]
            for row, key in ((0, "val_psnr_db"), (1, "heldout_psnr_db")):
                axes[row][col].semilogx(t, [x[key] for x in r["trace"]], "o-", ms=2, color=c,
                                        label=LABELS.get(name, name))
            s = r.get("summary") or {}
            if s.get("time_to_handed_back_s") is not None:  # the model the rule hands back, and where it stopped
                tb = max(when(r["trace"][early_stop(r["trace"])["best"]]), 1e-3)
                axes[0][col].plot([tb], [s["val_psnr_at_stop_db"]], "*", ms=11, color=c)
                axes[1][col].plot([tb], [s["heldout_psnr_at_stop_db"]], "*", ms=11, color=c)
                axes[0][col].axvline(max(when(r["trace"][early_stop(r["trace"])["stop"]]), 1e-3), color=c, lw=0.6, ls=":")
        axes[0][col].set_title(f"{ds}: ornament x{results['scale']}, {results.get('photos_total')} photos")
        axes[0][col].set_ylabel("validation pooled PSNR (dB): the rule's input")
        axes[1][col].set_ylabel("held-out pooled PSNR (dB): the score")
        axes[1][col].set_xlabel(f"{'CPU' if cpu else 'wall'} time (s, log); star: the model handed back, dotted: the stop")
        axes[0][col].legend(fontsize=7)
    fig.suptitle(f"validation and held-out error against run time on {results['device']} ({results['machine']}), "
                 f"commit {results['commit']}", fontsize=9)
    fig.tight_layout()
    fig.savefig(out / "peers.png", dpi=110)
    plt.close(fig)


def merge(runs: list[dict]) -> dict:
    """Several runs' results as one (the first's header; the runs it came from listed in ``merged_from``)."""
    out = dict(runs[0], datasets={})
    if len(runs) > 1:
        out["merged_from"] = [{k: r.get(k) for k in ("command", "commit", "date", "machine", "gpu")} for r in runs]
    for r in runs:
        for ds, methods in r["datasets"].items():
            for name, run in methods.items():
                out["datasets"].setdefault(ds, {}).setdefault(name, run)
    return out


def commit() -> str:
    try:
        return subprocess.check_output(["git", "rev-parse", "--short", "HEAD"], cwd=HERE, text=True).strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="toy size (scale 0.01, 120 photos), clean data, short budgets")
    ap.add_argument("--device", default="cpu", help="cpu or cuda:N")
    ap.add_argument("--scale", type=float, default=None, help="ornament scale (default 0.02 on the CPU, 0.25 on CUDA)")
    ap.add_argument("--photos", type=int, default=None,
                    help="photos before the hold-out split (default 880 on the CPU, 1760 on CUDA; 120 quick)")
    ap.add_argument("--datasets", default=None, help="comma list of clean, noisy8 (default both; quick: clean)")
    ap.add_argument("--methods", default=None, help=f"comma list (default: {','.join(METHODS)}; scipy is CPU only)")
    ap.add_argument("--out", default="out/peers")
    ap.add_argument("--timeout", type=float, default=900.0, help="seconds per method before it is stopped")
    ap.add_argument("--plot-only", default=None,
                    help="re-summarise, table and plot a finished run's peers.json; several (comma list): merged "
                         "into --out (each data set's methods in file order, a method's first run kept)")
    ap.add_argument("--worker", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--worker-out", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--dataset", default="clean", help=argparse.SUPPRESS)
    ap.add_argument("--iterations", type=int, default=0, help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.plot_only:  # re-summarise, table and plot finished runs' JSON
        paths = [Path(x) for x in a.plot_only.split(",")]
        results = merge([json.loads(x.read_text()) for x in paths])
        out = paths[0].parent if len(paths) == 1 else Path(a.out)
        out.mkdir(parents=True, exist_ok=True)
        summarise(results)
        (out / "peers.json").write_text(json.dumps(results, indent=1))
        (out / "peers_table.md").write_text(table(results) + "\n")
        plot(results, out)
        print(table(results))
        return 0
    cuda = a.device.startswith("cuda")
    if a.scale is None:
        a.scale = 0.01 if a.quick else (0.25 if cuda else 0.02)
    if a.photos is None:
        a.photos = 120 if a.quick else (1760 if cuda else 880)
    if a.worker:
        worker(a)
        return 0
    from common import machine

    datasets = (a.datasets or ("clean" if a.quick else "clean,noisy8")).split(",")
    default_methods = QUICK_METHODS if a.quick else METHODS
    methods = (a.methods or ",".join(m for m in default_methods if not (cuda and m == "scipy"))).split(",")
    budgets = BUDGETS["quick" if a.quick else "full"]
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    results = {"device": a.device, "scale": a.scale, "photos_total": a.photos, "quick": a.quick, "machine": machine(),
               "commit": commit(), "date": time.strftime("%Y-%m-%d"), "budgets": budgets,
               "command": " ".join([Path(sys.executable).name, *sys.argv]), "datasets": {}}
    if cuda:
        import shutil

        if shutil.which("nvidia-smi"):
            results["gpu"] = subprocess.run(["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"],
                                            capture_output=True, text=True).stdout.strip()
    env = dict(os.environ)
    if not cuda:  # one thread per method (see the module doc)
        env.update(OMP_NUM_THREADS="1", MKL_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
    t_all = time.perf_counter()
    if a.quick:  # one process, the data rendered once: seconds, not memory figures
        run_in_process(results, datasets, methods, budgets, a)
        methods = []
    for ds in datasets:
        runs = results["datasets"].setdefault(ds, {})
        for m in methods:
            wout = out / f"{ds}_{m}.json"
            cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", m, "--worker-out", str(wout),
                   "--dataset", ds, "--scale", str(a.scale), "--photos", str(a.photos), "--device", a.device,
                   "--iterations", str(budgets.get(m, 30))] + (["--quick"] if a.quick else [])
            t0 = time.perf_counter()
            try:
                p = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=a.timeout)
                ok = p.returncode == 0 and wout.exists()
                # a worker killed by a signal (a crash in a native library) prints nothing: keep its exit status
                runs[m] = json.loads(wout.read_text()) if ok else {
                    "error": f"exit status {p.returncode}: " + ((p.stderr or p.stdout).strip()[-2000:] or "no output")}
            except subprocess.TimeoutExpired:
                part = partial_path(wout)  # texstream_default's checks so far: the rule applies to them as they are
                runs[m] = ({**json.loads(part.read_text()), "error_partial": f"stopped after {a.timeout:.0f} s"}
                           if part.exists() else {"error": f"stopped after {a.timeout:.0f} s"})
            summarise(results)
            print(f"{ds:7s} {m:20s} {time.perf_counter() - t0:6.1f} s  {stop_line(runs[m])}", flush=True)
            (out / "peers.json").write_text(json.dumps(results, indent=1))
    results["total_s"] = time.perf_counter() - t_all
    (out / "peers.json").write_text(json.dumps(results, indent=1))
    (out / "peers_table.md").write_text(table(results) + "\n")
    plot(results, out)
    print(table(results))
    return 0 if all("error" not in r for runs in results["datasets"].values() for r in runs.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
