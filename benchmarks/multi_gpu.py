"""Time to a converged model on one device against several (tiles of texels, fit/tiles.py, or the photos split
over the devices, fit/photo_split.py); writes JSON.

    python benchmarks/multi_gpu.py --devices cuda:0,cuda:1 --scene ornament --scale 1.0 --texel-factor 4 --out DIR
    python benchmarks/multi_gpu.py --devices cpu,cpu --scene ornament --scale 0.02 --out DIR   # the path, on a CPU

The scene is rendered in memory (no OpenImageIO) on the first device; the fit's atlas is baked at
``--texel-factor`` times the scene's texel count (the side x its square root). Runs, each after an
untimed warm-up that compiles every kernel on every device:

- ``one_device``: the untiled fit on the first device (set-up, then LM);
- ``tiled_one_device``: the same problem in as many tiles as devices, all on the first device (what
  tiling costs by itself: the visibility pass, the tiles' set-up, lockstep);
- ``multi_device``: those tiles on the listed devices, one thread each (photos and maps copied to each
  device at the tiles' set-up);
- ``photos_one_device``: the photos split in as many runs as devices, all on the first device (the split's
  path and summation order on one device: the bit-for-bit reference of the next run);
- ``photos_multi_device``: the photos split over the listed devices (each device crops, uploads and maps
  its run of photos at once; the first adds the others' sums each pass).

``--splits`` picks the kinds (tiles, photos).

Each run reports the set-up (photos, maps, texels: ``setup_s``), the tiles' set-up (visibility and
the tile problems, ``tile_setup_s``), the fit loop, and the time to a converged model: set-up plus the
fit's time to within 0.1 dB of its best PSNR, as benchmarks/setup_time.py (an iteration's time in a
tiled fit: when its last tile recorded it). ``same_params_to_the_bit``: the tiled fits' parameters
against the one-device fit's; the split photos' against ``photos_one_device`` (and, to rounding, against
the one-device fit: their sums associate the photos' runs differently). The tiles take the untiled
problem's photo groups, so a tile that streams every photo (fit/tiles.py ``ALL_PHOTOS_FRACTION``) sums
each texel in the same order: bit-equal; a tile
that streams a subset splits its groups elsewhere (except with ``--groups 1``) and agrees to float
rounding carried through the iterations (max differences reported).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import platform
import time
from pathlib import Path

from gitinfo import commit


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--devices", default="cuda:0,cuda:1", help="comma-separated devices of the tiled fit")
    ap.add_argument("--scene", default="ornament")
    ap.add_argument("--scale", type=float, default=1.0, help="SynthConfig.scale (photos and texels x scale)")
    ap.add_argument("--texel-factor", type=float, default=4.0, help="the fit's texel count over the scene's")
    ap.add_argument("--iterations", type=int, default=10, help="LM iterations (fixed: rel_tol 0)")
    ap.add_argument("--image-precision", default="fp16", choices=("fp16", "fp32"))
    ap.add_argument("--shadow-map-size", type=int, default=512)
    ap.add_argument("--groups", type=int, default=0, help="StreamConfig.groups (1: summation order of the "
                                                          "one-device fit, bit-equal parameters)")
    ap.add_argument("--smooth-weight", type=float, default=0.0, help="LM smoothness (tiles exchange halos after "
                                                                     "every iteration)")
    ap.add_argument("--repeats", type=int, default=2, help="timed repeats of each run (the fastest is reported)")
    ap.add_argument("--splits", default="tiles,photos", help="how the devices share the fit: tiles, photos or both")
    ap.add_argument("--decode-threads", type=int, default=0, help="StreamConfig.decode_threads (0: the default)")
    ap.add_argument("--upload-slots", type=int, default=0, help="fit.stream.photo_set.UPLOAD_SLOTS (0: the default)")
    ap.add_argument("--upload-chunk-mib", type=float, default=0,
                    help="fit.stream.photo_set.ARRAY_UPLOAD_CHUNK_BYTES in MiB (0: the default)")
    ap.add_argument("--out", required=True)
    a = ap.parse_args()

    import numpy as np
    import warp as wp

    wp.config.quiet = True
    wp.init()
    from texstream.capture.synthetic.synth import SynthConfig, render_scene
    from texstream.fit.optim.fitter import FitConfig, run_fit
    from texstream.fit.stream.penalties import PenaltyConfig
    from texstream.fit.stream.config import StreamConfig
    from texstream.fit.stages.stage import build_problem
    from texstream.fit.multi.tiles import parse_devices, run_tiled_fit
    from texstream.geometry.bake import bake_texels

    import texstream.fit.stream.photo_set as fit_problem

    if a.upload_slots:
        fit_problem.UPLOAD_SLOTS = a.upload_slots
    if a.upload_chunk_mib:
        fit_problem.ARRAY_UPLOAD_CHUNK_BYTES = int(a.upload_chunk_mib * (1 << 20))
    pipeline = {"upload_slots": fit_problem.UPLOAD_SLOTS, "array_upload_chunk_bytes": fit_problem.ARRAY_UPLOAD_CHUNK_BYTES,
                "decode_threads": a.decode_threads}
    devices = parse_devices(a.devices, "cpu")
    dev0 = devices[0]
    t0 = time.perf_counter()
    sc = render_scene(a.scene, SynthConfig(scale=a.scale, device=dev0, progress=False))
    mesh, frames, images, masks = sc.mesh, sc.frames, sc.images, sc.masks
    side = float(np.sqrt(a.texel_factor))
    bake = bake_texels(mesh, int(round(sc.bake.width * side)), int(round(sc.bake.height * side)), device=dev0)
    render_s = time.perf_counter() - t0

    def config(**stream) -> FitConfig:
        return FitConfig(optimizer="lm", max_iterations=a.iterations, rel_tol=0.0, sync_every=5,
                         penalties=PenaltyConfig(smooth_weight=a.smooth_weight),
                         stream=StreamConfig(image_precision=a.image_precision, shadow_map_size=a.shadow_map_size,
                                             photo_residency="device", groups=a.groups,
                                             decode_threads=a.decode_threads, **stream))

    splits = [k.strip() for k in a.splits.split(",") if k.strip()]
    runs = {"one_device": config()}
    if "tiles" in splits:
        runs.update({"tiled_one_device": config(tiles=len(devices)),
                     "multi_device": config(tiles=len(devices), devices=",".join(devices))})
    if "photos" in splits:
        runs.update({"photos_one_device": config(device_split="photos", devices=",".join([dev0] * len(devices))),
                     "photos_multi_device": config(device_split="photos", devices=",".join(devices))})
    # warm-up: every kernel compiled and loaded on every device (a photo per device, the same configs)
    for cfg in runs.values():
        wcfg = dataclasses.replace(cfg, max_iterations=2)
        k = len(devices)
        wprob = build_problem(mesh, bake, frames[:k], images[:k], masks[:k], wcfg, dev0)
        run_tiled_fit(wprob, wcfg) if cfg.stream.tiles else run_fit(wprob, wcfg)
    for d in set(devices):
        wp.synchronize_device(d)

    def timed(cfg: FitConfig) -> dict:
        ts = time.perf_counter()
        prob = build_problem(mesh, bake, frames, images, masks, cfg, dev0)
        wp.synchronize_device(dev0)
        setup_s = time.perf_counter() - ts
        tf = time.perf_counter()
        report = None
        if cfg.stream.tiles:
            res, report = run_tiled_fit(prob, cfg)
        else:
            res = run_fit(prob, cfg)
        for d in set(devices):
            wp.synchronize_device(d)
        total_fit = time.perf_counter() - tf
        tile_setup = report["tile_setup_s"] if report else 0.0
        tr = res.trace
        best = max(r["psnr_db"] for r in tr)
        hit = next(r for r in tr if r["psnr_db"] >= best - 0.1)
        out = {"setup_s": setup_s, "tile_setup_s": tile_setup, "fit_loop_s": total_fit - tile_setup,
               "setup_and_fit_s": setup_s + total_fit, "iterations": tr[-1]["iteration"],
               "iterations_to_best_minus_0p1dB": hit["iteration"],
               "converged_model_s": setup_s + tile_setup + hit["time_s"],
               "final_objective": tr[-1]["objective"], "final_psnr_db": tr[-1]["psnr_db"],
               "texels": int(prob.n), "photos": int(prob.photos.n), "tiles": report,
               "setup_phases_s": {**{k: float(v) for k, v in prob.photos.timings.items()},
                                  "texels_and_problem": setup_s - float(sum(prob.photos.timings.values()))}}
        del prob
        return out, res.params

    results, params = {}, {}
    for name, cfg in runs.items():
        best = None
        for _ in range(max(1, a.repeats)):
            r, p = timed(cfg)
            if best is None or r["converged_model_s"] < best["converged_model_s"]:
                best = r
            params[name] = p
        results[name] = best
    def compare(name: str, against: str, prefix: str = "") -> None:
        ref, got = params[against], params[name]
        d = np.abs(got - ref)
        r = results[name]
        r[prefix + "same_params_to_the_bit"] = bool(np.array_equal(got, ref))
        r[prefix + "max_abs_param_diff"] = float(d.max())
        r[prefix + "max_rel_param_diff"] = float((d / np.maximum(np.abs(ref), 1e-6)).max())
        r[prefix + "params_differing_fraction"] = float(np.mean(d > 0))
        r[prefix + "final_objective_rel_diff"] = abs(r["final_objective"] - results[against]["final_objective"]) / abs(
            results[against]["final_objective"])

    for name in ("tiled_one_device", "multi_device", "photos_one_device"):
        if name in results:
            compare(name, "one_device")
    if "photos_multi_device" in results:
        compare("photos_multi_device", "photos_one_device")
        compare("photos_multi_device", "one_device", "vs_one_device_")
    one = results["one_device"]
    summary = {}
    for name, key in (("multi_device", ""), ("photos_multi_device", "_photos")):
        if name in results:
            summary["speedup_converged_model" + key] = one["converged_model_s"] / results[name]["converged_model_s"]
            summary["speedup_fit_loop" + key] = one["fit_loop_s"] / max(results[name]["fit_loop_s"], 1e-12)
    gpus = {d: wp.get_device(d).name for d in set(devices)}
    doc = {"command": "python benchmarks/multi_gpu.py " + " ".join(
               f"--{k.replace('_', '-')} {v}" for k, v in vars(a).items()),
           "commit": commit(), "machine": platform.node(), "devices": devices, "device_names": gpus,
           "scene": a.scene, "scale": a.scale, "texel_factor": a.texel_factor, "render_s": render_s,
           "photos": len(frames), "atlas": [bake.height, bake.width], "upload_pipeline": pipeline, "runs": results,
           "summary": summary}
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "multi_gpu.json").write_text(json.dumps(doc, indent=2))
    print(json.dumps({"summary": summary, **{k: {kk: v[kk] for kk in ("setup_s", "tile_setup_s", "fit_loop_s",
                                                                       "converged_model_s")}
                                              for k, v in results.items()}}, indent=2))


if __name__ == "__main__":
    main()
