#!/usr/bin/env python3
"""Record the CPU's fit that tests/test_fit_devices.py compares CPU and CUDA fits with.

    python scripts/record_cpu_reference.py            # writes tests/data/cpu_reference_fit.npz

Run it on a machine whose Warp has the CPU compiler, after an intended change of the fit's arithmetic (the
CPU test then fails, naming this script), and run ``python -m pytest tests/test_fit_devices.py -k cuda`` on
the GPU machine afterwards. It renders the flat sample on the CPU (24 photos of 32 x 32 pixels, 21 x 21
texels), keeps what the fit reads (photos rounded to float16 to keep the file small: the fit of the
recorded photos is what both devices repeat, so the rounding is part of the input), fits those inputs
with each case of the test, and writes inputs and results in one compressed file of about 140 KB.
"""

from __future__ import annotations

import argparse
import platform
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
SCENE = {"scale": 0.05, "photos": 24, "image_size": 32}


def scene_arrays() -> dict[str, np.ndarray]:
    """The flat sample rendered on the CPU, as the arrays test_fit_devices.recorded_inputs reads."""
    from texstream.capture.synthetic.synth import SynthConfig, render_scene

    sc = render_scene("flat_sample", SynthConfig(progress=False, device="cpu", **SCENE))
    mesh, bake, frames = sc.mesh, sc.bake, sc.frames
    for f in frames:  # what the recording's frames cannot hold
        assert f.intrinsics.is_pinhole and f.light is not None and not f.extra, f.file_path
    intrinsics = [f.intrinsics for f in frames]
    return {"mesh_vertices": mesh.vertices, "mesh_faces": mesh.faces, "mesh_normals": mesh.vertex_normals(),
            "mesh_uvs": mesh.uvs, "bake_width": np.int64(bake.width), "bake_height": np.int64(bake.height),
            "bake_padding": np.int64(bake.padding), **{f"bake_{k}": getattr(bake, k) for k in bake._ARRAYS},
            "frame_R": np.stack([f.R for f in frames]), "frame_t": np.stack([f.t for f in frames]),
            "frame_intrinsics": np.array([[k.width, k.height, k.fx, k.fy, k.cx, k.cy] for k in intrinsics]),
            "frame_light_type": np.array([f.light.type for f in frames]),
            "frame_light_intensity": np.stack([f.light.intensity for f in frames]),
            "frame_light_vector": np.stack([f.light.position if f.light.type == "point" else f.light.direction
                                            for f in frames]),
            "frame_exposure": np.array([f.exposure for f in frames]),
            "frame_saturation": np.array([np.nan if f.saturation is None else f.saturation for f in frames]),
            "photos": np.stack(sc.images).astype(np.float16), "masks": np.stack(sc.masks).astype(bool)}


def commit() -> str:
    done = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                          check=False)
    return done.stdout.strip() or "unknown"


def main(argv: list[str] | None = None) -> int:
    sys.path.insert(0, str(ROOT / "tests"))
    import test_fit_devices as t
    import warp as wp

    from texstream.geometry.mesh_io import write_npz_atomic

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=t.RECORDING, help="the recording (default: %(default)s)")
    args = ap.parse_args(argv)
    arrays = scene_arrays()
    for case in t.CASES:
        res = t.fit_recorded_inputs(arrays, case, "cpu")  # the recorded float16 photos, as the tests fit them
        objective = np.array([r["objective"] for r in res.trace])
        arrays.update({f"{case}_params": res.params, f"{case}_samples": res.samples,
                       f"{case}_objective": objective})
        print(f"{case}: objective {objective[0]:.6g} -> {objective[-1]:.6g}")
    arrays["recorded_with"] = np.array(f"commit {commit()}, warp {wp.config.version}, "
                                       f"numpy {np.__version__}, {platform.machine()}")
    write_npz_atomic(args.out, **arrays)
    print(f"wrote {args.out} ({args.out.stat().st_size // 1024} KB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
