"""The one-material sphere of tests/test_fit_materials.py fitted with and without ``--traced-materials`` (JSON lines).

    python benchmarks/traced_materials_sphere.py --out DIR [--device cpu] [--traced off,on]

The built-in sphere with one material (rho_s 0.6, n 60), 160 photos of 48x48 on its own atlas, every 8th held
out, materials on with one material: per setting, the held-out pooled and worst-view PSNR, the borrowing and
constrained texels, and the share of texels that never saw their highlight whose rho_s and n end within 10% of
the truth (the issue's ground-truth bound; fit/accuracy.py ``highlight_counts``).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--traced", default="off,on", help="the --traced-materials settings to fit, comma-separated")
    a = ap.parse_args()
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    import platform

    from gitinfo import commit
    import numpy as np

    from test_fit_materials import one_material_sphere
    from texstream.capture.capture_json import read_capture
    from texstream.capture.synthetic.synth import SynthConfig, load_ground_truth, synthesize
    from texstream.fit.diagnostics.accuracy import highlight_counts, relative_errors
    from texstream.fit.optim.fitter import FitConfig
    from texstream.fit.models.materials import MaterialConfig
    from texstream.fit.stages.stage import FitStageConfig, fit_stage, load_model, split_holdout

    root = Path(a.out)
    if not (root / "cap" / "capture.json").is_file():
        synthesize(one_material_sphere(), root / "cap", SynthConfig(scale=0.05, photos=160, image_size=48,
                                                                    progress=False, preview=False, device=a.device))
    _, truth, _, bake, _ = load_ground_truth(root / "cap")
    fitted, _ = split_holdout(read_capture(root / "cap").frames, 8)
    settings = [t.strip() for t in a.traced.split(",")]
    if not settings or any(t not in ("off", "on") for t in settings):
        ap.error(f"--traced {a.traced}: expected off, on or off,on")
    for traced in [t == "on" for t in settings]:
        cfg = FitStageConfig(device=a.device, renders=0, holdout_every=8, traced_materials=traced,
                             materials=MaterialConfig(mode="on", max_materials=1, validation_every=6),
                             fit=FitConfig(max_iterations=40))
        model = root / f"model_traced_{int(traced)}"
        fit_stage(root / "cap", root / "cap" / "ground_truth", model, cfg, progress=False)
        _, grid, lay, man = load_model(model)
        cov = bake.covered.reshape(-1)
        t = truth.reshape(-1, truth.shape[-1])[cov].astype(np.float64)
        p = grid.reshape(-1, grid.shape[-1])[cov].astype(np.float64)
        o = lay.lobe_offset(0)
        never = highlight_counts(fitted, bake.position.reshape(-1, 3)[cov], bake.normal.reshape(-1, 3)[cov], t,
                                 o) == 0
        ok = (relative_errors(p[:, o:o + 3], t[:, o:o + 3]).max(axis=1) <= 0.1) & (
            relative_errors(p[:, o + 5], t[:, o + 5]) <= 0.1)
        mat = man["materials"]
        row = {"traced_materials": traced, "heldout_pooled_db": man["heldout"]["pooled_psnr_db"],
               "heldout_worst_db": man["heldout"]["worst_psnr_db"], "borrowed_texels": mat["borrowed_texels"],
               "constrained_texels": mat["uncertainty"]["constrained_texels"],
               "never_saw_highlight": int(never.sum()), "within_10pct_share": float(ok[never].mean()),
               "device": a.device, "machine": f"{platform.node()} ({os.cpu_count()} cores)", "commit": commit()}
        print(json.dumps(row), flush=True)
        with open(root / "traced_materials_sphere.jsonl", "a") as fh:
            fh.write(json.dumps(row) + "\n")


if __name__ == "__main__":
    main()
