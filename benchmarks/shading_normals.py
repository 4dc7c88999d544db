"""Shading normals fitted to the photos (``--shading-normals.mode on``, fit/common/shading_normals.py): where they
help and where they hurt (issue 39; JSON). Run after ``benchmarks/flash_capture.py --out OUT`` (its truth, true
atlas and photos-only run).

    python benchmarks/flash_capture.py --scene flash_sphere_resolved ... --out OUT
    python benchmarks/shading_normals.py --out OUT [--json benchmarks/results/flash_capture_cpu/NAME.json]

The Lafortune fit as flash_capture_stages.py runs it (15 iterations, every 8th photo held out, the ambient term on),
with the shading normals off and on, on the true cameras and response of the synthetic flash capture and on:

- ``true_mesh_turned_normals``: the true mesh with its vertex normals turned at random, vertex by vertex, 2.75 degrees
  median (a scan's surface with a decimated or smoothed mesh's normals);
- ``recovered_mesh_exact_positions``: the photos-only run's mesh carried into the truth's frame (the cameras'
  similarity) with its vertices put on the true sphere and its own normals kept (2.2 degrees off);
- ``recovered_mesh``: the same mesh as it is (its surface about 0.004 off the sphere, the normals 2.2 degrees off),
  each with the pipeline's atlas at the run's resolution;

and ``sphere_room_turned``: the built-in sphere_room (half scale, 24 photos of 128 px, float photos) whose mesh
normals a smooth field turned 3.2 degrees (median), as tests/test_shading_normals.py fits it. Per fit: held-out flash
PSNR (pooled, worst), the albedo's median per-texel error, the vertex normals' angle to the true sphere's (median,
90th percentile) and the seconds.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import time
from pathlib import Path

import numpy as np
from flash_capture import _similarity, _texel_errors, heldout_flash
from flash_capture_stages import _camera_errors
from gitinfo import commit


def _angles(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=1), -1.0, 1.0)))


def _sphere_normal_error(mesh_path: Path) -> dict:
    """The mesh's stored vertex normals against the unit sphere's at the vertex (the truth's frame)."""
    from texstream.geometry.mesh_io import load_mesh

    mesh = load_mesh(mesh_path)
    true = mesh.vertices / np.linalg.norm(mesh.vertices, axis=1, keepdims=True)
    ang = _angles(mesh.vertex_normals(), true)
    return {"median": float(np.median(ang)), "p90": float(np.percentile(ang, 90))}


def _geometries(out: Path, work: Path) -> dict:
    """The three geometry folders (module doc), made once."""
    from texstream.capture.capture_json import read_capture
    from texstream.capture.synthetic.turned_normals import geometry_with_normals, random_turn
    from texstream.geometry.align import transform_mesh
    from texstream.geometry.atlas import AtlasConfig, atlas_stage
    from texstream.geometry.mesh_io import load_mesh, save_mesh

    truth_dir, run = out / "truth", out / "run"
    geo = {name: work / name for name in ("true_mesh_turned_normals", "recovered_mesh_exact_positions",
                                          "recovered_mesh")}
    if not (geo["true_mesh_turned_normals"] / "bake.npz").is_file():
        # about the recovered mesh's error (2.2 degrees median), the random field a little stronger: 2.75
        geometry_with_normals(out / "fit_geometry", random_turn(load_mesh(out / "fit_geometry" / "mesh.obj"), 2.75),
                              geo["true_mesh_turned_normals"])
    truth = read_capture(truth_dir)
    _, sim = _camera_errors(run / "lights", truth)
    to_truth = np.eye(4)
    to_truth[:3, :3], to_truth[:3, 3] = sim[0] * sim[1], sim[2]
    resolution = int(json.loads((run / "atlas" / "atlas_config.json").read_text())["resolution"])
    recovered = transform_mesh(load_mesh(run / "mesh" / "mesh.ply"), to_truth)
    exact = dataclasses.replace(recovered, normals=np.asarray(recovered.vertex_normals(), np.float64).copy(),
                                vertices=recovered.vertices / np.linalg.norm(recovered.vertices, axis=1,
                                                                             keepdims=True))
    for name, mesh in (("recovered_mesh", recovered), ("recovered_mesh_exact_positions", exact)):
        if not (geo[name] / "bake.npz").is_file():
            save_mesh(work / f"{name}.ply", mesh)
            atlas_stage(work / f"{name}.ply", geo[name], AtlasConfig(resolution=resolution), device="cpu")
    return geo


def _fit_flash(out: Path, geometry: Path, model: Path, mode: str) -> dict:
    from texstream.capture.capture_json import flash_fired, read_capture, split_holdout
    from texstream.fit.common.shading_normals import NormalsConfig
    from texstream.fit.optim.fitter import FitConfig
    from texstream.fit.stages.stage import FitStageConfig, fit_stage

    truth_dir = out / "truth"
    truth = read_capture(truth_dir)
    cfg = FitStageConfig(device="cpu", holdout_every=8, shading_normals=NormalsConfig(mode=mode),
                         fit=FitConfig(model="lafortune", ambient="on", max_iterations=15))
    t0 = time.perf_counter()
    fit_stage(truth_dir, geometry, model, cfg, progress=False)
    seconds = time.perf_counter() - t0
    train_flash = [f for f in split_holdout(truth.frames, 8)[0] if flash_fired(f)]
    texels = _texel_errors(model, truth_dir, _similarity(truth.frames, truth.frames), truth.frames, train_flash)
    held = heldout_flash(model)
    manifest = json.loads((model / "model.json").read_text())
    return {"heldout_flash_pooled_db": held["pooled_psnr_db"], "heldout_flash_worst_db": held["worst_psnr_db"],
            "albedo_rel_error_median": texels["albedo_rel_error"]["median"],
            "normal_error_deg": _sphere_normal_error(model / "mesh.obj"), "seconds": seconds,
            "shading_normals": manifest.get("shading_normals")}


def _sphere_room(work: Path) -> dict:
    """tests/test_shading_normals.py's scene and fits, off and on."""
    from texstream.capture.synthetic.synth import SynthConfig, synthesize
    from texstream.capture.synthetic.turned_normals import geometry_with_normals, smooth_turn
    from texstream.fit.common.shading_normals import NormalsConfig
    from texstream.fit.models.materials import MaterialConfig
    from texstream.fit.optim.fitter import FitConfig
    from texstream.fit.stages.stage import FitStageConfig, fit_stage
    from texstream.geometry.mesh_io import load_mesh

    cap, geometry = work / "sphere_room", work / "sphere_room_turned"
    if not (geometry / "bake.npz").is_file():
        synthesize("sphere_room", cap, SynthConfig(scale=0.5, photos=24, image_size=128, progress=False,
                                                   preview=False, device="cpu"))
        geometry_with_normals(cap / "ground_truth", smooth_turn(load_mesh(cap / "ground_truth" / "mesh.obj"), 5.0),
                              geometry)
    true_normals = load_mesh(cap / "ground_truth" / "mesh.obj").vertex_normals()
    rows = {}
    for mode in ("off", "on"):
        cfg = FitStageConfig(device="cpu", holdout_every=4, renders=0, traced_polish=0,
                             materials=MaterialConfig(mode="off"), fit=FitConfig(model="lafortune", ambient="on"),
                             shading_normals=NormalsConfig(mode=mode))
        t0 = time.perf_counter()
        res = fit_stage(cap, geometry, work / f"sphere_room_{mode}", cfg, progress=False)
        ang = _angles(load_mesh(work / f"sphere_room_{mode}" / "mesh.obj").vertex_normals(), true_normals)
        rows[mode] = {"heldout_pooled_db": res.summary["heldout"]["pooled_psnr_db"],
                      "heldout_worst_db": res.summary["heldout"]["worst_psnr_db"],
                      "normal_error_deg": {"median": float(np.median(ang)), "p90": float(np.percentile(ang, 90))},
                      "seconds": time.perf_counter() - t0}
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", required=True, help="benchmarks/flash_capture.py's output folder")
    ap.add_argument("--json", default="", help="where to write the results (default: OUT/shading_normals.json)")
    a = ap.parse_args()
    out = Path(a.out)
    work = out / "shading_normals"
    work.mkdir(exist_ok=True)
    result = {"command": "python benchmarks/shading_normals.py --out OUT", "commit": commit(),
              "machine": platform.node(), "cpu_count": os.cpu_count(), "fits": {}}
    for name, geometry in _geometries(out, work).items():
        result["fits"][name] = {mode: _fit_flash(out, geometry, work / f"fit_{name}_{mode}", mode)
                                for mode in ("off", "on")}
        print(name, {m: (round(r["heldout_flash_pooled_db"], 2), round(r["albedo_rel_error_median"], 4),
                         round(r["normal_error_deg"]["median"], 2)) for m, r in result["fits"][name].items()},
              flush=True)
    result["fits"]["sphere_room_turned"] = _sphere_room(work)
    print("sphere_room_turned", result["fits"]["sphere_room_turned"], flush=True)
    path = Path(a.json) if a.json else out / "shading_normals.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(result, indent=1, default=float))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
