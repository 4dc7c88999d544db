"""Real photos to a model, end to end, scored on held-out views against two baselines (JSON + PNG).

    python benchmarks/real_photos.py --set middlebury_temple_sparse --out out/real_temple

Runs ``texstream run`` on the photos alone (no cameras, no masks given: ingest makes masks,
pycolmap registers, the mesh comes from dense stereo points (``--dense off``: the SfM points) and
the masks, xatlas makes the atlas, and the run fits the radiance model and the view-dependent radiance
model with every 8th photo held out and keeps the better held-out one), then scores on the held-out
views, foreground pixels only (the photo's mask and the model's coverage), these models with the same
mesh and atlas:

- the fitted model the run kept, and the one it did not;
- the per-texel average of the reprojected photos, what texture bakers produce (the same streamed
  samples, least squares: the fit of a per-texel constant is the samples' mean);
- one constant colour (the mean foreground colour of the fitted photos);
- when the run refined cameras and mesh, the reprojection average again on the refined ones, scored with the
  refined capture's held-out cameras (aligned to the texture of the fitted photos, as the run's own held-out
  figure): the refinement's effect on the geometry, free of any model.

Pooled PSNR (of the pixel-weighted mean squared error over the views) and the worst view are
reported for each, with the per-view figures, stage times and the machine.
Data from ``--data`` or ``TEXSTREAM_DATA`` (default ``../shared/data``).

``--registration OUT/posed`` of an earlier run reuses its cameras instead of registering again: COLMAP's
matching and mapping on several threads do not give the same cameras every run (issue 40: the temple's two
registrations of one commit and one ingest, 15:17 and 20:23 UTC, differ by 0.45% in focal length and up to 0.1
degree in rotation, 0.23 dB of the every-4th reprojection average), so a comparison of the stages after
registration holds them fixed.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import subprocess
import time
from pathlib import Path

import numpy as np


def reuse_registration(registered: Path):
    """A stand-in for the run's ``register`` that copies ``registered`` (an earlier run's OUT/posed) to the run's
    posed folder, with that run's summary (from its registration report)."""
    import shutil

    from texstream.core.outputs import StageResult

    def register(_capture_dir, posed_dir, *_args, **_kwargs):
        if not (registered / "capture.json").is_file():
            raise SystemExit(f"--registration {registered}: no capture.json (give an earlier run's OUT/posed)")
        shutil.rmtree(posed_dir, ignore_errors=True)
        shutil.copytree(registered, posed_dir)
        report = json.loads((registered / "registration_report.json").read_text())
        keys = ("registered", "unregistered", "mean_reprojection_error", "points3D", "principal_point", "distortion")
        return StageResult(output=Path(posed_dir), summary={"reused": str(registered),
                                                            **{k: report.get(k) for k in keys}})
    return register


def constant_colour_views(capture_dir: Path, model_dir: Path, holdout_every: int, device: str) -> list[dict]:
    """Per held-out view: the mean foreground colour of the fitted photos, scored like eval_stage."""
    from texstream.capture.capture_json import read_capture
    from texstream.capture.imageio import read_image, read_mask
    from texstream.fit.common.model_folder import image_metrics
    from texstream.fit.stages.stage import load_model, render_model, split_holdout

    capture = read_capture(capture_dir)
    fitted, held = split_holdout(capture.frames, holdout_every)
    acc, count = np.zeros(3), 0
    for f in fitted:
        img = read_image(capture.image_path(f), channels=3)
        m = read_mask(capture.mask_path(f), img.shape[:2]) if capture.mask_path(f) else np.ones(img.shape[:2], bool)
        acc += img[m].sum(axis=0)
        count += int(m.sum())
    colour = (acc / max(count, 1)).astype(np.float32)
    mesh, grid, lay, _ = load_model(model_dir)
    rows = []
    for f in held:
        photo = read_image(capture.image_path(f), channels=3)
        _, coverage = render_model(mesh, grid, lay, f, device)
        m = coverage.astype(bool)
        if capture.mask_path(f):
            m &= read_mask(capture.mask_path(f), m.shape)
        rows.append({"frame": f.file_path, **image_metrics(np.broadcast_to(colour, photo.shape), photo, m)})
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--set", default="middlebury_temple_sparse", help="folder of photos under the data folder")
    ap.add_argument("--data", default=os.environ.get("TEXSTREAM_DATA", "../shared/data"))
    ap.add_argument("--out", default="out/real_temple")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--iterations", type=int, default=20)
    ap.add_argument("--holdout-every", type=int, default=8)
    ap.add_argument("--dense", default="auto", choices=("auto", "on", "off"),
                    help="the mesh stage's dense stereo points (geometry/mvs.py; off: the sparse SfM points)")
    ap.add_argument("--hull-fill", default="on", choices=("on", "off"),
                    help="the mesh stage's visual-hull samples where the points leave the surface open "
                         "(geometry/hull_fill.py)")
    ap.add_argument("--refine", default="auto", choices=("auto", "off", "cameras", "mesh"),
                    help="the run's photometric refinement (geometry/refine.py): auto (the run's), off (the "
                         "registered cameras and the mesh stage's mesh as they are), cameras or mesh (that alone)")
    ap.add_argument("--min-texel-pixels", type=float, default=None,
                    help="atlas.min_texel_pixels (default: the run's; 0: the atlas at its resolution whatever the photos)")
    ap.add_argument("--registration", default=None,
                    help="an earlier run's OUT/posed: its cameras instead of registering again (registration on "
                         "several threads is not the same every run; the module doc says why this matters)")
    ap.add_argument("--results", default=None, help="also copy the JSON here (e.g. benchmarks/results/real_photos)")
    args = ap.parse_args()

    import warp as wp

    import texstream.pipelines.run as run_module
    from texstream.fit.common.model_folder import pooled_psnr
    from texstream.fit.stages.stage import eval_stage, fit_stage
    from texstream.pipelines.run import RunConfig, run_pipeline

    wp.config.quiet = True
    wp.config.log_level = wp.LOG_WARNING
    photos = Path(args.data) / args.set
    out = Path(args.out)
    cfg = RunConfig(device=args.device)  # auto: no light known -> radiance and view_radiance, the better kept
    cfg.mesh = dataclasses.replace(cfg.mesh, dense=args.dense, hull_fill=args.hull_fill == "on")
    if args.refine != "auto":
        cfg.refine = dataclasses.replace(cfg.refine, mode="off" if args.refine == "off" else "auto",
                                         cameras=args.refine != "mesh", mesh=args.refine != "cameras")
    if args.min_texel_pixels is not None:
        cfg.atlas = dataclasses.replace(cfg.atlas, min_texel_pixels=args.min_texel_pixels)
    cfg.fit = dataclasses.replace(cfg.fit, holdout_every=args.holdout_every,
                                  fit=dataclasses.replace(cfg.fit.fit, max_iterations=args.iterations))
    if args.registration:
        run_module.register = reuse_registration(Path(args.registration).resolve())
    t0 = time.perf_counter()
    run = run_pipeline(photos, out, cfg)
    total_s = time.perf_counter() - t0
    posed = out / "posed"
    kept = run.get("model", "radiance")
    models = {f"fitted {kept} (kept by the run)": out / "model"}
    for other in sorted(out.glob("model_*")):
        models[f"fitted {other.name[len('model_'):]} (not kept)"] = other
    # the baker's average: the same samples, least squares, a per-texel constant -> their mean
    avg_dir = out / "baseline_average"
    avg_cfg = dataclasses.replace(cfg.fit, device=args.device, renders=2,
                                  fit=dataclasses.replace(cfg.fit.fit, model="radiance", robust_loss="none",
                                                          max_iterations=args.iterations))
    fit_stage(posed, out / "atlas", avg_dir, avg_cfg, progress=False)
    models["reprojection average"] = avg_dir
    # the same on the refined cameras and mesh the fit used, scored with the refined capture's held-out cameras
    # (aligned to the fitted photos' texture, as the run scores): what the refine stage did to the geometry
    refined = next((Path(s["output"]) for s in run["stages"] if s["name"] == "refine" and s.get("output")), None)
    if refined is not None:
        fit_stage(refined, refined, out / "baseline_average_refined", avg_cfg, progress=False)
    result = {"set": args.set, "photos": str(photos), "holdout_every": args.holdout_every, "device": args.device,
              "machine": f"{platform.node()} ({os.cpu_count()} cores, {platform.processor() or platform.machine()})",
              "commit": subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                                       cwd=Path(__file__).parent).stdout.strip(),
              "command": "python benchmarks/real_photos.py " + " ".join(
                  f"--{k.replace('_', '-')} {v}" for k, v in vars(args).items() if v is not None and k != "data"),
              "run_total_s": total_s, "stages": [{k: s[k] for k in ("name", "status", "reason", "seconds")}
                                                 for s in run["stages"]],
              "mesh": next((s["summary"] for s in run["stages"] if s["name"] == "mesh"), {}),
              "registration": next((s["summary"] for s in run["stages"] if s["name"] == "register"), {}),
              "models": {}}
    for name, folder in models.items():
        ev = eval_stage(folder, posed, device=args.device, holdout_every=args.holdout_every,
                        out_json=out / f"eval_{folder.name}.json")
        per = json.loads(Path(ev.output).read_text())["per_frame"]
        result["models"][name] = {**pooled_psnr(per), "per_view": per}
    if refined is not None:
        ev = eval_stage(out / "baseline_average_refined", refined, device=args.device,
                        holdout_every=args.holdout_every, out_json=out / "eval_baseline_average_refined.json")
        per = json.loads(Path(ev.output).read_text())["per_frame"]
        result["models"]["reprojection average, refined geometry"] = {**pooled_psnr(per), "per_view": per}
    const = constant_colour_views(posed, out / "model", args.holdout_every, args.device)
    result["models"]["constant colour"] = {**pooled_psnr(const), "per_view": const}
    result["model_kept"] = kept
    result["model_reason"] = run.get("model_reason")
    fitted = result["models"][f"fitted {kept} (kept by the run)"]["pooled_psnr_db"]
    average = result["models"]["reprojection average"]["pooled_psnr_db"]
    result["fitted_minus_average_db"] = fitted - average
    text = json.dumps(result, indent=2)
    (out / "real_photos.json").write_text(text)
    if args.results:
        Path(args.results).mkdir(parents=True, exist_ok=True)
        (Path(args.results) / f"{args.set}.json").write_text(text)
    for name, m in result["models"].items():
        print(f"{name:>26}: pooled {m['pooled_psnr_db']:.2f} dB, worst view {m['worst_psnr_db']:.2f} dB "
              f"({m['views']} held-out views)")
    print(f"fitted - average: {result['fitted_minus_average_db']:+.2f} dB; run {total_s:.1f} s; {out / 'real_photos.json'}")


if __name__ == "__main__":
    main()
