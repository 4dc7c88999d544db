"""The ambient radiance term on a flash capture in a lit room, and on one without room light (JSON).

    python benchmarks/ambient_term.py --out DIR [--device cpu] [--ambient off,on,auto] [--scale 0.25]
        [--photos 96] [--image-size 96] [--holdout-every 8]

Scenes: ``sphere_room`` (the glossy sphere under a flash beside the camera, the room adding rho_d E_room with
E_room brighter from above: capture/synthetic/scenes/sphere_room.json) and ``sphere`` (the same sphere under the
flash alone). Per scene and ``--ambient`` setting, ``texstream fit`` (Lafortune, every ``--holdout-every``-th
photo held out): the held-out pooled and worst-view PSNR, the diffuse albedo rho_d's and the ambient's relative
error against the ground truth over the texels the fitted photos saw (median, 95th percentile, max per channel),
what auto chose and why, and the fit's seconds. Writes ``DIR/results.json`` (and the captures and model folders
under DIR).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path


def relative_error_stats(fit, truth) -> dict:
    import numpy as np

    err = np.abs(fit - truth) / np.maximum(np.abs(truth), 1e-12)
    return {"median": float(np.median(err)), "p95": float(np.percentile(err, 95)), "max": float(err.max())}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--ambient", default="off,on,auto", help="the fit's --ambient settings, comma-separated")
    ap.add_argument("--scenes", default="sphere_room,sphere")
    ap.add_argument("--scale", type=float, default=0.25)
    ap.add_argument("--photos", type=int, default=96)
    ap.add_argument("--image-size", type=int, default=96)
    ap.add_argument("--holdout-every", type=int, default=8)
    a = ap.parse_args()
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from gitinfo import commit

    import numpy as np

    from texstream.capture.imageio import read_image
    from texstream.capture.synthetic.synth import SynthConfig, load_ground_truth, synthesize
    from texstream.fit.optim.fitter import FitConfig
    from texstream.fit.stages.stage import FitStageConfig, fit_stage, load_model

    root = Path(a.out)
    rows = []
    for scene in a.scenes.split(","):
        cap = root / scene / "cap"
        if not (cap / "capture.json").is_file():
            synthesize(scene, cap, SynthConfig(scale=a.scale, photos=a.photos, image_size=a.image_size,
                                               progress=False, preview=False, device=a.device))
        _, truth, true_layout, bake, _ = load_ground_truth(cap)
        for mode in a.ambient.split(","):
            cfg = FitStageConfig(device=a.device, renders=0, holdout_every=a.holdout_every,
                                 fit=FitConfig(ambient=mode.strip()))
            model = root / scene / f"model_ambient_{mode.strip()}"
            t0 = time.perf_counter()
            fit_stage(cap, cap / "ground_truth", model, cfg, progress=False)
            seconds = time.perf_counter() - t0
            _, grid, lay, man = load_model(model)
            seen = bake.covered & (read_image(model / "seen.png", channels=3)[..., 0] > 0.5)  # texels photos saw
            row = {"scene": scene, "ambient": mode, "chosen": (man.get("ambient") or {}).get("chosen"),
                   "reason": (man.get("ambient") or {}).get("reason"), "heldout": man["heldout"],
                   "seconds": seconds, "texels": int(seen.sum()),
                   "rho_d_rel_error": relative_error_stats(grid[seen][:, 0:3], truth[seen][:, 0:3])}
            if true_layout.ambient and lay.ambient:
                o, to = lay.ambient_offset, true_layout.ambient_offset
                row["ambient_rel_error"] = relative_error_stats(grid[seen][:, o:o + 3], truth[seen][:, to:to + 3])
            if lay.ambient and not true_layout.ambient:
                row["ambient_fitted_max"] = float(grid[seen][:, lay.ambient_offset:].max())
            rows.append(row)
            print(json.dumps(row), flush=True)
    out = {"command": " ".join(sys.argv), "commit": commit(), "machine": platform.platform(),
           "cpu_count": os.cpu_count(), "device": a.device, "scale": a.scale, "photos": a.photos,
           "image_size": a.image_size, "holdout_every": a.holdout_every, "results": rows}
    (root / "results.json").write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
