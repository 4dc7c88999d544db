"""How much of an LFM model survives the unlit export (glTF / OBJ): held-out PSNR (JSON).

    python benchmarks/lfm_unlit.py MODEL CAPTURE --holdout-every 8 --out out/lfm_unlit.json

MODEL is an LFM model folder (``texstream fit --model lfm``) and CAPTURE the capture it was fitted
to. On the held-out views (every k-th photo, foreground: the render's coverage and the photo's mask)
it scores, pooled over the views (PSNR of the pixel-weighted mean squared error) and the worst view:

- the full LFM model (fit/lfm_stage.py LFMRenderer),
- each unlit approximation the export can write (fit/export.py ``lfm_view_mean``: ``cosine``, the
  view-independent term plus each term's cosine-weighted mean over view directions; ``none``, the
  view-independent term alone), rendered by the radiance renderer from the exported atlas,

each against the photos, and the unlit approximations against the full model's render (same pixels).
"""

from __future__ import annotations

import argparse
import json
import platform
import subprocess
import time
from pathlib import Path


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model")
    ap.add_argument("capture")
    ap.add_argument("--holdout-every", type=int, default=8)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--out", default=None, help="JSON to write (default: print only)")
    a = ap.parse_args(argv)

    from texstream.capture.capture_json import read_capture
    from texstream.capture.imageio import read_image, read_mask
    from texstream.fit.models.lfm.export import LFM_VIEW_MEANS, lfm_unlit_renderer
    from texstream.fit.models.lfm.model_folder import load_lfm_model
    from texstream.fit.common.model_folder import image_metrics, pooled_psnr
    from texstream.fit.stages.stage import split_holdout

    t0 = time.perf_counter()
    model = load_lfm_model(a.model)
    capture = read_capture(a.capture)
    held = split_holdout(capture.frames, a.holdout_every)[1]
    renders = {"lfm": model.renderer(a.device).render_frame}
    renders.update({f"unlit_{m}": lfm_unlit_renderer(model, m, a.device) for m in LFM_VIEW_MEANS})
    rows: dict[str, list] = {k: [] for k in renders}
    rows.update({f"{k}_vs_lfm": [] for k in renders if k != "lfm"})
    for f in held:
        photo = read_image(capture.image_path(f), channels=3)
        full, mask = renders["lfm"](f)
        mp = capture.mask_path(f)
        m = mask.astype(bool)
        if mp is not None and mp.exists():
            m &= read_mask(mp, mask.shape)
        rows["lfm"].append({"frame": f.file_path, **image_metrics(full, photo, m)})
        for k, render in renders.items():
            if k == "lfm":
                continue
            img, _ = render(f)
            rows[k].append({"frame": f.file_path, **image_metrics(img, photo, m)})
            rows[f"{k}_vs_lfm"].append({"frame": f.file_path, **image_metrics(img, full, m)})
    out = {"model": str(Path(a.model).resolve()), "capture": str(Path(a.capture).resolve()),
           "holdout_every": a.holdout_every, "views": len(held),
           "lfm": dict(model.manifest["layout"]),
           "scores": {k: pooled_psnr(v) for k, v in rows.items()}, "per_view": rows,
           "seconds": time.perf_counter() - t0, "machine": platform.processor() or platform.machine(),
           "commit": subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                                    cwd=Path(__file__).parent).stdout.strip()}
    for k, v in out["scores"].items():
        print(f"{k:>22}: pooled {v['pooled_psnr_db']:.2f} dB, worst {v['worst_psnr_db']:.2f} dB")
    if a.out:
        Path(a.out).parent.mkdir(parents=True, exist_ok=True)
        Path(a.out).write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
