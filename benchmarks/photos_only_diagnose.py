"""Where the photos-only run loses against the true cameras and mesh (JSON): run after
``benchmarks/photos_only.py --out OUT``.

    python benchmarks/photos_only_diagnose.py --out out/photos_only

Reads ``OUT/truth`` (the synthetic capture and its ground truth) and ``OUT/run`` (the photos-only
run), aligns the SfM frame to the true one by the Sim3 of the camera centres (Umeyama), and measures:

- cameras: rotation error (deg), centre error (fraction of the object's diameter), focal length error;
- the mesh: distance of its vertices to the true surface and of the true surface to it (by latitude
  band for a sphere scene), as fractions of the object's diameter;
- masks: IoU of the ingest masks against the renderer's;
- the held-out PSNR of the same diffuse fit with (a) recovered cameras and mesh, (b) true cameras and
  the recovered mesh mapped into the true frame, (c) recovered cameras and the true mesh mapped into
  the SfM frame, (d) true cameras and mesh (the true atlas), each on its own capture's held-out views;
  (d2) as (d) with the pipeline's xatlas atlas of the true mesh; (b2), (c2) as (b), (c) with the meshes
  aligned by their surfaces (scaled ICP) instead of the camera centres.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np


def sim3_sfm_to_truth(got, truth) -> tuple[float, np.ndarray, np.ndarray, list[str]]:
    """(s, R, t) with x_truth = s R x_sfm + t from the matched camera centres, and the matched names."""
    from texstream.geometry.align import umeyama

    gt = {f.name: f for f in truth.frames}
    names = [f.name for f in got.frames if f.name in gt]
    src = np.stack([f.center for f in got.frames if f.name in gt])
    dst = np.stack([gt[n].center for n in names])
    s, r, t = umeyama(src, dst)
    return s, r, t, names


def camera_errors(got, truth, s, r, t, diameter: float) -> dict:
    gt = {f.name: f for f in truth.frames}
    rot, cen, foc = [], [], []
    for f in got.frames:
        g = gt[f.name]
        # world-to-camera rotation in the truth frame: R_sfm R^T
        d = (f.R @ r.T) @ g.R.T
        rot.append(np.degrees(np.arccos(np.clip((np.trace(d) - 1) / 2, -1, 1))))
        cen.append(np.linalg.norm(s * r @ f.center + t - g.center) / diameter)
        foc.append(f.intrinsics.fx / g.intrinsics.fx - 1)
    return {"rotation_deg": {"median": float(np.median(rot)), "max": float(np.max(rot))},
            "centre_over_diameter": {"median": float(np.median(cen)), "max": float(np.max(cen))},
            "focal_rel": {"median": float(np.median(foc)), "max_abs": float(np.max(np.abs(foc)))},
            "principal_point_px": [float(got.frames[0].intrinsics.cx - truth.frames[0].intrinsics.cx),
                                   float(got.frames[0].intrinsics.cy - truth.frames[0].intrinsics.cy)],
            "distortion": got.frames[0].intrinsics.distortion}


def mesh_errors(mesh, true_mesh, diameter: float) -> dict:
    """Two-sided surface distances, fractions of the object's diameter; true-to-mesh by latitude band (z up)."""
    from texstream.geometry.align import sample_mesh
    from texstream.geometry.reconstruct import point_surface_distance

    pm = sample_mesh(mesh, 20000, seed=1)
    pt = sample_mesh(true_mesh, 20000, seed=2)
    d_m = point_surface_distance(pm, true_mesh) / diameter
    d_t = point_surface_distance(pt, mesh) / diameter
    c = true_mesh.vertices.mean(axis=0)
    lat = np.degrees(np.arcsin(np.clip((pt[:, 2] - c[2]) / np.linalg.norm(pt - c, axis=1), -1, 1)))
    bands = {}
    for lo, hi in ((-90, -60), (-60, -30), (-30, 0), (0, 30), (30, 60), (60, 90)):
        sel = (lat >= lo) & (lat < hi)
        bands[f"{lo}..{hi}"] = {"median": float(np.median(d_t[sel])), "p95": float(np.quantile(d_t[sel], 0.95))}
    return {"mesh_to_true": {"median": float(np.median(d_m)), "p95": float(np.quantile(d_m, 0.95)),
                             "max": float(d_m.max())},
            "true_to_mesh": {"median": float(np.median(d_t)), "p95": float(np.quantile(d_t, 0.95)),
                             "max": float(d_t.max())},
            "true_to_mesh_by_latitude_deg": bands}


def mask_iou(got, truth) -> dict:
    from texstream.capture.imageio import read_mask

    gt = {f.name: f for f in truth.frames}
    ious = []
    for f in got.frames:
        g = gt[f.name]
        a = read_mask(got.mask_path(f), (f.intrinsics.height, f.intrinsics.width)) > 0
        b = read_mask(truth.mask_path(g), (g.intrinsics.height, g.intrinsics.width)) > 0
        ious.append((a & b).sum() / max(1, (a | b).sum()))
    return {"median": float(np.median(ious)), "min": float(np.min(ious))}


def fit_heldout(capture_dir: Path, geometry: Path, out: Path, iterations: int, device: str) -> dict:
    from texstream.fit.stages.stage import FitStageConfig, fit_stage

    cfg = FitStageConfig(holdout_every=8, device=device)
    cfg = dataclasses.replace(cfg, fit=dataclasses.replace(cfg.fit, model="diffuse", max_iterations=iterations))
    shutil.rmtree(out, ignore_errors=True)
    res = fit_stage(capture_dir, geometry, out, cfg, progress=False)
    h = res.summary["heldout"]
    return {"pooled_psnr_db": h["pooled_psnr_db"], "worst_psnr_db": h["worst_psnr_db"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="out/photos_only")
    ap.add_argument("--iterations", type=int, default=15)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--no-fits", action="store_true", help="only the camera, mesh and mask errors")
    args = ap.parse_args()

    import warp as wp
    from texstream.capture.capture_json import read_capture
    from texstream.geometry.align import align_to_points, sample_mesh, transform_mesh
    from texstream.geometry.atlas import AtlasConfig, atlas_stage
    from texstream.geometry.mesh_io import load_mesh, save_mesh

    wp.config.quiet = True
    out = Path(args.out)
    truth, got = read_capture(out / "truth"), read_capture(out / "run" / "posed")
    true_mesh = load_mesh(out / "truth" / "ground_truth" / "mesh.obj")
    mesh = load_mesh(out / "run" / "mesh" / "mesh.ply")
    lo, hi = true_mesh.bbox()
    diameter = float((hi - lo).max())
    s, r, t, names = sim3_sfm_to_truth(got, truth)
    to_truth = np.eye(4)
    to_truth[:3, :3], to_truth[:3, 3] = s * r, t
    mesh_t = transform_mesh(mesh, to_truth)
    result = {"sim3_scale": s, "registered": len(names), "cameras": camera_errors(got, truth, s, r, t, diameter),
              "mesh": mesh_errors(mesh_t, true_mesh, diameter), "mask_iou": mask_iou(got, truth)}
    print(json.dumps(result, indent=1))
    if not args.no_fits:
        d = out / "diagnose"
        d.mkdir(exist_ok=True)
        save_mesh(d / "recovered_in_truth.ply", mesh_t)
        save_mesh(d / "truth_in_sfm.ply", transform_mesh(true_mesh, np.linalg.inv(to_truth)))
        fits = {}
        fits["a_recovered_cameras_recovered_mesh"] = fit_heldout(out / "run" / "posed", out / "run" / "atlas",
                                                                  d / "fit_a", args.iterations, args.device)
        atlas_stage(d / "recovered_in_truth.ply", d / "atlas_b", AtlasConfig(), device=args.device)
        fits["b_true_cameras_recovered_mesh"] = fit_heldout(out / "truth", d / "atlas_b", d / "fit_b",
                                                             args.iterations, args.device)
        atlas_stage(d / "truth_in_sfm.ply", d / "atlas_c", AtlasConfig(), device=args.device)
        fits["c_recovered_cameras_true_mesh"] = fit_heldout(out / "run" / "posed", d / "atlas_c", d / "fit_c",
                                                             args.iterations, args.device)
        fits["d_truth"] = fit_heldout(out / "truth", out / "truth" / "ground_truth", d / "fit_d", args.iterations,
                                      args.device)
        # the pipeline's own atlas (xatlas) on the true mesh with the true cameras: what the atlas costs
        atlas_stage(out / "truth" / "ground_truth" / "mesh.obj", d / "atlas_d2", AtlasConfig(), device=args.device)
        fits["d2_truth_xatlas"] = fit_heldout(out / "truth", d / "atlas_d2", d / "fit_d2", args.iterations, args.device)
        # the meshes aligned by their surfaces (scaled ICP) instead of the camera centres: (b) then isolates the
        # recovered mesh's shape, (c) the recovered cameras' agreement with the true shape
        al = align_to_points(mesh, sample_mesh(true_mesh, 20000, seed=3))
        result["mesh_icp"] = {"scale": al.scale, "rms_over_diameter": al.rms / diameter}
        save_mesh(d / "recovered_icp_truth.ply", transform_mesh(mesh, al.matrix))
        save_mesh(d / "truth_icp_sfm.ply", transform_mesh(true_mesh, np.linalg.inv(al.matrix)))
        atlas_stage(d / "recovered_icp_truth.ply", d / "atlas_b2", AtlasConfig(), device=args.device)
        fits["b2_true_cameras_recovered_mesh_icp"] = fit_heldout(out / "truth", d / "atlas_b2", d / "fit_b2",
                                                                 args.iterations, args.device)
        atlas_stage(d / "truth_icp_sfm.ply", d / "atlas_c2", AtlasConfig(), device=args.device)
        fits["c2_recovered_cameras_true_mesh_icp"] = fit_heldout(out / "run" / "posed", d / "atlas_c2", d / "fit_c2",
                                                                 args.iterations, args.device)
        result["fits_diffuse_heldout"] = fits
        print(json.dumps(fits, indent=1))
    (out / "diagnose.json").write_text(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
