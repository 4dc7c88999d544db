"""texstream itself: the image-streaming LM fit (fit/fitter.py run_fit), default options.

Three runs from the same start: one timed as benchmarks/fit_error_vs_time.py times it (kernels warmed
up by a one-iteration fit, the trace's per-iteration wall times), the same with the fit's clock reading
the process's CPU time (common.cpu_seconds: the time on an idle core, whatever the shared box's load), and
one that hands back the parameters after every iteration (run_fit's checkpoint hook), scored on the
validation and held-out views afterwards. LM is deterministic on one device, so iteration k of the runs
has the same parameters; the trace pairs the first two runs' times with the third's scores. This is the bare core fit
(no lobe support, unseen-texel fill, traced polish or shared materials): ``texstream fit`` with its
defaults is peer_texstream_default.py.
"""

from __future__ import annotations

import contextlib
import dataclasses
import time

from common import HeldOut, build_problem, cpu_seconds, fit_config


@contextlib.contextmanager
def cpu_clock():
    """The fitter's per-iteration clock (``time.perf_counter`` in fit/optim/fitter.py) reads CPU seconds."""
    from texstream.fit.optim import fitter

    class Clock:
        perf_counter = staticmethod(cpu_seconds)
        time = staticmethod(time.time)

    saved, fitter.time = fitter.time, Clock
    try:
        yield
    finally:
        fitter.time = saved


def run(data, device: str, iterations: int, photo_sampling: str = "filtered") -> dict:
    from texstream.fit.optim.fitter import initial_guess, run_fit

    import warp as wp

    cfg = fit_config(data, photo_sampling, max_iterations=iterations, sync_every=100000, rel_tol=0.0)
    prob = build_problem(data, cfg, device)
    run_fit(prob, dataclasses.replace(cfg, max_iterations=1))  # compile / warm up
    prob.passes = 0
    wp.synchronize_device(device)
    timed = run_fit(prob, cfg)
    prob.passes = 0
    with cpu_clock():
        cpu = {r["iteration"]: r["time_s"] for r in run_fit(prob, cfg).trace}
    snaps = []
    run_fit(prob, dataclasses.replace(cfg, sync_every=1),
            checkpoint=lambda st: snaps.append((int(st["iteration"]), st["p"].copy())))
    scorer = HeldOut(data, prob, prob.layout, device)
    times = {r["iteration"]: r["time_s"] for r in timed.trace}
    p0, _ = initial_guess(prob, cfg)
    trace = []
    for it, p in [(0, p0), *snaps, (timed.trace[-1]["iteration"], timed.params)]:
        if it in times and (not trace or trace[-1]["iteration"] < it):
            trace.append({"time_s": times[it], "cpu_s": cpu.get(it), "iteration": it, **scorer.score(p),
                          "train_psnr_db": timed.trace[it]["psnr_db"]})
    return {"trace": trace, "texels": prob.n, "passes": timed.passes, "layout": prob.layout.to_json(),
            "fit_s": timed.trace[-1]["time_s"], "val_check_s": scorer.check_seconds(),
            "settings": f"FitConfig defaults: LM, photo_sampling {photo_sampling}, lobe shape "
                        f"{prob.layout.lobe_shape} (auto), energy bound on, {iterations} iterations"}
