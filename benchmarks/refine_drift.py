"""How far the photometric refinement moves EXACT cameras and mesh of the synthetic glossy flash capture
(issue 39; JSON): the refinement's bias, by the photo level it compares at and with or without the room's light.

    python benchmarks/refine_drift.py --out DIR [--room-light 0] [--variants default,level0,level2,noshade]

Synthesises ``flash_sphere_resolved`` (72 flash photos of 400 px, no no-flash pairs; ``--room-light`` the room's
irradiance, 0.6 the scene's default, 0 the flash alone) into ``DIR/truth`` (kept between runs), then runs the
refine stage (``texstream refine``'s defaults but for the variant's options) from the true cameras and the true
mesh (its fit atlas) and reports: whether its own rule kept the result (the fitted photos' residual fell), and
against the truth the cameras' pixel error (per photo the median distance, in full-resolution pixels, between
where the true camera and the refined one put the true sphere's points; flash_capture_stages.py), the mesh's
distance to the sphere and the written vertex normals' angle to the sphere's. Exact inputs should stay where they
are: what moves is the stage's bias on this scene.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from flash_capture_stages import _camera_errors, _mesh_distance  # noqa: E402

VARIANTS = {"default": {}, "noshade": {"normal_iterations": 0}, "level0": {"photo_level": 0},
            "level2": {"photo_level": 2}}
"""the refine options of each variant (the rest: RefineConfig's defaults; level 1 is the default's choice here)"""


def _normal_error(mesh_path: Path, sim) -> dict:
    from texstream.geometry.mesh_io import load_mesh

    mesh = load_mesh(mesh_path)
    s, r, t = sim[:3]
    v = s * mesh.vertices.astype(np.float64) @ r.T + t
    n = mesh.vertex_normals() if mesh.normals is None else mesh.normals.astype(np.float64)
    n = n @ r.T
    cos = np.sum(n * v, 1) / (np.linalg.norm(n, axis=1) * np.linalg.norm(v, axis=1))
    angle = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    return {"median": float(np.median(angle)), "p90": float(np.percentile(angle, 90))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="out/refine_drift")
    ap.add_argument("--room-light", type=float, default=0.0)
    ap.add_argument("--variants", default="default,level0,level2,noshade")
    a = ap.parse_args()
    from texstream.capture.capture_json import read_capture
    from texstream.capture.synthetic.flash_capture import (FlashCaptureConfig, fit_geometry,
                                                           synthesize_flash_capture)
    from texstream.geometry.refine import RefineConfig, refine_stage

    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=Path(__file__).parent).stdout.strip()
    out = Path(a.out)
    truth_dir = out / "truth"
    if not (truth_dir / "capture.json").is_file():
        synthesize_flash_capture(truth_dir, FlashCaptureConfig(scene="flash_sphere_resolved", image_size=400,
                                                               room_light=a.room_light, progress=False))
    truth = read_capture(truth_dir)
    geometry = fit_geometry(truth_dir, out / "fit_geometry", "cpu")
    result = {"commit": commit, "machine": f"{platform.node()} ({os.cpu_count()} cores)", "load": os.getloadavg(),
              "command": f"python benchmarks/refine_drift.py --room-light {a.room_light} --variants {a.variants}",
              "variants": {}}
    for name in a.variants.split(","):
        t0 = time.perf_counter()
        refined = out / f"refine_{name}"
        refine_stage(truth_dir, geometry, refined, RefineConfig(**VARIANTS[name]), device="cpu")
        cams, sim = _camera_errors(refined, truth)
        summary = json.loads((refined / "refine.json").read_text())
        result["variants"][name] = {"options": VARIANTS[name], "kept": summary.get("kept"),
                                    "kept_why": summary.get("kept_why"), "resolution": summary.get("resolution"),
                                    **cams, "mesh": _mesh_distance(refined / "mesh.obj", sim),
                                    "normal_error_deg": _normal_error(refined / "mesh.obj", sim),
                                    "seconds": time.perf_counter() - t0}
        print(name, json.dumps(result["variants"][name], default=float), flush=True)
    (out / f"refine_drift_room{a.room_light:g}.json").write_text(json.dumps(result, indent=1, default=float))


if __name__ == "__main__":
    main()
