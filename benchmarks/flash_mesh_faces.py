"""How the photos-only flash capture's mesh loses accuracy: its surface, its normals, or its faces against the atlas's
texels (issue 39; JSON). Run after ``benchmarks/flash_capture.py --out OUT`` (its truth and photos-only run).

    python benchmarks/flash_mesh_faces.py --out OUT [--faces 20000,8000,4000,2000] [--true-faces 2000] [--json PATH]

Every fit is flash_capture_stages.py's (Lafortune, the ambient term, 15 iterations, every 8th photo held out) on the
true cameras and response, each mesh charted by the pipeline's atlas stage at the run's resolution:

- ``recovered``: the photos-only run's mesh (``OUT/run/mesh/mesh.ply``, 20,000 faces) carried into the truth's frame by
  the cameras' similarity, decimated by quadric edge collapse (pymeshlab, as the mesh stage decimates) to each count;
- ``recovered_on_sphere_true_normals``: the same with its vertices put on the true sphere and the sphere's normals:
  its triangulation alone differs from the truth;
- ``recovered_normals_smoothed_R`` (``--smooth-rounds``): its surface as it is, its vertex normals averaged with
  their neighbours' R times;
- ``true_mesh``: the truth's mesh welded and without its UVs (flash_capture.py ``true_mesh_without_uvs``), as it is
  (9,216 faces) and decimated (``true_mesh_N``, its vertices put back on the sphere, the sphere's normals).

Per fit: held-out flash views (pooled, worst), the albedo's median per-texel error, the atlas's size, covered texels
and faces that own no texel.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import time
from pathlib import Path

import numpy as np
from flash_capture import _similarity, _texel_errors, heldout_flash, true_mesh_without_uvs
from flash_capture_stages import _camera_errors
from gitinfo import commit


def _decimated(src: Path, faces: int, dst: Path, on_sphere: bool) -> Path:
    import pymeshlab

    from texstream.geometry.mesh_io import save_mesh
    from texstream.render.mesh import SurfaceMesh

    ms = pymeshlab.MeshSet()
    ms.load_new_mesh(str(src))
    if faces < ms.current_mesh().face_number():
        ms.meshing_decimation_quadric_edge_collapse(targetfacenum=faces, preservenormal=True)
    m = ms.current_mesh()
    v = np.asarray(m.vertex_matrix(), np.float64)
    f = np.asarray(m.face_matrix(), np.int32)
    if on_sphere:
        v = v / np.linalg.norm(v, axis=1, keepdims=True)
        save_mesh(dst, SurfaceMesh(vertices=v, faces=f, normals=v.copy()))
    else:
        save_mesh(dst, SurfaceMesh(vertices=v, faces=f))
    return dst


def _smoothed_normals(src: Path, rounds: int, dst: Path) -> tuple[Path, dict]:
    """(``src`` with its vertex normals averaged with their 1-ring neighbours' ``rounds`` times (the refine stage's
    smoothing), its surface kept; their angle to the true sphere's, median and p90 in degrees)."""
    import dataclasses

    from texstream.geometry.mesh_io import load_mesh, save_mesh
    from texstream.geometry.refine import smoothed_normals, vertex_neighbours

    m = load_mesh(src)
    key = m.weld_key()
    offsets, neighbours = vertex_neighbours(key[m.faces], int(key.max()) + 1)
    first = np.unique(key, return_index=True)[1]
    normals = smoothed_normals(np.asarray(m.vertex_normals())[first], offsets, neighbours, rounds)[key]
    save_mesh(dst, dataclasses.replace(m, normals=normals))
    true = m.vertices / np.linalg.norm(m.vertices, axis=1, keepdims=True)
    ang = np.degrees(np.arccos(np.clip(np.sum(normals * true, axis=1), -1.0, 1.0)))
    return dst, {"median": float(np.median(ang)), "p90": float(np.percentile(ang, 90))}


def _fit(out: Path, mesh: Path, work: Path, name: str, resolution: int) -> dict:
    from texstream.capture.capture_json import flash_fired, read_capture, split_holdout
    from texstream.fit.optim.fitter import FitConfig
    from texstream.fit.stages.stage import FitStageConfig, fit_stage
    from texstream.geometry.atlas import AtlasConfig, atlas_stage

    truth_dir = out / "truth"
    truth = read_capture(truth_dir)
    geometry = work / f"atlas_{name}"
    shutil.rmtree(geometry, ignore_errors=True)
    atlas_stage(mesh, geometry, AtlasConfig(resolution=resolution), device="cpu")
    info = json.loads((geometry / "atlas_info.json").read_text())
    cfg = FitStageConfig(device="cpu", holdout_every=8,
                         fit=FitConfig(model="lafortune", ambient="on", max_iterations=15))
    t0 = time.perf_counter()
    fit_stage(truth_dir, geometry, work / f"fit_{name}", cfg, progress=False)
    seconds = time.perf_counter() - t0
    train_flash = [f for f in split_holdout(truth.frames, 8)[0] if flash_fired(f)]
    texels = _texel_errors(work / f"fit_{name}", truth_dir, _similarity(truth.frames, truth.frames), truth.frames,
                           train_flash)
    held = heldout_flash(work / f"fit_{name}")
    row = {"heldout_flash_pooled_db": held["pooled_psnr_db"], "heldout_flash_worst_db": held["worst_psnr_db"],
           "albedo_rel_error_median": texels["albedo_rel_error"]["median"], "fit_seconds": seconds,
           "atlas": {k: info[k] for k in ("width", "height", "n_faces", "n_covered", "faces_without_texels",
                                           "n_charts")}}
    print(name, json.dumps(row), flush=True)
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", required=True, help="benchmarks/flash_capture.py's output folder")
    ap.add_argument("--faces", default="20000,8000,4000,2000", help="face counts of the decimated recovered mesh")
    ap.add_argument("--true-faces", default="2000", help="face counts of the decimated true mesh (its vertices put "
                                                           "back on the sphere, the sphere's normals)")
    ap.add_argument("--smooth-rounds", default="", help="the recovered mesh with its vertex normals averaged with "
                                                         "their neighbours' this many times (comma-separated)")
    ap.add_argument("--json", default="", help="where to write the results (default: OUT/flash_mesh_faces.json)")
    a = ap.parse_args()
    from texstream.capture.capture_json import read_capture
    from texstream.geometry.align import transform_mesh
    from texstream.geometry.mesh_io import load_mesh, save_mesh

    out = Path(a.out)
    work = out / "mesh_faces"
    work.mkdir(exist_ok=True)
    run = out / "run"
    _, sim = _camera_errors(run / "lights", read_capture(out / "truth"))
    to_truth = np.eye(4)
    to_truth[:3, :3], to_truth[:3, 3] = sim[0] * sim[1], sim[2]
    recovered = work / "recovered_in_truth.ply"
    save_mesh(recovered, transform_mesh(load_mesh(run / "mesh" / "mesh.ply"), to_truth))
    resolution = int(json.loads((run / "atlas" / "atlas_config.json").read_text())["resolution"])
    result = {"command": f"python benchmarks/flash_mesh_faces.py --out OUT --faces {a.faces} "
                         f"--true-faces {a.true_faces} --smooth-rounds {a.smooth_rounds}", "commit": commit(),
              "machine": f"{platform.node()} ({os.cpu_count()} cores)", "atlas_resolution": resolution, "fits": {}}
    true_mesh = true_mesh_without_uvs(out / "truth", out / "true_mesh_no_uvs.ply")
    result["fits"]["true_mesh"] = _fit(out, true_mesh, work, "true_mesh", resolution)
    for faces in (int(x) for x in a.true_faces.split(",") if x):
        name = f"true_mesh_{faces}"
        result["fits"][name] = _fit(out, _decimated(true_mesh, faces, work / f"{name}.ply", True), work, name,
                                    resolution)
    for rounds in (int(x) for x in a.smooth_rounds.split(",") if x):
        name = f"recovered_normals_smoothed_{rounds}"
        mesh, angles = _smoothed_normals(recovered, rounds, work / f"{name}.ply")
        result["fits"][name] = {**_fit(out, mesh, work, name, resolution), "normals_off_sphere_deg": angles}
    for faces in (int(x) for x in a.faces.split(",") if x):
        for on_sphere in (False, True):
            name = f"recovered_{faces}" + ("_on_sphere_true_normals" if on_sphere else "")
            mesh = _decimated(recovered, faces, work / f"{name}.ply", on_sphere)
            result["fits"][name] = _fit(out, mesh, work, name, resolution)
    path = Path(a.json) if a.json else out / "flash_mesh_faces.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(result, indent=1, default=float))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
