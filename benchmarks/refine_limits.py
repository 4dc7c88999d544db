"""What bounds the photometric refinement on the photos-only sphere (JSON): run after ``benchmarks/photos_only.py
--out OUT``.

    python benchmarks/refine_limits.py --out out/photos_only [--cases truth,registered] [--refine JSON]

Each case runs the refine stage (``geometry/refine.py``) from a start and then the diffuse held-out fit of
``photos_only_diagnose.fit_heldout`` (every 8th photo held out, 15 LM iterations; the held-out cameras are the
refine stage's aligned ones), so the cases compare like with like:

* ``truth``: no refinement, the true cameras and atlas (the reference);
* ``from_truth``: refined from the true cameras and mesh: how far the objective's minimum lies from the truth;
* ``from_truth_focal``: the same with every focal length 0.12% long (the registration's error on this set);
* ``from_truth_detail0``: from the truth, intensities compared instead of the band-passed detail;
* ``registered`` / ``registered_detail0``: from the registered cameras and the dense-stereo mesh (the run's own
  start), with the detail and with intensities;
* ``registered_all_fitted``: the same with the held-out photos refined jointly with the others (a diagnostic: it
  lets held-out photos move the geometry), to tell the alignment of held-out photos from the reconstruction;
* ``registered_cameras_true_mesh``: the registered cameras with the true mesh (mapped into their frame by the Sim3 of
  the camera centres, xatlas atlas), cameras refined, the mesh held: what the cameras' refinement reaches alone;
* ``true_cameras_registered_mesh``: the true cameras with the run's mesh (mapped into the true frame), the mesh
  refined, the cameras held: what the mesh's refinement reaches alone.

Per case: the refine residuals before and after, the median camera turn, the held-out pooled and worst PSNR, and the
training PSNR of the fit.
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


def focal_scaled_capture(src: Path, out: Path, factor: float) -> Path:
    from texstream.capture.capture_json import Capture, read_capture, write_capture

    cap = read_capture(src)
    frames = [dataclasses.replace(f, intrinsics=dataclasses.replace(f.intrinsics, fx=f.intrinsics.fx * factor,
                                                                    fy=f.intrinsics.fy * factor),
                                  file_path=str((src / f.file_path).resolve()),
                                  mask_path=None if f.mask_path is None else str((src / f.mask_path).resolve()))
              for f in cap.frames]
    shutil.rmtree(out, ignore_errors=True)
    write_capture(Capture(root=out, frames=frames, extra=dict(cap.extra)), out)
    return out


def map_meshes(out: Path, work: Path) -> dict:
    """Atlas folders of the true mesh in the registered frame and of the run's mesh in the true frame (the Sim3 of
    the camera centres, ``photos_only_diagnose.sim3_sfm_to_truth``; xatlas atlases)."""
    import numpy as np

    from photos_only_diagnose import sim3_sfm_to_truth
    from texstream.capture.capture_json import read_capture
    from texstream.geometry.align import transform_mesh
    from texstream.geometry.atlas import AtlasConfig, atlas_stage
    from texstream.geometry.mesh_io import load_mesh, save_mesh

    s, r, t, _ = sim3_sfm_to_truth(read_capture(out / "run" / "posed"), read_capture(out / "truth"))
    to_truth = np.eye(4)
    to_truth[:3, :3], to_truth[:3, 3] = s * r, t
    save_mesh(work / "true_in_registered.ply",
              transform_mesh(load_mesh(out / "truth" / "ground_truth" / "mesh.obj"), np.linalg.inv(to_truth)))
    save_mesh(work / "registered_in_truth.ply", transform_mesh(load_mesh(out / "run" / "atlas" / "mesh.obj"), to_truth))
    res = {}
    for name in ("true_in_registered", "registered_in_truth"):
        atlas_stage(work / f"{name}.ply", work / f"atlas_{name}", AtlasConfig())
        res[name] = work / f"atlas_{name}"
    return res


def fit_case(capture: Path, atlas: Path, out: Path) -> dict:
    from photos_only_diagnose import fit_heldout

    res = fit_heldout(capture, atlas, out, 15, "cpu")
    res["training_psnr_db"] = json.loads((out / "model.json").read_text())["final"]["psnr_db"]
    return res


def refine_with(capture: Path, atlas: Path, out: Path, **options) -> dict:
    from texstream.geometry.refine import RefineConfig, refine_stage

    shutil.rmtree(out, ignore_errors=True)
    t0 = time.perf_counter()
    s = refine_stage(capture, atlas, out, RefineConfig(**options), device="cpu").summary
    return {"options": options, "residual_before": s["residual_before"], "residual_after": s["residual_after"],
            "camera_turn_deg": s["camera_rotation_deg"], "seconds": time.perf_counter() - t0,
            "shading_normals": s.get("shading_normals"),
            **fit_case(out, out, Path(str(out) + "_fit"))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="out/photos_only")
    ap.add_argument("--results", default=None, help="also copy the JSON here (e.g. benchmarks/results/real_photos)")
    ap.add_argument("--cases", default="", help="only these cases (comma-separated names; default: all)")
    ap.add_argument("--refine", default="{}", help="RefineConfig options for every refining case, as JSON "
                                                   "(e.g. '{\"normal_iterations\": 0}': no shaded refinement)")
    args = ap.parse_args()

    import warp as wp

    wp.config.quiet = True
    out = Path(args.out)
    truth, true_atlas, run = out / "truth", out / "truth" / "ground_truth", out / "run"
    common = json.loads(args.refine)

    def refine_case(capture, atlas, folder, **options):
        return refine_with(capture, atlas, folder, **{**common, **options})

    work = out / "refine_limits"
    work.mkdir(exist_ok=True)
    mapped = map_meshes(out, work)
    todo = {
        "truth": lambda: fit_case(truth, true_atlas, work / "truth_fit"),
        "from_truth": lambda: refine_case(truth, true_atlas, work / "from_truth"),
        "from_truth_focal": lambda: refine_case(focal_scaled_capture(truth, work / "focal_capture", 1.0012),
                                                true_atlas, work / "from_truth_focal"),
        "from_truth_detail0": lambda: refine_case(truth, true_atlas, work / "from_truth_detail0", detail=0.0),
        "registered": lambda: refine_case(run / "posed", run / "atlas", work / "registered"),
        "registered_detail0": lambda: refine_case(run / "posed", run / "atlas", work / "registered_detail0",
                                                  detail=0.0),
        "registered_all_fitted": lambda: refine_case(run / "posed", run / "atlas",
                                                     work / "registered_all_fitted", holdout_every=0),
        "registered_cameras_true_mesh": lambda: refine_case(run / "posed", mapped["true_in_registered"],
                                                            work / "registered_cameras_true_mesh",
                                                            mesh=False),
        "true_cameras_registered_mesh": lambda: refine_case(truth, mapped["registered_in_truth"],
                                                            work / "true_cameras_registered_mesh",
                                                            cameras=False)}
    chosen = [c for c in args.cases.split(",") if c] or list(todo)
    unknown = sorted(set(chosen) - set(todo))
    if unknown:
        raise SystemExit(f"refine_limits.py: unknown case(s) {unknown}; choose from {sorted(todo)}")
    cases = {name: todo[name]() for name in chosen}
    result = {
        "machine": f"{platform.node()} ({os.cpu_count()} cores)",
        "commit": subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                                 cwd=Path(__file__).parent).stdout.strip(),
        "command": f"python benchmarks/refine_limits.py --out {args.out}"
                   + (f" --cases {args.cases}" if args.cases else "")
                   + (f" --refine '{args.refine}'" if common else ""), "cases": cases}
    text = json.dumps(result, indent=2)
    (out / "refine_limits.json").write_text(text)
    if args.results:
        Path(args.results).mkdir(parents=True, exist_ok=True)
        (Path(args.results) / "refine_limits_textured_sphere.json").write_text(text)
    for name, c in cases.items():
        print(f"{name}: held-out pooled {c['pooled_psnr_db']:.2f} dB, worst {c['worst_psnr_db']:.2f} dB, training "
              f"{c['training_psnr_db']:.2f} dB" + (f", refine residual {c['residual_before']['fit_rms']:.4f} -> "
                                                  f"{c['residual_after']['fit_rms']:.4f}" if "residual_after" in c else ""))


if __name__ == "__main__":
    main()
