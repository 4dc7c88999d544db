"""CPU-vs-CUDA agreement of the fit across two machines (the GPU machine's warp has no CPU compiler).

    python benchmarks/device_agreement.py --device cpu --out out/agree_cpu.npz        # dev box
    python benchmarks/device_agreement.py --device cuda:0 --out $OUT/agree_cuda.npz   # GPU machine
    python benchmarks/device_agreement.py --compare out/agree_cpu.npz agree_cuda.npz --out out/agree.json

``--photos-from out/agree_cpu.npz`` on the GPU machine fits the CPU's photos, so the comparison
shows the fit's own device differences (the renderers differ by ~5e-6 in fp32).

The cases are those of tests/test_fit_devices.py (which runs both devices in one process where
both exist): the flat sample, 24 photos, six iterations of LM (with smoothness) and CG.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

CASES = {"lm_fp64": ("lm", "fp64"), "cg_fp64": ("cg", "fp64"), "lm_fp32": ("lm", "fp32"), "cg_fp32": ("cg", "fp32")}


def run(device: str, out: Path, cases: list[str], photos_from: Path | None = None) -> None:
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    from texstream.capture.synthetic.synth import SynthConfig, render_scene
    from texstream.fit.optim.fitter import FitConfig, run_fit
    from texstream.fit.stream.penalties import PenaltyConfig
    from texstream.fit.stream.config import StreamConfig
    from texstream.fit.stages.stage import build_problem

    sc = render_scene("flat_sample", SynthConfig(scale=0.3, photos=24, image_size=48, progress=False, device=device))
    if photos_from is not None:
        # fit the other machine's photos: separates fitting differences from rendering ones
        sc.images = [np.asarray(p, np.float32) for p in np.load(photos_from)["photos"]]
    arrays = {}
    for name in cases:
        opt, acc = CASES[name]
        cfg = FitConfig(optimizer=opt, max_iterations=6, sync_every=100,
                        stream=StreamConfig(accumulate=acc, storage="fp64" if acc == "fp64" else "fp32"),
                        penalties=PenaltyConfig(smooth_weight=1e-3 if opt == "lm" else 0.0))
        prob = build_problem(sc.mesh, sc.bake, sc.frames, sc.images, sc.masks, cfg, device)
        res = run_fit(prob, cfg)
        arrays[f"{name}_params"] = res.params
        arrays[f"{name}_samples"] = res.samples
        arrays[f"{name}_objective"] = np.array([r["objective"] for r in res.trace])
    # the photos themselves, to separate rendering differences from fitting differences
    arrays["photos"] = np.stack(sc.images)
    out.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(out, **arrays)


def compare(a_path: Path, b_path: Path) -> dict:
    a, b = np.load(a_path), np.load(b_path)
    rep = {"photos_max_abs_diff": float(np.abs(a["photos"] - b["photos"]).max())}
    for name in CASES:
        if f"{name}_params" not in a or f"{name}_params" not in b:
            continue
        pa, pb = a[f"{name}_params"], b[f"{name}_params"]
        rel = np.abs(pa - pb) / np.maximum(np.abs(pa), 1e-3)
        off = rel.max(axis=1) > 1e-3
        rep[name] = {"samples_equal": bool(np.array_equal(a[f"{name}_samples"], b[f"{name}_samples"])),
                     "params_max_rel_diff": float(rel.max()),
                     "params_p99_rel_diff": float(np.percentile(rel, 99)),
                     # where single parameters differ, how well the texel is determined: a lobe fitted
                     # to a handful of samples has flat directions that last-ulp differences can roam
                     "texels_over_1e-3": int(off.sum()), "texels": int(len(pa)),
                     "max_samples_of_texels_over_1e-3": int(a[f"{name}_samples"][off].max()) if off.any() else None,
                     "objective_max_rel_diff": float(np.max(np.abs(a[f"{name}_objective"] - b[f"{name}_objective"])
                                                            / np.abs(a[f"{name}_objective"])))}
    return rep


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--out", default="out/agree_cpu.npz")
    ap.add_argument("--compare", nargs=2, default=None)
    ap.add_argument("--photos-from", default=None, help="fit the photos stored in this npz (another run's output)")
    ap.add_argument("--cases", default=",".join(CASES), help="comma-separated subset of " + ", ".join(CASES))
    a = ap.parse_args()
    if a.compare:
        rep = compare(Path(a.compare[0]), Path(a.compare[1]))
        from texstream.core.outputs import write_json_atomic

        write_json_atomic(a.out, rep, indent=1)
        print(json.dumps(rep, indent=1))
    else:
        run(a.device, Path(a.out), a.cases.split(","), Path(a.photos_from) if a.photos_from else None)


if __name__ == "__main__":
    main()
