"""Where a streaming pass's time goes: ms per pass by model, photo sampling, pass kind and photo groups (JSON).

    python benchmarks/pass_profile.py --scene ornament --scale 1.0 --device cuda:0 --out $OUT/profile   # GPU machine
    python benchmarks/pass_profile.py --scene ornament --scale 0.02 --device cpu --groups 1 --out out/profile

The bandwidth target counts the bytes a pass must move (fit_error_vs_time.py ``unique_bytes_per_pass``);
this script explains a pass that moves them slower than the memory allows by taking the work apart:

* model ``diffuse`` vs ``lafortune``: the same photos, projections, visibility tests and pixel reads,
  with and without the lobe (log, exp, the lobe's Jacobian columns);
* sampling ``bilinear`` vs ``filtered``: one model evaluation at the texel centre vs four, each at
  its tap's surface point (a ray-plane intersection, the extrapolated normal, the light, the frame);
* pass ``grad`` (objective + gradient + Gauss-Newton diagonal: SD / CG / L-BFGS), ``plain``
  (objective + gradient: line-search trials), ``dhd`` (+ Gauss-Newton d^T H d: the Hessian step)
  vs ``lm`` (objective + J^T r + J^T J: 33 running sums for one isotropic lobe);
* ``--groups``: photo groups per pass, i.e. threads per texel (StreamProblem.set_groups): more
  groups give the GPU more threads to hide memory latency with, and more partial sums to reduce;
* ``--max-registers``: the streaming kernels recompiled with a register cap per thread (more
  resident threads, more spills) and ``--block-dims``: threads per block (an SM holds whole
  blocks, so at ~170-210 registers per thread 128-thread blocks fit 12 warps where 256-thread
  blocks fit 8); on CUDA the JSON also lists each compiled streaming kernel's registers and local
  memory (``kernel_resources``; benchmarks/kernel_resources.py reports the same without a GPU).

Per configuration: ms per pass (median of ``--passes`` timed passes after a warm-up pass), accepted
samples per pass, ns per accepted sample, and the pass's unique bytes over its time as a fraction of
``--bandwidth-probe``'s measured copy bandwidth. Nothing here changes the fit; it only times passes.
"""

from __future__ import annotations

import argparse
import itertools
import json
import platform
import statistics
import time
from pathlib import Path


def time_passes(prob, kind: str, passes: int) -> tuple[float, float]:
    """(median seconds per pass, accepted samples per pass) of ``passes`` passes at the default parameters."""
    import numpy as np
    import warp as wp

    lay = prob.layout
    p = prob.new_storage(np.broadcast_to(lay.defaults(), (prob.n, lay.n_params)))
    f, g, st = prob.new_scalar(), prob.new_vec(), wp.zeros(prob.n, dtype=wp.vec4d, device=prob.device)
    extra, dhd = prob.new_vec(), prob.new_scalar()
    jtj = wp.zeros(prob.n, dtype=prob.mat, device=prob.device) if kind == "lm" else None

    def one_pass():
        if kind == "lm":
            prob.evaluate_lm(p, f, g, jtj, st)
        elif kind == "grad":
            prob.evaluate(p, f, g, st, diag=extra)
        elif kind == "dhd":
            prob.evaluate(p, f, g, st, direction=p, dhd=dhd)
        else:
            prob.evaluate(p, f, g, st)

    one_pass()  # compile / warm up
    wp.synchronize_device(prob.device)
    times = []
    for _ in range(passes):
        t0 = time.perf_counter()
        one_pass()
        wp.synchronize_device(prob.device)
        times.append(time.perf_counter() - t0)
    samples = float(st.numpy()[:, 0].sum())  # trace stats: 1/3 per channel, so samples per texel
    return statistics.median(times), samples


def kernel_resources() -> list[dict]:
    """Registers and local (spill) memory per thread of the compiled streaming kernels, read from
    Warp's CUDA kernel cache with CuPy (present on the GPU machine); [] where either is missing.
    Registers bound how many threads an SM keeps resident to hide memory latency with."""
    import re

    import warp as wp

    try:
        import cupy
    except ImportError:
        return []
    found = []
    for path in sorted(Path(wp.config.kernel_cache_dir).rglob("*")):
        if ("stream" not in path.parent.name and "accumulate" not in path.parent.name) or path.suffix not in (".ptx", ".cubin"):
            continue
        text = path.read_bytes()
        names = sorted(set(re.findall(rb"(accumulate\w*?_cuda_kernel_forward)", text)))
        try:
            mod = cupy.RawModule(path=str(path))
            for name in names:
                fn = mod.get_function(name.decode())
                found.append({"file": path.name, "kernel": name.decode(), "registers": fn.num_regs,
                              "local_bytes": fn.local_size_bytes})
        except Exception as exc:  # best effort: a report, not a requirement
            found.append({"file": path.name, "error": str(exc)[:200]})
    return found


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scene", default="ornament")
    ap.add_argument("--scale", type=float, default=1.0)
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--models", default="lafortune,diffuse")
    ap.add_argument("--samplings", default="filtered,bilinear")
    ap.add_argument("--lookups", default="texel", help="StreamConfig.model_lookup values to try (texel, bilinear)")
    ap.add_argument("--taps", default="plane", help="StreamConfig.tap_geometry values to try (plane, mesh)")
    ap.add_argument("--kinds", default="grad,lm")
    ap.add_argument("--groups", default="0,8,16,32", help="photo groups to try (0 = the automatic choice)")
    ap.add_argument("--max-registers", default="-1",
                    help="register caps per thread to try, e.g. 0,168,128 (0 = none, -1 = StreamConfig's; CUDA only)")
    ap.add_argument("--block-dims", default="0", help="CUDA threads per block to try, e.g. 256,128,64 (0 = StreamConfig's)")
    ap.add_argument("--passes", type=int, default=5)
    ap.add_argument("--bandwidth-probe", action="store_true")
    ap.add_argument("--out", default="out/pass_profile")
    a = ap.parse_args()
    import numpy as np
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    from fit_error_vs_time import measured_bandwidth, unique_bytes_per_pass

    from texstream.capture.synthetic.synth import SynthConfig, render_scene
    from texstream.fit.optim.fitter import FitConfig
    from texstream.fit.stream.config import StreamConfig
    from texstream.fit.stages.stage import build_problem
    from texstream.core.outputs import write_json_atomic

    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    sc = render_scene(a.scene, SynthConfig(scale=a.scale, device=a.device, progress=False))
    rep = {"scene": a.scene, "scale": a.scale, "device": a.device, "machine": platform.node(),
           "photos": len(sc.images), "image_size": list(sc.images[0].shape[:2]), "passes": a.passes, "runs": []}
    if a.device.startswith("cuda"):
        rep["gpu"] = wp.get_device(a.device).name
    if a.bandwidth_probe:
        rep["measured_bandwidth_GBps"] = measured_bandwidth(a.device) / 1e9
    for model in a.models.split(","):
        for sampling, lookup, taps in itertools.product(a.samplings.split(","), a.lookups.split(","), a.taps.split(",")):
            if (lookup != "texel" or taps != "plane") and sampling != "filtered":
                continue  # the lookup and traced taps need filtered sampling
            cfg = FitConfig(model=model, stream=StreamConfig(photo_sampling=sampling, model_lookup=lookup, tap_geometry=taps))
            prob = build_problem(sc.mesh, sc.bake, sc.frames, sc.images, sc.masks, cfg, a.device)
            prob.refresh_lookup(prob.new_storage(np.tile(prob.layout.defaults(), (prob.n, 1))))
            rep["texels"] = prob.n
            defaults = prob.max_registers, prob.block_dim
            for max_regs, block_dim in itertools.product([int(x) for x in a.max_registers.split(",")],
                                                          [int(x) for x in a.block_dims.split(",")]):
                prob.max_registers = max_regs if max_regs >= 0 else defaults[0]
                prob.block_dim = block_dim or defaults[1]
                max_regs, block_dim = prob.max_registers, prob.block_dim
                for groups in [int(x) for x in a.groups.split(",")]:
                    prob.set_groups(groups)
                    for kind in a.kinds.split(","):
                        t0 = time.perf_counter()
                        sec, samples = time_passes(prob, kind, a.passes)
                        ub = unique_bytes_per_pass(prob, "lm" if kind == "lm" else "sd", diag=kind == "grad")
                        run = {"model": model, "sampling": sampling, "lookup": lookup, "taps": taps, "kind": kind, "groups": prob.groups,
                               "max_registers": max_regs, "block_dim": block_dim, "ms_per_pass": 1000 * sec,
                               "samples_per_pass": samples, "ns_per_sample": 1e9 * sec / max(samples, 1.0),
                               "unique_bytes_per_pass": ub, "unique_GBps": ub / sec / 1e9,
                               "wall_s_incl_compile": time.perf_counter() - t0}
                        if "measured_bandwidth_GBps" in rep:
                            run["bandwidth_fraction"] = run["unique_GBps"] / rep["measured_bandwidth_GBps"]
                        rep["runs"].append(run)
                        print(model, sampling, lookup, taps, kind, f"groups {prob.groups}", f"maxreg {max_regs}", f"block {block_dim}",
                              f"{run['ms_per_pass']:.2f} ms/pass", f"{run['ns_per_sample']:.3f} ns/sample",
                              f"{run.get('bandwidth_fraction', 0):.3f} of bw", flush=True)
                        write_json_atomic(out / "pass_profile.json", rep, indent=1)
            del prob
    if a.device.startswith("cuda"):
        rep["kernel_resources"] = kernel_resources()
        write_json_atomic(out / "pass_profile.json", rep, indent=1)
    print(json.dumps({k: v for k, v in rep.items() if k != "runs"}, indent=1))


if __name__ == "__main__":
    main()
