"""Where the photos-only flash capture loses accuracy, stage by stage (issue 39; JSON): run after
``benchmarks/flash_capture.py --out OUT``.

    python benchmarks/flash_capture_stages.py --out out/flash_capture [--controls]

Reads ``OUT/truth`` (the synthetic capture) and ``OUT/run`` (the photos-only run). Per stage whose cameras the
fit can see (``posed``: registration; ``refine``: the photometric refinement), with the run's frame brought
into the truth's by the similarity of the camera centres (as flash_capture.py's texel errors are): the centres'
RMS (scene units: the sphere's radius is 1, the cameras about 5.2 from its centre), the rotations' median and
largest error, the focal length's error, and the pixel error of the true sphere (per photo the median distance
between where a point of the true surface lands in the photo by the true camera and by the run's, the point
mapped by the similarity; its median and 90th percentile over the photos): the error a texel sees. The meshes
(``mesh``, ``refine``): their vertices' distance to the true sphere in that frame.

With ``--controls`` (about 15 minutes on a loaded 2-core CPU, the mesh of the true cameras 7 of them) the same
stages from the true inputs: the mesh stage on the true cameras; the refine stage on the true cameras and mesh
(the true atlas, ``OUT/fit_geometry``); and the Lafortune fit (as flash_capture.py runs it: 15 iterations, every
8th photo held out, the ambient term on) on the true inputs (with the true atlas, with the pipeline's atlas of the
true mesh, after the refine stage) and on crossings of true and recovered inputs (true cameras and the recovered
mesh, the recovered cameras and the true mesh, each mesh carried across by the cameras' similarity and given the
pipeline's atlas; the recovered cameras and mesh with the true response) and the photos-only run without its refine
stage (``run/lights`` and ``run/atlas``), with it, and with its parts alone (no shaded refinement; poses held):
held-out flash PSNR (in each capture's units: the chart's response
is 1.83x the true one at mid codes, 5.2 dB), the albedo's per-texel error. The meshes' normals against the
sphere's (what the flash's cosine, so the albedo, depends on). Writes ``OUT/flash_capture_stages.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import time
from pathlib import Path

import numpy as np
from flash_capture import _similarity, _texel_errors, heldout_flash


def _sphere_pixel_error(frames, truth, sim) -> dict:
    """Per photo, the median pixel distance between the true sphere's points (those the true camera faces) as
    the true camera and as the run's camera (the point mapped into the run's frame) project them."""
    s, r, t = sim[:3]
    gt = {f.name: f for f in truth.frames}
    u = np.random.default_rng(0).normal(size=(4000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)

    def project(f, x):
        cam = x @ np.asarray(f.R).T + np.asarray(f.t).reshape(3)
        k = f.intrinsics
        return np.c_[k.fx * cam[:, 0] / cam[:, 2] + k.cx, k.fy * cam[:, 1] / cam[:, 2] + k.cy]

    per = []
    for f in frames:
        g = gt[f.name]
        view = g.center - u
        q = u[np.sum(u * view, axis=1) / np.linalg.norm(view, axis=1) > 0.2]
        per.append(float(np.median(np.linalg.norm(project(f, ((q - t) / s) @ r) - project(g, q), axis=1))))
    return {"median": float(np.median(per)), "p90": float(np.percentile(per, 90)), "max": float(np.max(per))}


def _camera_errors(capture_dir: Path, truth) -> dict:
    from texstream.capture.capture_json import read_capture

    got = read_capture(capture_dir)
    gt = {f.name: f for f in truth.frames}
    frames = [f for f in got.frames if f.name in gt]
    sim = _similarity(frames, truth.frames)
    r = sim[1]
    rot = []
    for f in frames:
        d = (np.asarray(f.R) @ r.T) @ np.asarray(gt[f.name].R).T
        rot.append(np.degrees(np.arccos(np.clip((np.trace(d) - 1) / 2, -1, 1))))
    fx = float(np.median([f.intrinsics.fx for f in frames]))
    return {"camera_rms": sim[3], "rotation_deg": {"median": float(np.median(rot)), "max": float(np.max(rot))},
            "focal_rel_error": fx / truth.frames[0].intrinsics.fx - 1.0,
            "sphere_pixel_error": _sphere_pixel_error(frames, truth, sim)}, sim


def _mesh_distance(mesh_path: Path, sim) -> dict:
    from texstream.geometry.mesh_io import load_mesh

    s, r, t = sim[:3]
    v = s * load_mesh(mesh_path).vertices.astype(np.float64) @ r.T + t
    d = np.abs(np.linalg.norm(v, axis=1) - 1.0)
    return {"sphere_distance_median": float(np.median(d)), "sphere_distance_p99": float(np.percentile(d, 99))}


def _fit(capture_dir: Path, geometry: Path, out: Path, truth_dir: Path, truth, reuse: bool = False) -> dict:
    """flash_capture.py's fit (Lafortune, 15 iterations, every 8th photo held out, ambient on) and its scores
    (with ``reuse``, those of the model already in ``out``)."""
    from texstream.capture.capture_json import flash_fired, read_capture, split_holdout
    from texstream.fit.optim.fitter import FitConfig
    from texstream.fit.stages.stage import FitStageConfig, fit_stage

    cfg = FitStageConfig(device="cpu", holdout_every=8, fit=FitConfig(model="lafortune", ambient="on",
                                                                      max_iterations=15))
    t0 = time.perf_counter()
    if not (reuse and (out / "model.json").is_file()):
        fit_stage(capture_dir, geometry, out, cfg, progress=False)
    train_flash = [f for f in split_holdout(truth.frames, 8)[0] if flash_fired(f)]
    sim = _similarity(read_capture(capture_dir).frames, truth.frames)
    texels = _texel_errors(out, truth_dir, sim, truth.frames, train_flash)
    return {"heldout_flash": heldout_flash(out), "albedo_rel_error_median": texels["albedo_rel_error"]["median"],
            "albedo_rel_error_neighbourhood_median": texels["albedo_rel_error_neighbourhood"]["median"],
            "match_distance_median": texels["match_distance_median"], "seconds": time.perf_counter() - t0}


def _normal_error_deg(mesh_path: Path, sim) -> dict:
    """The angle between the mesh's area-weighted vertex normals (from its faces) and the true sphere's at the
    vertex (degrees): what sets the flash's cosine, so the albedo divided by it (2 degrees at 40 degrees off the
    flash: 3%)."""
    from texstream.geometry.mesh_io import load_mesh

    mesh = load_mesh(mesh_path)
    s, r, t = sim[:3]
    v = s * mesh.vertices.astype(np.float64) @ r.T + t
    f = mesh.faces
    face_normal = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    normal = np.zeros_like(v)
    for k in range(3):
        np.add.at(normal, f[:, k], face_normal)
    cos = np.sum(normal * v, axis=1) / (np.linalg.norm(normal, axis=1) * np.linalg.norm(v, axis=1) + 1e-30)
    ang = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    return {"median": float(np.median(ang)), "p90": float(np.percentile(ang, 90))}


def _controls(out: Path, truth, reuse: bool) -> dict:
    """The true inputs through the mesh and refine stages, and the fit on crossings of true and recovered inputs
    (module doc); with ``reuse`` the outputs of an earlier --controls run are read again."""
    import shutil

    from texstream.geometry.align import transform_mesh
    from texstream.geometry.atlas import AtlasConfig, atlas_stage
    from texstream.geometry.make_mesh import MeshConfig, make_mesh
    from texstream.geometry.mesh_io import load_mesh, save_mesh
    from texstream.geometry.refine import RefineConfig, refine_stage

    work = out / "stages"
    truth_dir, true_geometry, run = out / "truth", out / "fit_geometry", out / "run"
    identity = (1.0, np.eye(3), np.zeros(3))
    result = {}
    t0 = time.perf_counter()
    if not (reuse and (work / "mesh_true_cameras" / "mesh.ply").is_file()):
        make_mesh(truth_dir, work / "mesh_true_cameras", MeshConfig(device="cpu"))
    result["mesh_true_cameras"] = {**_mesh_distance(work / "mesh_true_cameras" / "mesh.ply", identity),
                                   "normal_error_deg": _normal_error_deg(work / "mesh_true_cameras" / "mesh.ply",
                                                                         identity),
                                   "seconds": time.perf_counter() - t0}
    t0 = time.perf_counter()
    if not (reuse and (work / "refine_true_inputs" / "capture.json").is_file()):
        refine_stage(truth_dir, true_geometry, work / "refine_true_inputs", RefineConfig(), device="cpu")
    cams, sim = _camera_errors(work / "refine_true_inputs", truth)
    result["refine_true_inputs"] = {**cams, "mesh": _mesh_distance(work / "refine_true_inputs" / "mesh.obj", sim),
                                    "seconds": time.perf_counter() - t0}
    # the crossings: the recovered mesh in the truth's frame, the true mesh in the run's, each through the
    # pipeline's atlas at the run's resolution; the run's cameras with the true response (its flash rescaled)
    _, run_sim = _camera_errors(run / "lights", truth)
    to_truth = np.eye(4)
    to_truth[:3, :3], to_truth[:3, 3] = run_sim[0] * run_sim[1], run_sim[2]
    atlas = AtlasConfig(resolution=int(json.loads((run / "atlas" / "atlas_config.json").read_text())["resolution"]))
    save_mesh(work / "recovered_mesh_in_truth.ply", transform_mesh(load_mesh(run / "mesh" / "mesh.ply"), to_truth))
    save_mesh(work / "true_mesh_in_run.obj", transform_mesh(load_mesh(truth_dir / "ground_truth" / "mesh.obj"),
                                                            np.linalg.inv(to_truth)))
    for name, mesh in (("recovered_in_truth", work / "recovered_mesh_in_truth.ply"),
                       ("true_in_run", work / "true_mesh_in_run.obj"),
                       ("true", truth_dir / "ground_truth" / "mesh.obj")):
        if not (reuse and (work / f"atlas_{name}" / "bake.npz").is_file()):
            shutil.rmtree(work / f"atlas_{name}", ignore_errors=True)
            atlas_stage(mesh, work / f"atlas_{name}", atlas, device="cpu")
    _true_response_capture(out, work / "true_response")
    fits = {"true_inputs": (truth_dir, true_geometry),
            "true_inputs_pipeline_atlas": (truth_dir, work / "atlas_true"),
            "true_inputs_refined": (work / "refine_true_inputs", work / "refine_true_inputs"),
            "true_cameras_recovered_mesh": (truth_dir, work / "atlas_recovered_in_truth"),
            "recovered_cameras_true_mesh": (run / "lights", work / "atlas_true_in_run"),
            "recovered_cameras_mesh_true_response": (work / "true_response", run / "atlas"),
            "photos_only_without_refine": (run / "lights", run / "atlas")}
    # the refine stage's parts on the photos-only run: without the shaded refinement (poses and displacements on
    # the photos' detail only), and with the poses held (displacements and shading normals only)
    for name, option in (("photos_only_refined_without_shading", {"normal_iterations": 0}),
                         ("photos_only_refined_poses_held", {"cameras": False})):
        if not (reuse and (work / f"refine_{name}" / "capture.json").is_file()):
            refine_stage(run / "lights", run / "atlas", work / f"refine_{name}", RefineConfig(**option), device="cpu")
        fits[name] = (work / f"refine_{name}", work / f"refine_{name}")
    fits["photos_only_refined"] = (run / "refine", run / "refine")
    result["fits"] = {name: _fit(cap, geometry, work / f"fit_{name}", truth_dir, truth, reuse)
                      for name, (cap, geometry) in fits.items()}
    return result


def _true_response_capture(out: Path, dst: Path) -> None:
    """The run's lit capture (``run/lights``) with the true response, its flash's intensity divided by the two
    curves' scale ratio (flash_capture.json's chart check) so the albedos stay absolute; photo paths absolute."""
    data = json.loads((out / "run" / "lights" / "capture.json").read_text())
    scale = json.loads((out / "flash_capture.json").read_text())["chart"]["scale_fitted_over_true"]
    data["response"] = json.loads((out / "truth" / "capture.json").read_text())["response"]
    for f in data["frames"]:
        if f.get("light"):
            f["light"]["intensity"] = [v / scale for v in f["light"]["intensity"]]
        for key in ("file_path", "mask_path"):
            if f.get(key):
                f[key] = str((out / "run" / "lights" / f[key]).resolve())
    dst.mkdir(parents=True, exist_ok=True)
    (dst / "capture.json").write_text(json.dumps(data))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="out/flash_capture")
    ap.add_argument("--controls", action="store_true", help="the true inputs through the mesh and refine stages, "
                    "and the fits on crossings of true and recovered inputs (module doc)")
    ap.add_argument("--reuse", action="store_true", help="with --controls: the outputs of an earlier run (OUT/stages: "
                    "the true-camera mesh, the refined true inputs, the atlases and fits) read again")
    a = ap.parse_args()

    import warp as wp
    from texstream.capture.capture_json import read_capture

    wp.config.quiet = True
    out = Path(a.out)
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=False,
                            cwd=Path(__file__).parent).stdout.strip()
    truth = read_capture(out / "truth")
    result = {"commit": commit, "machine": f"{platform.node()} ({os.cpu_count()} cores)", "load_before": os.getloadavg(),
              "command": "python benchmarks/flash_capture_stages.py" + (" --controls" if a.controls else "")
                         + (" --reuse" if a.reuse else ""),
              "run_commit": json.loads((out / "flash_capture.json").read_text()).get("commit")
              if (out / "flash_capture.json").is_file() else None}
    posed, posed_sim = _camera_errors(out / "run" / "posed", truth)
    result["register"] = posed
    result["mesh"] = {**_mesh_distance(out / "run" / "mesh" / "mesh.ply", posed_sim),
                      "normal_error_deg": _normal_error_deg(out / "run" / "mesh" / "mesh.ply", posed_sim)}
    if (out / "run" / "refine" / "capture.json").is_file():
        refined, refined_sim = _camera_errors(out / "run" / "refine", truth)
        result["refine"] = {**refined, "mesh": _mesh_distance(out / "run" / "refine" / "mesh.obj", refined_sim)}
    if a.controls:
        result["controls"] = _controls(out, truth, a.reuse)
    result["load_after"] = os.getloadavg()
    (out / "flash_capture_stages.json").write_text(json.dumps(result, indent=2, default=float))
    print(json.dumps(result, indent=1, default=float))


if __name__ == "__main__":
    main()
