"""Dense meshes from captures that give cameras and nothing else (issue 38, "dense meshes from any posed set").

Two cases, both synthetic with ground truth, both with their masks and SfM points removed (cameras and
photos only):

- ``object``: the ``textured_sphere`` scene made glossy (a Lafortune lobe, a flash beside the lens,
  tests/test_geometry_posed_mesh.py's scene), 24 photos of 192 x 192;
- ``facade``: capture/synthetic/facade.py, a building front with relief and the ground before it, 11
  photos of 640 x 480 on a 70-degree street arc, exposures spread over 2 stops, a fixed sun.

For each: ``make_mesh`` (the ``texstream mesh`` stage) with its defaults, the mesh's distance to the
truth both ways (geometry/mesh_error.py: median and 90th percentile over area samples, as fractions
of the true bounding-box diagonal), face count and time. With ``--run`` the facade also goes through
``texstream run`` twice, every 4th photo held out: once with the true mesh (``--mesh-file
ground_truth/mesh.obj``) and once with the mesh made here (``--mesh-file OUT/facade_mesh/mesh.ply``, so the
atlas and fit are the run's own), and the held-out pooled PSNR of both is reported.

    PYTHONPATH=.pkg python benchmarks/posed_mesh.py --out /tmp/posed --cases object,facade --run

Writes ``OUT/posed_mesh.json``.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

HOLDOUT_TOML = "[fit]\nholdout_every = 4\n"


def _object_capture(root: Path, photos: int, size: int) -> None:
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    from test_geometry_posed_mesh import glossy_sphere_scene, strip_to_cameras
    from texstream.capture.synthetic.synth import SynthConfig, synthesize

    synthesize(glossy_sphere_scene(), root, SynthConfig(photos=photos, image_size=size, progress=False,
                                                        preview=False))
    strip_to_cameras(root)


def _facade_capture(root: Path, width: int, height: int) -> None:
    from texstream.capture.synthetic.facade import FacadeConfig, synthesize_facade

    synthesize_facade(root, FacadeConfig(width=width, height=height))


def _mesh_case(name: str, root: Path, out: Path) -> dict:
    from texstream.geometry.make_mesh import make_mesh
    from texstream.geometry.mesh_error import mesh_error
    from texstream.geometry.mesh_io import load_mesh

    t0 = time.perf_counter()
    res = make_mesh(root, out)
    seconds = time.perf_counter() - t0
    s = res.summary
    mesh = load_mesh(out / "mesh.ply")
    err = mesh_error(mesh, load_mesh(root / "ground_truth" / "mesh.obj"))
    d = s.get("dense", {})
    return {"case": name, "faces": mesh.n_faces, "seconds": round(seconds, 1), "error": err,
            "source": s["source"], "reason": s["reason"], "capture_kind": s.get("capture_kind", {}).get("kind"),
            "triangulated_points": s.get("triangulation", {}).get("points"),
            "triangulation_seconds": s.get("triangulation", {}).get("seconds"),
            "dense": {k: d.get(k) for k in ("used", "masks", "depth_range_from", "points", "mean_fill", "seconds")}}


def _run(capture: Path, mesh_file: Path, out: Path) -> dict:
    """``texstream run`` with a given mesh, every 4th photo held out; its held-out numbers."""
    out.mkdir(parents=True, exist_ok=True)
    toml = out.parent / (out.name + "_config.toml")
    toml.write_text(HOLDOUT_TOML)
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "texstream.pipelines.cli", "run", str(capture), "-o", str(out),
                    "--mesh-file", str(mesh_file), "--config", str(toml), "--no-progress"], check=True)
    fit = json.loads((out / "run.json").read_text())["fit"]
    return {"heldout_pooled_psnr_db": fit["heldout"]["pooled_psnr_db"], "heldout": fit["heldout"],
            "model": fit.get("selection", {}).get("chosen"), "texels": fit.get("texels"),
            "seconds": round(time.perf_counter() - t0, 1)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", required=True, help="work folder (captures, meshes, runs, posed_mesh.json)")
    ap.add_argument("--cases", default="object,facade", help="comma-separated: object, facade")
    ap.add_argument("--run", action="store_true", help="facade: held-out PSNR of texstream run, true vs made mesh")
    ap.add_argument("--object-photos", type=int, default=24)
    ap.add_argument("--object-size", type=int, default=192)
    ap.add_argument("--facade-size", default="640x480", help="WxH")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    results = {"command": " ".join(sys.argv), "cases": []}
    for case in args.cases.split(","):
        root = out / case
        if case == "object":
            _object_capture(root, args.object_photos, args.object_size)
        elif case == "facade":
            w, h = (int(v) for v in args.facade_size.split("x"))
            _facade_capture(root, w, h)
        else:
            raise SystemExit(f"unknown case {case!r}: use object or facade")
        r = _mesh_case(case, root, out / f"{case}_mesh")
        if case == "facade" and args.run:
            true_run = _run(root, root / "ground_truth" / "mesh.obj", out / "facade_run_true")
            made_run = _run(root, out / "facade_mesh" / "mesh.ply", out / "facade_run_made")
            r["run"] = {"true_mesh": true_run, "made_mesh": made_run,
                        "psnr_gap_db": true_run["heldout_pooled_psnr_db"] - made_run["heldout_pooled_psnr_db"]}
        results["cases"].append(r)
        (out / "posed_mesh.json").write_text(json.dumps(results, indent=1))
        e = r["error"]
        print(f"{case}: {r['faces']} faces in {r['seconds']} s; median error made->true "
              f"{100 * e['made_to_true']['median']:.3f}%, true->made {100 * e['true_to_made']['median']:.3f}% of the "
              f"true bounding-box diagonal ({e['scale']:.3g})"
              + (f"; held-out PSNR true mesh {r['run']['true_mesh']['heldout_pooled_psnr_db']:.2f} dB, made mesh "
                 f"{r['run']['made_mesh']['heldout_pooled_psnr_db']:.2f} dB" if "run" in r else ""))
    print(f"wrote {out / 'posed_mesh.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
