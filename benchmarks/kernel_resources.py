"""Registers, stack and spills per GPU thread of the streaming kernels, without a GPU.

Runs one objective / gradient / d^T H d / LM pass of each requested model on a small synthetic
scene on the CPU (which creates the kernels' overloads), compiles the modules holding the
accumulation kernels for a CUDA architecture with Warp's ahead-of-time compiler (its bundled
NVRTC, no driver needed) and assembles the PTX with ``ptxas -v`` (CUDA's assembler, on the dev
box's PATH), whose report is what the GPU would load. Registers and local memory per thread set
how many threads an SM keeps resident, and the stack holds what a thread indexes at run time
or spills (Nsight Compute's "local memory"); benchmarks/pass_profile.py times the same kernels.

    python benchmarks/kernel_resources.py --arch 90 --max-registers 0,168,128

writes ``kernel_resources.json`` under ``--out``. Warp's PTX may name a newer ``.version`` than
the local ptxas knows; it is lowered to the version ptxas names (the kernels use nothing newer).
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))


def assemble(ptx: Path, arch: int) -> list[dict]:
    """``ptxas -v`` on one PTX file: per entry function, registers, stack and spill bytes."""
    text = ptx.read_bytes().replace(b"\0", b"")
    for _ in range(2):
        tmp = ptx.with_suffix(".fixed.ptx")
        tmp.write_bytes(text)
        r = subprocess.run(["ptxas", f"-arch=sm_{arch}", "-v", str(tmp), "-o", "/dev/null"],
                           capture_output=True, text=True)
        known = re.search(r"Unsupported \.version [\d.]+; current version is '([\d.]+)'", r.stderr)
        if r.returncode == 0 or not known:
            break
        text = re.sub(rb"^\.version [\d.]+", b".version " + known.group(1).encode(), text, count=1, flags=re.M)
    if r.returncode != 0:
        raise SystemExit(f"ptxas failed on {ptx}: {r.stderr.strip().splitlines()[-1]}")
    out, cur = [], None
    for line in r.stderr.splitlines():
        m = re.search(r"Compiling entry function '(\w+)'", line)
        if m:
            cur = {"function": m.group(1)}
            out.append(cur)
        m = re.search(r"(\d+) bytes stack frame, (\d+) bytes spill stores, (\d+) bytes spill loads", line)
        if m and cur is not None:
            cur.update(stack_bytes=int(m.group(1)), spill_store_bytes=int(m.group(2)), spill_load_bytes=int(m.group(3)))
        m = re.search(r"Used (\d+) registers", line)
        if m and cur is not None:
            cur["registers"] = int(m.group(1))
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--arch", type=int, default=90, help="CUDA compute capability x10 (90: H100 / H200)")
    ap.add_argument("--models", default="lafortune,diffuse,lafortune2aniso",
                    help="diffuse, lafortune (one isotropic lobe) or lafortune<K>[aniso], e.g. lafortune2aniso")
    ap.add_argument("--max-registers", default="0", help="register caps per thread to compile, e.g. 0,168,128")
    ap.add_argument("--accumulate", default="fp32")
    ap.add_argument("--out", default="out/kernel_resources")
    a = ap.parse_args()
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    from pass_profile import time_passes

    from texstream.capture.synthetic.synth import SynthConfig, render_scene
    from texstream.fit.optim.fitter import FitConfig
    from texstream.fit.stream.config import StreamConfig
    from texstream.fit.stages.stage import build_problem
    from texstream.core.outputs import write_json_atomic

    sc = render_scene("ornament", SynthConfig(scale=0.02, device="cpu", progress=False))
    for model in a.models.split(","):
        spec = re.fullmatch(r"(diffuse|lafortune)(\d?)(aniso)?", model)
        if spec is None:
            raise SystemExit(f"--models: {model!r} unknown; use diffuse, lafortune or e.g. lafortune2aniso")
        cfg = FitConfig(model=spec.group(1), lobes=int(spec.group(2) or 1), anisotropic=bool(spec.group(3)),
                        stream=StreamConfig(accumulate=a.accumulate))
        prob = build_problem(sc.mesh, sc.bake, sc.frames, sc.images, sc.masks, cfg, "cpu")
        for cap in [int(x) for x in a.max_registers.split(",")]:
            if hasattr(prob, "max_registers"):
                prob.max_registers = cap
            elif cap:
                continue  # a commit before the per-problem cap: its kernels as shipped only
            for kind in ("grad", "lm"):
                time_passes(prob, kind, 1)
            # the gradient pass with the preconditioner's diagonal and the d^T H d passes
            f, g = prob.new_scalar(), prob.new_vec()
            st = wp.zeros(prob.n, dtype=wp.vec4d, device="cpu")
            p = prob.new_storage()
            prob.evaluate(p, f, g, st)
            prob.evaluate(p, f, g, st, diag=prob.new_vec())
            for full in (False, True):
                prob.evaluate(p, f, g, st, direction=p, dhd=prob.new_scalar(), full_hessian=full)
    from warp._src.context import user_modules

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name, module in sorted(user_modules.items()):
            if "accumulate" not in name and not name.endswith("kernels.stream"):
                continue
            for ptx in wp.compile_aot_module(module, arch=a.arch, module_dir=tmp, use_ptx=True):
                for entry in assemble(Path(ptx), a.arch):
                    if "accumulate" in entry["function"]:
                        entry["kernel"] = re.sub(r"_[0-9a-f]{8}_cuda_kernel_forward$", "", entry["function"])
                        rows.append(entry)
                        print(f"{entry['kernel']:48s} {entry['registers']:4d} registers "
                              f"{entry['stack_bytes']:5d} B stack {entry['spill_store_bytes']:5d} B spilled", flush=True)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out / "kernel_resources.json", {"arch": a.arch, "accumulate": a.accumulate, "kernels": rows}, indent=1)


if __name__ == "__main__":
    main()
