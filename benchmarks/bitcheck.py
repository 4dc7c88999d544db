"""Fitted parameters of the same in-memory fits under two versions of texstream, compared bit for bit.

Issue 37 moved the fit into layers and plugins without changing its arithmetic; this script is how that is
checked on a device: run it once with each version's source tree first on PYTHONPATH (``--tag before`` /
``--tag after``, each writes ``OUT/params_<tag>.npz``), then ``--compare`` the two files. Scenes render in memory
(no OpenImageIO), so it runs on the GPU machine, which has only numpy and warp. It imports through the module
paths of either version (the flat fit/ of before, the layered fit/ and render/ of after).

    python benchmarks/bitcheck.py --device cuda:0 --tag after --out DIR
    python benchmarks/bitcheck.py --compare DIR/params_before.npz DIR/params_after.npz
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

# (name, FitConfig fields, materials choice): the per-texel kinds, LM and CG, the shared materials' evidence path
CASES = [
    ("lafortune_lm", {"model": "lafortune", "optimizer": "lm", "max_iterations": 12}),
    ("lafortune_cg", {"model": "lafortune", "optimizer": "cg", "max_iterations": 12}),
    ("diffuse_lm", {"model": "diffuse", "optimizer": "lm", "max_iterations": 8}),
    ("radiance_lm", {"model": "radiance", "optimizer": "lm", "max_iterations": 8}),
    ("view_radiance_lm", {"model": "view_radiance", "optimizer": "lm", "max_iterations": 8}),
]


def _imports():
    """(render_scene, SynthConfig, FitConfig, fit_synthetic) from whichever layout is on the path."""
    try:
        from texstream.capture.synthetic.synth import SynthConfig, render_scene
        from texstream.fit.common.setup import fit_synthetic
        from texstream.fit.optim.fitter import FitConfig
    except ImportError:  # before issue 37
        from texstream.capture.synth import SynthConfig, render_scene
        from texstream.fit.fitter import FitConfig
        from texstream.fit.stage import fit_synthetic
    return render_scene, SynthConfig, FitConfig, fit_synthetic


def run(device: str, scene: str, scale: float, out: Path, tag: str) -> dict:
    render_scene, SynthConfig, FitConfig, fit_synthetic = _imports()
    train = render_scene(scene, SynthConfig(scale=scale, device=device, progress=False))
    held = render_scene(scene, SynthConfig(scale=scale, device=device, progress=False, photos=8, azimuth_offset=3.0))
    arrays, summary = {}, {}
    for name, fields in CASES:
        cfg = FitConfig(**fields)
        fit = fit_synthetic(train, held, cfg, device)
        arrays[name] = np.asarray(fit.result.params)
        arrays[f"{name}_grid"] = np.asarray(fit.grid)
        summary[name] = {"heldout_pooled_db": fit.heldout_pooled_db, "objective": fit.result.trace[-1]["objective"]}
        print(f"{tag} {name}: held out {fit.heldout_pooled_db:.4f} dB", flush=True)
    out.mkdir(parents=True, exist_ok=True)
    np.savez(out / f"params_{tag}.npz", **arrays)
    (out / f"summary_{tag}.json").write_text(json.dumps(summary, indent=1))
    return summary


def compare(a: Path, b: Path) -> bool:
    za, zb = np.load(a), np.load(b)
    same = True
    for k in sorted(za.files):
        eq = np.array_equal(za[k], zb[k])
        diff = float(np.max(np.abs(za[k].astype(np.float64) - zb[k].astype(np.float64)))) if za[k].shape == zb[k].shape else None
        print(f"{k}: {'identical' if eq else f'DIFFERENT (max |diff| {diff})'}")
        same &= eq
    return same


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--scene", default="ornament")
    ap.add_argument("--scale", type=float, default=0.05)
    ap.add_argument("--tag", default="after")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/bitcheck"))
    ap.add_argument("--compare", nargs=2, type=Path, metavar=("BEFORE", "AFTER"))
    a = ap.parse_args(argv)
    if a.compare:
        return 0 if compare(*a.compare) else 1
    run(a.device, a.scene, a.scale, a.out, a.tag)
    return 0


if __name__ == "__main__":
    sys.exit(main())
