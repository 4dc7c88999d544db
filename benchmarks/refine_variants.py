"""Variants of the refinement on the photos-only sphere (JSON lines): run after ``benchmarks/refine_limits.py --out
OUT``, whose folders it reuses.

    python benchmarks/refine_variants.py --out out/photos_only mesh '{"iterations": 24, "normal_smoothing": "0"}'
    python benchmarks/refine_variants.py --out out/photos_only normals 0,5,20,60
    python benchmarks/refine_variants.py --out out/photos_only run '{}'
    python benchmarks/refine_variants.py --out out/photos_only normal_errors -

* ``mesh OPTIONS``: the true cameras with the run's mesh (refine_limits' ``atlas_registered_in_truth``), the mesh
  refined with these RefineConfig options (cameras held), then the diffuse held-out fit;
* ``normals ROUNDS``: the refined mesh of refine_limits' ``true_cameras_registered_mesh`` case with its vertex
  normals averaged over 1-ring neighbours this many times (``geometry/refine.py`` ``smoothed_normals``), re-baked,
  then the same fit, per number of rounds;
* ``run OPTIONS``: the run's registered cameras and mesh refined with these options, then the same fit;
* ``shading OPTIONS``: refine_limits' ``registered`` and ``true_cameras_registered_mesh`` refinements and the
  true cameras and mesh taken as they are (cameras and mesh held) and only their shading normals made with
  these options, then the same fit (``SHADING_CASES=registered,...`` in the environment: only those);
* ``truth_swap PARTS``: the refined meshes of refine_limits' ``true_cameras_registered_mesh`` (true frame) and
  ``registered`` (the run's frame, the true sphere mapped into it by the Sim3 of the camera centres) with the
  true sphere's normals (``normals``: radial, positions kept), its positions (``positions``: each vertex moved
  radially onto the sphere, its normals kept) or both (``both``), re-baked, then the same fit: what the mesh's
  normals and positions each cost (comma-separated parts);
* ``normal_errors``: the angle between each mesh's vertex normals and the true sphere's (radial) normals, median
  and 90th percentile, for the true mesh, the run's mesh, its refinement (true cameras) and the ``normals`` meshes
  made so far.

Each result is printed and appended to ``OUT/refine_variants.jsonl`` with the machine and commit.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import shutil
import subprocess
from pathlib import Path


def smoothed_atlas(src: Path, out: Path, rounds: int) -> Path:
    import numpy as np

    from texstream.geometry.bake import TexelBake, bake_texels
    from texstream.geometry.mesh_io import load_mesh, save_mesh
    from texstream.geometry.refine import smoothed_normals, vertex_neighbours, weld_vertices, welded_normals

    mesh = load_mesh(src / "mesh.obj")
    bake = TexelBake.load(src / "bake.npz")
    weld, welded = weld_vertices(mesh)
    faces = weld[np.asarray(mesh.faces)]
    normals = smoothed_normals(welded_normals(welded, faces), *vertex_neighbours(faces, len(welded)), rounds)
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    moved = dataclasses.replace(mesh, normals=normals[weld])
    save_mesh(out / "mesh.obj", moved)
    bake_texels(load_mesh(out / "mesh.obj"), bake.width, bake.height, device="cpu", padding=bake.padding).save(
        out / "bake.npz")
    if (src / "seams.npz").exists():
        shutil.copy2(src / "seams.npz", out / "seams.npz")
    return out


def swapped_atlas(src: Path, out: Path, centre, radius: float, part: str) -> Path:
    """``src``'s atlas folder with the true sphere's normals, positions or both (see the module), re-baked."""
    import numpy as np

    from texstream.geometry.bake import TexelBake, bake_texels
    from texstream.geometry.mesh_io import load_mesh, save_mesh

    mesh = load_mesh(src / "mesh.obj")
    bake = TexelBake.load(src / "bake.npz")
    radial = mesh.vertices - centre
    radial /= np.linalg.norm(radial, axis=1, keepdims=True)
    vertices = centre + radius * radial if part in ("positions", "both") else mesh.vertices
    normals = radial if part in ("normals", "both") else mesh.vertex_normals()
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    save_mesh(out / "mesh.obj", dataclasses.replace(mesh, vertices=vertices, normals=normals))
    moved = load_mesh(out / "mesh.obj")
    bake_texels(moved, bake.width, bake.height, device="cpu", padding=bake.padding).save(out / "bake.npz")
    if (src / "seams.npz").exists():
        shutil.copy2(src / "seams.npz", out / "seams.npz")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="out/photos_only")
    ap.add_argument("mode", choices=("mesh", "normals", "run", "shading", "truth_swap", "normal_errors"))
    ap.add_argument("arg", help="RefineConfig options as JSON (mesh, run, shading), comma-separated rounds "
                                "(normals) or parts (truth_swap: normals, positions, both)")
    args = ap.parse_args()

    import warp as wp

    from refine_limits import fit_case, refine_with as refine_case

    wp.config.quiet = True
    out = Path(args.out)
    work = out / "refine_limits"
    rows = []
    if args.mode == "normal_errors":
        import numpy as np

        from texstream.geometry.mesh_io import load_mesh

        truth = load_mesh(out / "truth" / "ground_truth" / "mesh.obj")
        centre = 0.5 * (truth.vertices.min(axis=0) + truth.vertices.max(axis=0))  # the mean leans to the seam
        meshes = {"true mesh": out / "truth" / "ground_truth", "run's mesh": work / "atlas_registered_in_truth",
                  "refined (true cameras)": work / "true_cameras_registered_mesh",
                  **{f"refined, {p.name.split('_')[1]} rounds": p for p in sorted(work.glob("normals_*"))
                     if p.is_dir() and not p.name.endswith("_fit")}}
        for name, folder in meshes.items():
            m = load_mesh(folder / "mesh.obj")
            radial = m.vertices - centre
            radial /= np.linalg.norm(radial, axis=1, keepdims=True)
            deg = np.degrees(np.arccos(np.clip(np.sum(m.vertex_normals() * radial, axis=1), -1.0, 1.0)))
            rows.append({"mode": "normal_errors", "mesh": name, "median_deg": float(np.median(deg)),
                         "p90_deg": float(np.percentile(deg, 90))})
    elif args.mode == "normals":
        for rounds in [int(x) for x in args.arg.split(",")]:
            atlas = smoothed_atlas(work / "true_cameras_registered_mesh", work / f"normals_{rounds}", rounds)
            rows.append({"mode": "normals", "rounds": rounds,
                         **fit_case(work / "true_cameras_registered_mesh", atlas, Path(str(atlas) + "_fit"))})
    elif args.mode == "truth_swap":
        import numpy as np

        from photos_only_diagnose import sim3_sfm_to_truth
        from texstream.capture.capture_json import read_capture
        from texstream.geometry.mesh_io import load_mesh

        s, r, t, _ = sim3_sfm_to_truth(read_capture(out / "run" / "posed"), read_capture(out / "truth"))
        truth_mesh = load_mesh(out / "truth" / "ground_truth" / "mesh.obj")
        centre = 0.5 * (truth_mesh.vertices.min(axis=0) + truth_mesh.vertices.max(axis=0))
        radius = float(np.linalg.norm(truth_mesh.vertices - centre, axis=1).mean())
        frames = {"true_cameras_registered_mesh": (centre, radius),
                  "registered": (r.T @ (centre - t) / s, radius / s)}
        for part in args.arg.split(","):
            for case, (c, rad) in frames.items():
                atlas = swapped_atlas(work / case, work / f"swap_{case}_{part}", c, rad, part)
                rows.append({"mode": "truth_swap", "case": case, "part": part,
                             **fit_case(work / case, atlas, Path(str(atlas) + "_fit"))})
    elif args.mode == "shading":
        options = json.loads(args.arg)
        tag = "_".join(f"{k}{v}" for k, v in sorted(options.items())) or "default"
        starts = {"registered": (work / "registered", work / "registered"),
                  "true_cameras_registered_mesh": (work / "true_cameras_registered_mesh",) * 2,
                  "truth": (out / "truth", out / "truth" / "ground_truth")}
        for case in [c for c in os.environ.get("SHADING_CASES", ",".join(starts)).split(",") if c]:
            res = refine_case(*starts[case], work / f"shading_{case}_{tag}", cameras=False, mesh=False,
                              iterations=1, blur="0.5", **options)
            rows.append({"mode": "shading", "case": case, **res})
    else:
        options = json.loads(args.arg)
        tag = "_".join(f"{k}{v}" for k, v in sorted(options.items())) or "default"
        if args.mode == "mesh":
            res = refine_case(out / "truth", work / "atlas_registered_in_truth", work / f"mesh_{tag}",
                              cameras=False, **options)
        else:
            res = refine_case(out / "run" / "posed", out / "run" / "atlas", work / f"run_{tag}", **options)
        rows.append({"mode": args.mode, **res})
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=Path(__file__).parent).stdout.strip()
    with open(out / "refine_variants.jsonl", "a") as f:
        for r in rows:
            r.update(machine=f"{platform.node()} ({os.cpu_count()} cores)", commit=commit)
            f.write(json.dumps(r) + "\n")
            print(json.dumps({k: r[k] for k in r if k in ("mode", "rounds", "options", "pooled_psnr_db",
                                                         "worst_psnr_db", "training_psnr_db", "mesh", "case",
                                                         "part", "median_deg", "p90_deg")}))


if __name__ == "__main__":
    main()
