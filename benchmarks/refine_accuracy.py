"""How close the photometric refinement brings the cameras and the mesh to the truth (JSON): run after
``benchmarks/photos_only.py --out OUT``.

    python benchmarks/refine_accuracy.py --out out/photos_only

Compares ``OUT/run/posed`` + ``OUT/run/atlas`` (structure from motion and the mesh stage) and ``OUT/run/refine``
(the refine stage's output) with ``OUT/truth``, each mapped into the true frame by the Sim3 of its camera
centres (``photos_only_diagnose.py``'s measures: camera rotation and centre errors, two-sided mesh-to-surface
distances as fractions of the object's diameter), and the image distance between where each camera and its true
camera put the true surface (pixels, median over the surface facing the camera), which is what the texture sees.

With ``--fits``, also the held-out PSNR of a diffuse fit (every 8th photo held out, 15 LM iterations) with
(a) the refined cameras and mesh, (b) the true cameras and the refined mesh mapped into the true frame, (c) the
refined cameras and the true mesh mapped into the refined frame (both by the centres' Sim3; the meshes mapped
get an xatlas atlas): which of the two limits the model.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
from pathlib import Path

import numpy as np

from photos_only_diagnose import camera_errors, mesh_errors, sim3_sfm_to_truth


def reprojection_px(got, truth, s, r, t, points: np.ndarray) -> dict:
    """Median image distance per camera between the true surface points projected by the camera (mapped into the
    true frame) and by the true camera, over the points facing the true camera."""
    gt = {f.name: f for f in truth.frames}
    centre = points.mean(axis=0)
    per = []
    for f in got.frames:
        g = gt[f.name]
        # the camera in the true frame: x_cam = R_f x_sfm + t_f with x_sfm = R^T (x - t) / s, times s (a
        # projection does not see the scale): s x_cam = R_f R^T x + (s t_f - R_f R^T t)
        rot = f.R @ r.T
        trans = s * f.t - rot @ t
        k = f.intrinsics

        def project(rr, tt, kk):
            p = points @ rr.T + tt
            return np.stack([kk.fx * p[:, 0] / p[:, 2] + kk.cx, kk.fy * p[:, 1] / p[:, 2] + kk.cy], 1)

        facing = (points - centre) @ (g.center - centre) > 0.3 * np.linalg.norm(points - centre, axis=1) * \
            np.linalg.norm(g.center - centre)
        d = np.linalg.norm(project(rot, trans, k) - project(g.R, g.t, g.intrinsics), axis=1)
        per.append(float(np.median(d[facing])))
    return {"median": float(np.median(per)), "max": float(np.max(per))}


def measure(cap_dir: Path, mesh_file: Path, truth, true_mesh, diameter: float) -> dict:
    from texstream.capture.capture_json import read_capture
    from texstream.geometry.mesh_io import load_mesh

    got = read_capture(cap_dir)
    s, r, t, _ = sim3_sfm_to_truth(got, truth)
    mesh = load_mesh(mesh_file)
    mapped = type(mesh)(vertices=(s * (r @ mesh.vertices.T)).T + t, faces=mesh.faces)
    return {"cameras": camera_errors(got, truth, s, r, t, diameter),
            "surface_px": reprojection_px(got, truth, s, r, t, true_mesh.vertices),
            "mesh": mesh_errors(mapped, true_mesh, diameter)}


def swapped_fits(out: Path, truth, true_mesh) -> dict:
    import shutil

    from photos_only_diagnose import fit_heldout
    from texstream.capture.capture_json import read_capture
    from texstream.geometry.align import transform_mesh
    from texstream.geometry.atlas import AtlasConfig, atlas_stage
    from texstream.geometry.mesh_io import load_mesh, save_mesh

    refined = out / "run" / "refine"
    d = out / "refine_fits"
    shutil.rmtree(d, ignore_errors=True)
    d.mkdir()
    s, r, t, _ = sim3_sfm_to_truth(read_capture(refined), truth)
    to_truth = np.eye(4)
    to_truth[:3, :3], to_truth[:3, 3] = s * r, t
    save_mesh(d / "refined_in_truth.ply", transform_mesh(load_mesh(refined / "mesh.obj"), to_truth))
    save_mesh(d / "truth_in_refined.ply", transform_mesh(true_mesh, np.linalg.inv(to_truth)))
    atlas_stage(d / "refined_in_truth.ply", d / "atlas_b", AtlasConfig())
    atlas_stage(d / "truth_in_refined.ply", d / "atlas_c", AtlasConfig())
    return {"a_refined_cameras_refined_mesh": fit_heldout(refined, refined, d / "fit_a", 15, "cpu"),
            "b_true_cameras_refined_mesh": fit_heldout(out / "truth", d / "atlas_b", d / "fit_b", 15, "cpu"),
            "c_refined_cameras_true_mesh": fit_heldout(refined, d / "atlas_c", d / "fit_c", 15, "cpu")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="out/photos_only")
    ap.add_argument("--results", default=None, help="also copy the JSON here (e.g. benchmarks/results/real_photos)")
    ap.add_argument("--fits", action="store_true", help="also fit with refined / true cameras and meshes (minutes)")
    args = ap.parse_args()

    import warp as wp

    from texstream.capture.capture_json import read_capture
    from texstream.geometry.mesh_io import load_mesh

    wp.config.quiet = True
    out = Path(args.out)
    truth = read_capture(out / "truth")
    true_mesh = load_mesh(out / "truth" / "ground_truth" / "mesh.obj")
    diameter = float(np.ptp(true_mesh.vertices, axis=0).max())
    run = out / "run"
    result = {
        "machine": f"{platform.node()} ({os.cpu_count()} cores)",
        "commit": subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                                 cwd=Path(__file__).parent).stdout.strip(),
        "command": f"python benchmarks/refine_accuracy.py --out {args.out}" + (" --fits" if args.fits else ""),
        "registered": measure(run / "posed", run / "atlas" / "mesh.obj", truth, true_mesh, diameter),
        "refined": measure(run / "refine", run / "refine" / "mesh.obj", truth, true_mesh, diameter),
        "refine": {k: v for k, v in json.loads((run / "refine" / "refine.json").read_text()).items() if k != "trace"},
    }
    if args.fits:
        result["heldout_fits"] = swapped_fits(out, truth, true_mesh)
    text = json.dumps(result, indent=2)
    (out / "refine_accuracy.json").write_text(text)
    if args.results:
        Path(args.results).mkdir(parents=True, exist_ok=True)
        (Path(args.results) / "refine_accuracy_textured_sphere.json").write_text(text)
    for k in ("registered", "refined"):
        m = result[k]
        print(f"{k}: rotation {m['cameras']['rotation_deg']['median']:.3f} / {m['cameras']['rotation_deg']['max']:.3f} deg, "
              f"centre {100 * m['cameras']['centre_over_diameter']['median']:.2f}% / "
              f"{100 * m['cameras']['centre_over_diameter']['max']:.2f}%, surface in the image "
              f"{m['surface_px']['median']:.2f} / {m['surface_px']['max']:.2f} px, mesh to surface "
              f"{100 * m['mesh']['true_to_mesh']['median']:.3f}% / {100 * m['mesh']['true_to_mesh']['p95']:.3f}% (p95)")


if __name__ == "__main__":
    main()
