"""A synthetic capture given as photos only, through ``texstream run PHOTOS``, against the same fit with
the true cameras and mesh (JSON).

    python benchmarks/photos_only.py --out out/photos_only

Renders the ``textured_sphere`` scene (a noise-textured matte sphere, a flash at each camera, 8-bit
photos), writes only its images into a folder as a camera leaves them (the same pixels with the
camera's EXIF focal length, :func:`texstream.capture.synthetic.photos_only.write_photos_only`; no capture.json, no masks,
no cameras), and runs the end-to-end pipeline with ``--colocated-light``: ingest (masks from the dark
background, the EXIF focal length as the prior), pycolmap registration with self-calibration, a mesh from the SfM points and masks, an atlas and the Lafortune
fit, every 8th photo held out. The reference runs the same pipeline and options on the capture with the
true cameras and the true atlas. Both are scored on their held-out views (pooled PSNR over foreground
pixels, worst view).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import shutil
import subprocess
import time
from pathlib import Path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="out/photos_only")
    ap.add_argument("--scene", default="textured_sphere")
    ap.add_argument("--iterations", type=int, default=15)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--hull-fill", default="on", choices=("on", "off"),
                    help="the mesh stage's visual-hull samples where the SfM points leave the object open")
    ap.add_argument("--atlas-resolution", type=int, default=0,
                    help="the atlas stage's largest side (0: the run's default)")
    ap.add_argument("--reference", default="on", choices=("on", "off"),
                    help="also run the pipeline with the true cameras and atlas (off: the photos-only run alone)")
    args = ap.parse_args()

    import warp as wp

    from texstream.capture.capture_json import read_capture
    from texstream.capture.synthetic.photos_only import write_photos_only
    from texstream.capture.synthetic.synth import SynthConfig, synthesize
    from texstream.pipelines.run import RunConfig, run_pipeline

    # the code that runs, read before the run (a commit made while it runs must not be named)
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=Path(__file__).parent).stdout.strip()
    wp.config.quiet = True
    wp.config.log_level = wp.LOG_WARNING
    out = Path(args.out)
    shutil.rmtree(out, ignore_errors=True)
    synthesize(args.scene, out / "truth", SynthConfig(progress=False, preview=False, device=args.device))
    truth = read_capture(out / "truth")
    light = truth.frames[0].light
    photos = out / "photos"
    write_photos_only(out / "truth", photos)  # the images as a camera leaves them: EXIF focal length, no poses

    cfg = RunConfig(device=args.device)
    cfg.mesh = dataclasses.replace(cfg.mesh, hull_fill=args.hull_fill == "on")
    if args.atlas_resolution:
        cfg.atlas = dataclasses.replace(cfg.atlas, resolution=args.atlas_resolution)
    # the flash's intensity as the irradiance it gives at the object (what the user can state without
    # knowing the reconstruction's scale): the truth's intensity over its camera-to-centre distance squared
    d = float(sum(((f.center ** 2).sum()) ** 0.5 for f in truth.frames) / len(truth.frames))
    irradiance = float(max(light.intensity)) / d ** 2
    cfg.ingest = dataclasses.replace(cfg.ingest, colocated_light=irradiance)
    cfg.fit = dataclasses.replace(cfg.fit, fit=dataclasses.replace(cfg.fit.fit, max_iterations=args.iterations))
    t0 = time.perf_counter()
    run = run_pipeline(photos, out / "run", cfg, log=lambda m: print(m, flush=True))
    run_s = time.perf_counter() - t0
    # the same pipeline and options with the true cameras (the capture folder) and the true atlas
    ref, ref_s = None, 0.0
    if args.reference == "on":
        t0 = time.perf_counter()
        ref = run_pipeline(out / "truth", out / "reference",
                           dataclasses.replace(cfg, mesh_file=str(out / "truth" / "ground_truth")),
                           log=lambda m: print(m, flush=True))
        ref_s = time.perf_counter() - t0
    result = {
        "scene": args.scene, "photos": len(truth.frames), "device": args.device,
        "machine": f"{platform.node()} ({os.cpu_count()} cores)",
        "commit": commit,
        "command": f"python benchmarks/photos_only.py --scene {args.scene} --iterations {args.iterations} "
                   f"--hull-fill {args.hull_fill} --atlas-resolution {args.atlas_resolution} "
                   f"--reference {args.reference}",
        "photos_only": {"heldout": run["heldout"], "seconds": run_s, "model": run["model"],
                        "model_reason": run["model_reason"],
                        "stages": [{k: s[k] for k in ("name", "status", "reason", "seconds")} for s in run["stages"]],
                        "registered": len(read_capture(out / "run" / "posed").frames)},
    }
    a = result["photos_only"]["heldout"]
    line = (f"photos only: pooled {a['pooled_psnr_db']:.2f} dB, worst {a['worst_psnr_db']:.2f} dB "
            f"({a['views']} views, {result['photos_only']['registered']} of {len(truth.frames)} registered)")
    if ref is not None:
        result["true_cameras_and_mesh"] = {"heldout": ref["heldout"], "seconds": ref_s, "model": ref["model"],
                                           "model_reason": ref["model_reason"]}
        b = ref["heldout"]
        result["pooled_gap_db"] = b["pooled_psnr_db"] - a["pooled_psnr_db"]
        line += (f"; true cameras and mesh: pooled {b['pooled_psnr_db']:.2f} dB, worst {b['worst_psnr_db']:.2f} dB; "
                 f"gap {result['pooled_gap_db']:.2f} dB")
    (out / "photos_only.json").write_text(json.dumps(result, indent=2))
    print(line)


if __name__ == "__main__":
    main()
