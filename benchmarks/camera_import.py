"""A synthetic capture written as a Metashape project and as RealityCapture XMPs, imported and run, against the
same run with the true cameras and mesh (JSON).

    python benchmarks/camera_import.py --out out/camera_import

The ``sphere`` scene (a glossy Lafortune sphere) with its light moved onto the camera (a flash: the light the
import can state with ``--colocated-light``), rendered through two sensors with Brown distortion
(:mod:`texstream.capture.synthetic.camera_exports`). Metashape: ``cameras.xml`` (calibration at 4x the photos'
resolution, a chunk transform with scale 2.5, one disabled and one unaligned camera), the photos as 8-bit JPEGs
with the full sensor's stale EXIF, the true mesh exported in chunk coordinates; ``texstream import metashape
--mesh`` then ``texstream run`` on the capture (its mesh taken as it is). RealityCapture: XMP sidecars (one
without a pose), imported, run with the true mesh. Each import is compared (same fit options, Lafortune, every
8th photo held out, held-out pooled PSNR over the scored pixels) with two runs on the same views:

- ``true_cameras_same_photos``: the same exported JPEGs undistorted by the same code with the TRUE lenses and
  poses, the true mesh: the same fit with the true cameras. Its gap to the import is what the import is
  responsible for (the cameras; ~0).
- ``pristine_photos``: the pinhole renders as 8-bit PNGs with the true cameras and mesh (no lens, no JPEG, no
  resampling): what the photos' round trip through an export costs on top.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import platform
import shutil
import subprocess
import time
from pathlib import Path


def _scene(name: str, intensity: float) -> dict:
    """The scene with its light at the camera; ``textured_sphere`` (diffuse noise albedo, a sharper test of the
    cameras) with its texture at 256 x 128 and noise cells of about 3 pixels of a 128 x 96 photo, for the CPU."""
    from texstream.capture.synthetic.synth import load_scene

    sc = load_scene(name)
    sc["light"] = {"type": "point", "mode": "camera", "offset": [0.0, 0.0, 0.0], "intensity": intensity}
    if name == "textured_sphere":
        sc["texture"] = {"width": 256, "height": 128, "padding": 2}
        sc["materials"]["noisy"]["noise"]["cells"] = [48, 24]
    return sc


def _heldout(run: dict, seconds: float) -> dict:
    h = run["heldout"]
    return {"pooled_psnr_db": h.get("pooled_psnr_db"), "worst_psnr_db": h.get("worst_psnr_db"),
            "views": h.get("views"), "model": run["model"], "seconds": seconds}


def heldout_photos_vs_pristine(capture_dir: Path, truth_dir: Path, every: int) -> dict:
    """The held-out photos of an imported capture against the pristine ones of the same views (pooled PSNR over
    the pixels the capture's masks keep where the pristine photo is not background black): the error of the
    reference the imported run is scored against, which no model can remove."""
    from texstream.capture.capture_json import read_capture, split_holdout
    from texstream.capture.imageio import read_image, read_mask

    cap, truth = read_capture(capture_dir), read_capture(truth_dir)
    views = {f.extra["label"]: f for f in split_holdout(cap.frames, every)[1]}
    sq, n = 0.0, 0
    for f in split_holdout(truth.frames, every)[1]:
        g = views[Path(f.file_path).stem]
        pristine = read_image(truth.image_path(f), channels=3)
        keep = pristine.max(-1) > 0
        if g.mask_path is not None:
            keep &= read_mask(cap.mask_path(g), keep.shape)
        d = read_image(cap.image_path(g), channels=3)[keep] - pristine[keep]
        sq, n = sq + float((d * d).sum()), n + d.size
    return {"pooled_psnr_db": -10.0 * math.log10(sq / n), "views": len(views)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="out/camera_import")
    ap.add_argument("--scene", default="sphere", choices=("sphere", "textured_sphere"))
    ap.add_argument("--photos", type=int, default=24)
    ap.add_argument("--width", type=int, default=128)
    ap.add_argument("--height", type=int, default=96)
    ap.add_argument("--iterations", type=int, default=15)
    ap.add_argument("--intensity", type=float, default=12.0)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--control", default="off", choices=("on", "off"),
                    help="also run the Metashape capture with the distortion ignored")
    args = ap.parse_args()

    import warp as wp

    from texstream.calib.metashape import MetashapeImportConfig, import_metashape
    from texstream.calib.posed_import import PosedPhoto, write_posed_capture
    from texstream.calib.realitycapture import RealityCaptureImportConfig, import_realitycapture
    from texstream.capture.capture_json import read_capture, write_capture
    from texstream.capture.synthetic.camera_exports import (render_export_set, write_metashape,
                                                            write_realitycapture, write_truth)
    from texstream.fit.stages.stage import eval_stage
    from texstream.pipelines.cmd_import import transform_mesh_file
    from texstream.pipelines.run import RunConfig, run_pipeline

    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=Path(__file__).parent).stdout.strip()
    wp.config.quiet = True
    out = Path(args.out)
    shutil.rmtree(out, ignore_errors=True)
    cfg = RunConfig(device=args.device, model="lafortune", second_lobe=False, progress=False)
    cfg.fit = dataclasses.replace(cfg.fit, fit=dataclasses.replace(cfg.fit.fit, max_iterations=args.iterations))
    scene = _scene(args.scene, args.intensity)

    def timed_run(src: Path, dst: Path, mesh: Path | None) -> tuple[dict, float]:
        t0 = time.perf_counter()
        run = run_pipeline(src, dst, dataclasses.replace(cfg, mesh_file=None if mesh is None else str(mesh)),
                           log=lambda m: print(m, flush=True))
        return run, time.perf_counter() - t0

    def on_truth(run_dir: Path, truth: Path) -> dict:
        s = eval_stage(run_dir / "model", truth, device=args.device, out_json=run_dir / "eval_on_truth.json",
                       holdout_every=cfg.fit.holdout_every).summary
        return {"pooled_psnr_db": s["pooled_psnr_db"], "worst_psnr_db": s["worst_psnr_db"], "views": s["frames"]}

    def same_photos_true_cameras(es, photos: Path, ext: str, skip: list[int], dst: Path) -> Path:
        """The exported photos with the true lenses and poses, undistorted as the import does."""
        posed = [PosedPhoto(label=lab, photo=photos / f"{lab}{ext}", r=f.R, t=f.t, lens=lens)
                 for i, (lab, f, lens) in enumerate(zip(es.labels, es.frames, es.lenses)) if i not in skip]
        dst.mkdir(parents=True)
        write_posed_capture(dst, posed, undistort=True, copy_mode="copy", colocated=args.intensity,
                            extra={"source": "camera_import benchmark: exported photos, true cameras"})
        return dst

    def compare(imp_run: dict, imp_s: float, same: tuple[dict, float], pristine: tuple[dict, float]) -> dict:
        psnr = imp_run["heldout"]["pooled_psnr_db"]
        return {"imported": _heldout(imp_run, imp_s), "true_cameras_same_photos": _heldout(*same),
                "pristine_photos": _heldout(*pristine),
                "gap_to_true_cameras_db": same[0]["heldout"]["pooled_psnr_db"] - psnr,
                "gap_to_pristine_db": pristine[0]["heldout"]["pooled_psnr_db"] - psnr}

    result: dict = {"scene": f"{args.scene}, light at the camera", "photos": args.photos,
                    "photo_size": [args.width, args.height], "device": args.device,
                    "machine": f"{platform.node()} ({os.cpu_count()} cores)", "commit": commit,
                    "command": f"python benchmarks/camera_import.py --scene {args.scene} --photos {args.photos} "
                               f"--width {args.width} "
                               f"--height {args.height} --iterations {args.iterations}"}
    # Metashape: cameras.xml + photos + the mesh in chunk coordinates
    es = render_export_set(scene, args.photos, args.width, args.height, device=args.device)
    info = write_metashape(es, out / "metashape")
    truth = write_truth(es, out / "metashape_truth", skip=tuple(info["disabled"] + info["unaligned"]))
    t0 = time.perf_counter()
    imp = import_metashape(out / "metashape" / "cameras.xml", out / "metashape" / "photos", out / "metashape_capture",
                           MetashapeImportConfig(colocated_light=args.intensity,
                                                 mesh=str(out / "metashape" / "mesh_chunk.obj")),
                           mesh_writer=transform_mesh_file)
    import_s = time.perf_counter() - t0
    run, run_s = timed_run(out / "metashape_capture", out / "metashape_run", None)
    skip = info["disabled"] + info["unaligned"]
    same = timed_run(same_photos_true_cameras(es, out / "metashape" / "photos", ".JPG", skip,
                                              out / "metashape_true_cameras"), out / "metashape_true_cameras_run",
                     truth / "mesh.obj")
    ref = timed_run(truth, out / "metashape_reference", truth / "mesh.obj")
    result["metashape"] = {"import": {**imp.summary, "seconds": import_s}, **compare(run, run_s, same, ref),
                           "imported_model_on_pristine_photos": on_truth(out / "metashape_run", truth),
                           "heldout_photos_vs_pristine": heldout_photos_vs_pristine(
                               out / "metashape_capture", truth, cfg.fit.holdout_every)}
    if args.control == "on":  # the same capture with the photos as taken: their distortion not undone
        ctl = out / "metashape_control"
        shutil.copytree(out / "metashape_capture", ctl)
        cap = read_capture(ctl)
        for f in cap.frames:
            (ctl / f.file_path).unlink()
            f.file_path = f"images/{f.extra['label']}.JPG"
            f.mask_path = None  # the undistortion's masks do not fit the distorted photos
            shutil.copy2(out / "metashape" / "photos" / f"{f.extra['label']}.JPG", ctl / f.file_path)
        write_capture(cap, ctl)
        run, run_s = timed_run(ctl, out / "metashape_control_run", None)
        result["metashape"]["distortion_ignored"] = _heldout(run, run_s)
    # RealityCapture: XMPs + photos, the true mesh given to the run
    es = render_export_set(scene, args.photos, args.width, args.height, skew_free=True, device=args.device)
    info = write_realitycapture(es, out / "realitycapture")
    truth = write_truth(es, out / "realitycapture_truth", skip=tuple(info["unposed"]))
    t0 = time.perf_counter()
    imp = import_realitycapture(out / "realitycapture" / "xmp", out / "realitycapture" / "photos",
                                out / "realitycapture_capture", RealityCaptureImportConfig(colocated_light=args.intensity))
    import_s = time.perf_counter() - t0
    run, run_s = timed_run(out / "realitycapture_capture", out / "realitycapture_run", truth / "mesh.obj")
    same = timed_run(same_photos_true_cameras(es, out / "realitycapture" / "photos", ".jpg", info["unposed"],
                                              out / "realitycapture_true_cameras"),
                     out / "realitycapture_true_cameras_run", truth / "mesh.obj")
    ref = timed_run(truth, out / "realitycapture_reference", truth / "mesh.obj")
    result["realitycapture"] = {"import": {**imp.summary, "seconds": import_s}, **compare(run, run_s, same, ref),
                                "imported_model_on_pristine_photos": on_truth(out / "realitycapture_run", truth),
                                "heldout_photos_vs_pristine": heldout_photos_vs_pristine(
                                    out / "realitycapture_capture", truth, cfg.fit.holdout_every)}
    (out / "camera_import.json").write_text(json.dumps(result, indent=2, default=str))
    for k in ("metashape", "realitycapture"):
        r = result[k]
        print(f"{k}: imported {r['imported']['pooled_psnr_db']:.2f} dB, true cameras same photos "
              f"{r['true_cameras_same_photos']['pooled_psnr_db']:.2f} dB (gap {r['gap_to_true_cameras_db']:.2f}), "
              f"pristine photos {r['pristine_photos']['pooled_psnr_db']:.2f} dB (gap {r['gap_to_pristine_db']:.2f})"
              f"; imported model on the pristine photos {r['imported_model_on_pristine_photos']['pooled_psnr_db']:.2f}"
              f"; held-out photos vs pristine {r['heldout_photos_vs_pristine']['pooled_psnr_db']:.2f} dB"
              + (f"; distortion ignored {r['distortion_ignored']['pooled_psnr_db']:.2f} dB"
                 if "distortion_ignored" in r else ""))

if __name__ == "__main__":
    main()
