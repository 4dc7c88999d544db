"""``texstream run`` of 11 photos of 6 megapixels, each stage at the resolution it needs, against the same run
with every photo at full resolution (JSON: wall time per stage, the resolution each stage used, held-out PSNR).

    python benchmarks/hires_run.py --out out/hires                 # 3072x2048, the default run only
    python benchmarks/hires_run.py --out out/hires --full on       # and the full-resolution run
    python benchmarks/hires_run.py --out out/hires_1536 --scale 0.5 --full on   # 1536x1024 photos

Renders ``textured_sphere_6mp`` (capture/synthetic/scenes/textured_sphere_6mp.json: a noise-textured matte
sphere, a flash at each camera, 11 sRGB photos of 3072x2048 on one ring), writes only its images with the
camera's EXIF focal length as a camera leaves them (capture/synthetic/photos_only.py), and runs the pipeline from
them with ``--colocated-light`` as benchmarks/photos_only.py does (ingest, register, mesh, atlas, refine, fit,
export, report; every 8th photo held out). The full-resolution run differs only by the options that switch the
new behaviour off: SIFT on the photos as they are (``register.max_image_size`` the longest side), the refinement
on full-resolution photos with every blur level run (``refine.photo_level 0``, ``refine.pyramid off``,
``refine.min_move 0``), the fit's photos at full resolution (``fit.photo_level 0``).
``--scale s`` multiplies the photo sides by s (the same 11 photos; the texture sides too).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import shutil
import time
from pathlib import Path

import gitinfo

SCENE = Path(__file__).resolve().parent.parent / "capture" / "synthetic" / "scenes" / "textured_sphere_6mp.json"


def _run(photos: Path, out: Path, cfg, label: str) -> dict:
    from texstream.pipelines.run import STAGES, run_pipeline

    marks: list[tuple[str, float]] = []  # (stage, this process's CPU seconds at its first line): a shared box's load
    # stretches the wall time, the CPU time much less

    def log(message: str) -> None:
        name = message[1:].split("]", 1)[0] if message.startswith("[") else ""
        if name in STAGES and (not marks or marks[-1][0] != name):
            marks.append((name, time.process_time()))
        print(f"[{label}] {message}", flush=True)

    load = os.getloadavg()
    t0 = time.perf_counter()
    run = run_pipeline(photos, out, cfg, log=log)
    marks.append(("end", time.process_time()))
    cpu = {a[0]: round(b[1] - a[1], 2) for a, b in zip(marks, marks[1:])}
    return {"seconds": time.perf_counter() - t0, "cpu_seconds_per_stage": cpu, "loadavg_before": [round(x, 2) for x in load],
            "loadavg_after": [round(x, 2) for x in os.getloadavg()], "heldout": run["heldout"],
            "model": run["model"], "resolutions": run["resolutions"],
            "stages": {s["name"]: {"status": s["status"], "seconds": round(s["seconds"], 2)} for s in run["stages"]},
            "refine": {k: (run_stage(run, "refine").get(k)) for k in ("levels", "residual_before", "residual_after",
                                                                      "camera_rotation_deg")},
            "register": {k: run_stage(run, "register").get(k) for k in ("timings", "mean_reprojection_error")}}


def run_stage(run: dict, name: str) -> dict:
    return next((s.get("summary") or {} for s in run["stages"] if s["name"] == name), {})


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="out/hires")
    ap.add_argument("--scale", type=float, default=1.0, help="photo sides times this (1: 3072x2048)")
    ap.add_argument("--full", default="off", choices=("on", "off"), help="also the run at full resolution")
    ap.add_argument("--default", default="on", choices=("on", "off"), help="the run at the resolutions needed")
    ap.add_argument("--reuse", default="off", choices=("on", "off"),
                    help="the full-resolution run starts from a copy of the default run's folder: the stages whose "
                         "inputs and options are the same (ingest, mesh, atlas; register where SIFT read the photos "
                         "as they are in both) are not run again, only those whose resolution differs")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--mvs-level", type=int, default=None,
                    help="both runs' dense-stereo level (mvs.level; -1 auto; default: the run's default)")
    args = ap.parse_args()

    import warp as wp

    from texstream.capture.capture_json import read_capture
    from texstream.capture.synthetic.photos_only import write_photos_only
    from texstream.capture.synthetic.synth import SynthConfig, synthesize
    from texstream.pipelines.run import RunConfig

    # the code that runs, read before the run (a commit made while it runs must not be named)
    commit = gitinfo.commit()
    wp.config.quiet = True
    wp.config.log_level = wp.LOG_WARNING
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if not (out / "truth" / "capture.json").is_file():  # the render is reused: it is not what is measured
        synthesize(str(SCENE), out / "truth", SynthConfig(progress=False, preview=False, device=args.device,
                                                          scale=args.scale ** 2, photos=11))
    truth = read_capture(out / "truth")
    photos = out / "photos"
    if not photos.is_dir():
        write_photos_only(out / "truth", photos)
    size = f"{truth.frames[0].intrinsics.width}x{truth.frames[0].intrinsics.height}"

    cfg = RunConfig(device=args.device, progress=False)
    d = float(sum(((f.center ** 2).sum()) ** 0.5 for f in truth.frames) / len(truth.frames))
    cfg.ingest = dataclasses.replace(cfg.ingest, colocated_light=float(max(truth.frames[0].light.intensity)) / d ** 2)
    if args.mvs_level is not None:  # the mesh's resolution, the same in both runs (what they compare is the others')
        cfg.mesh = dataclasses.replace(cfg.mesh, mvs=dataclasses.replace(cfg.mesh.mvs, level=args.mvs_level))
    from texstream.calib.register import feature_image_size

    side = max(truth.frames[0].intrinsics.width, truth.frames[0].intrinsics.height)
    downscaled = feature_image_size(side, side, 0)[0] < side  # else SIFT reads the photos as they are either way
    full = dataclasses.replace(
        cfg, register=dataclasses.replace(cfg.register, max_image_size=side if downscaled else 0),
        refine=dataclasses.replace(cfg.refine, photo_level=0, pyramid=False, min_move=0.0),
        fit=dataclasses.replace(cfg.fit, photo_level=0))
    result = {"scene": "textured_sphere_6mp", "photos": len(truth.frames), "photo_size": size,
              "device": args.device, "machine": f"{platform.node()} ({os.cpu_count()} cores)", "commit": commit,
              "command": f"python benchmarks/hires_run.py --out {args.out} --scale {args.scale} --full {args.full} "
                         f"--default {args.default} --reuse {args.reuse} --device {args.device}"
                         + ("" if args.mvs_level is None else f" --mvs-level {args.mvs_level}"),
              "mvs_level": cfg.mesh.mvs.level}
    name = out / "hires_run.json"
    if name.is_file():  # a second invocation adds the other run
        result = {**json.loads(name.read_text()), **{k: v for k, v in result.items() if k != "command"}}
    for label, on, run_cfg in (("needed", args.default, cfg), ("full", args.full, full)):
        if on == "on":
            shutil.rmtree(out / f"run_{label}", ignore_errors=True)
            if label == "full" and args.reuse == "on":
                shutil.copytree(out / "run_needed", out / "run_full", symlinks=True)
            result[label] = _run(photos, out / f"run_{label}", run_cfg, label)
            name.write_text(json.dumps(result, indent=2, default=str))
    if "needed" in result and "full" in result:
        result["heldout_gap_db"] = (result["full"]["heldout"]["pooled_psnr_db"]
                                    - result["needed"]["heldout"]["pooled_psnr_db"])
        result["speedup"] = result["full"]["seconds"] / result["needed"]["seconds"]
    name.write_text(json.dumps(result, indent=2, default=str))
    for label in ("needed", "full"):
        if label in result:
            r = result[label]
            print(f"{label}: {r['seconds']:.1f} s, held-out pooled {r['heldout']['pooled_psnr_db']:.2f} dB; "
                  + ", ".join(f"{k} {v['seconds']:.1f} s" for k, v in r["stages"].items()))


if __name__ == "__main__":
    main()
