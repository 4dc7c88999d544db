"""Ground-truth lobe accuracy of a model folder fitted on a synthetic capture's own atlas (issue 17).

    texstream fit CAP --mesh CAP/ground_truth -o MODEL --holdout-every 8
    python benchmarks/materials_accuracy.py MODEL CAP --holdout-every 8 [--out result.json]

Splits the texels of the lobe materials (true rho_s > 0) by how many *fitted* photos show their true
highlight at >= 10% of its peak (fit/accuracy.py ``highlight_counts``; held-out photos excluded):
"never" (0 photos: no photo caught the highlight, the texels the materials are for) and "highlight"
(5+ photos: the per-texel bounds' texel set, diffuse 1%, rho_s 3%, n 5%). Reports, per set, the share of
texels with every rho_s channel and n within 10% (and within the per-texel bounds), the median
relative errors, and the model's materials choice from model.json. Needs the model's atlas to be
the capture's (``--mesh CAP/ground_truth``): texel i of both maps is the same surface point.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("model")
    ap.add_argument("capture")
    ap.add_argument("--holdout-every", type=int, default=8)
    ap.add_argument("--out", default=None)
    a = ap.parse_args()
    from texstream.capture.capture_json import read_capture
    from texstream.capture.synthetic.synth import load_ground_truth
    from texstream.fit.diagnostics.accuracy import highlight_counts, relative_errors
    from texstream.fit.stages.stage import load_model, split_holdout

    _, truth, lay_t, bake, _ = load_ground_truth(a.capture)
    _, grid, lay, man = load_model(a.model)
    if grid.shape[:2] != truth.shape[:2]:
        raise SystemExit(f"model atlas {grid.shape[:2]} is not the capture's {truth.shape[:2]}: fit with "
                         "--mesh CAPTURE/ground_truth")
    cov = bake.covered.reshape(-1)
    t = truth.reshape(-1, truth.shape[-1])[cov].astype(np.float64)
    p = grid.reshape(-1, grid.shape[-1])[cov].astype(np.float64)
    fitted, _ = split_holdout(read_capture(a.capture).frames, a.holdout_every)
    o = lay_t.lobe_offset(0)
    counts = highlight_counts(fitted, bake.position.reshape(-1, 3)[cov], bake.normal.reshape(-1, 3)[cov], t, o)
    lobe = t[:, o:o + 3].max(axis=1) > 0
    rho_err = relative_errors(p[:, o:o + 3], t[:, o:o + 3]).max(axis=1)
    n_err = relative_errors(p[:, o + 5], t[:, o + 5])
    d_err = relative_errors(p[:, 0:3], t[:, 0:3]).max(axis=1)
    out = {"model": str(a.model), "capture": str(a.capture), "fitted_photos": len(fitted),
           "materials": {k: v for k, v in (man.get("materials") or {}).items() if k != "materials"},
           "heldout": man.get("heldout")}
    for name, sel in (("never", lobe & (counts == 0)), ("highlight", lobe & (counts >= 5)),
                      ("between", lobe & (counts > 0) & (counts < 5))):
        k = int(sel.sum())
        row = {"texels": k}
        if k:
            row.update({"within_10pct": float(np.mean((rho_err[sel] <= 0.1) & (n_err[sel] <= 0.1))),
                        "rho_s_within_10pct": float(np.mean(rho_err[sel] <= 0.1)),
                        "n_within_10pct": float(np.mean(n_err[sel] <= 0.1)),
                        "per_texel_bounds": float(np.mean((d_err[sel] <= 0.01) & (rho_err[sel] <= 0.03)
                                                          & (n_err[sel] <= 0.05))),
                        "rho_s_median_err": float(np.median(rho_err[sel])), "n_median_err": float(np.median(n_err[sel])),
                        "diffuse_median_err": float(np.median(d_err[sel]))})
        out[name] = row
    text = json.dumps(out, indent=1)
    print(text)
    if a.out:
        Path(a.out).parent.mkdir(parents=True, exist_ok=True)
        Path(a.out).write_text(text + "\n")


if __name__ == "__main__":
    main()
