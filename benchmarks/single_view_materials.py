"""Single-view fits with and without shared materials, and the model choice's pick (docs/accuracy.md, "Single-view
fits: the model choice and shared materials").

A glossy hemisphere of two materials (left: rho_s 1.2, n 20; right: rho_s 0.5, n 6) seen by one camera under
directional lights 5-60 degrees off the view axis, rendered in numpy with the Lafortune convention of
render/shading.py: pixels further than ~30 degrees from facing the camera never see their highlight in any
photo (their mirror direction lies beyond the lights). Every ``--holdout-every``-th photo is held out; the
Lafortune model is fitted with materials off and auto, then ``--model auto`` (the candidates judged on the
held-out photos). Prints one JSON object.

    python benchmarks/single_view_materials.py --out /tmp/sv --lights 64 --holdout-every 8
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path

import numpy as np

from texstream.capture.capture_json import Capture, Frame, Intrinsics, Light, write_capture
from texstream.capture.imageio import write_image
from texstream.fit.models.materials import MaterialConfig
from texstream.fit.optim.fitter import FitConfig
from texstream.fit.stages.single_view import SingleViewConfig, fit_single_view_stage


def write_scene(folder: Path, size: int, n_lights: int) -> Path:
    """The capture folder (float EXR photos, camera = world frame) and its normals.npy (OpenGL camera axes)."""
    f = 5.0 * size
    intr = Intrinsics(size, size, f, f, size / 2, size / 2)
    ys, xs = np.mgrid[0:size, 0:size] + 0.5
    a, b = (xs - size / 2) / (0.45 * size), (ys - size / 2) / (0.45 * size)
    r2 = a * a + b * b
    inside = r2 < 0.97
    n = np.stack([a, b, -np.sqrt(np.clip(1 - r2, 0, None))], -1)
    n[~inside] = [0.0, 0.0, -1.0]
    ray = np.stack([(xs - intr.cx) / f, (ys - intr.cy) / f, np.ones_like(xs)], -1)
    v = -ray / np.linalg.norm(ray, axis=-1, keepdims=True)
    left = (a < 0)[..., None]
    rho_d = np.stack([0.10 + 0.05 * (a + 1), 0.20 - 0.04 * (b + 1), 0.15 + 0.02 * np.sin(3 * a)], -1)
    rho_s = np.where(left, [1.2, 1.1, 1.0], [0.5, 0.5, 0.45])
    nexp = np.where(left[..., 0], 20.0, 6.0)
    cz = 0.8
    k = np.arange(n_lights) + 0.5
    cos_t = 1 - (k / n_lights) * (1 - np.cos(np.deg2rad(60)))  # cosine-uniform over 0-60, lights from 5 on
    theta = np.maximum(np.arccos(cos_t), np.deg2rad(5))
    phi = k * np.pi * (3 - np.sqrt(5))  # golden angle
    to_light = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), -np.cos(theta)], -1)
    (folder / "images").mkdir(parents=True)
    frames = []
    for i, dl in enumerate(to_light):
        cos_i = n @ dl
        uz, vz, uv = cos_i, np.sum(n * v, -1), v @ dl
        s = -(uv - uz * vz) + cz * uz * vz
        lobe = np.where(s > 0, np.exp(np.minimum(nexp * np.log(np.maximum(s, 1e-30)), 30.0)), 0.0)
        img = (2.0 * np.clip(cos_i, 0, None))[..., None] * (rho_d + rho_s * lobe[..., None])
        write_image(folder / "images" / f"{i:03d}.exr", np.where(inside[..., None], img, 0.0).astype(np.float32))
        frames.append(Frame(f"images/{i:03d}.exr", np.eye(3), np.zeros(3), intr, light=Light.directional(-dl, [2.0] * 3)))
    write_capture(Capture(folder, frames))
    np.save(folder / "normals.npy", (np.where(inside[..., None], n, 0.0) * [1.0, -1.0, -1.0]).astype(np.float32))
    return folder / "normals.npy"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--lights", type=int, default=64)
    ap.add_argument("--holdout-every", type=int, default=8)
    ap.add_argument("--iterations", type=int, default=60)
    args = ap.parse_args()
    shutil.rmtree(args.out, ignore_errors=True)
    normals = write_scene(args.out / "cap", args.size, args.lights)
    rows = {}
    for name, model, mode in (("lafortune, materials off", "lafortune", "off"),
                              ("lafortune, materials auto", "lafortune", "auto"), ("model auto", "auto", "auto")):
        cfg = SingleViewConfig(renders=0, holdout_every=args.holdout_every, materials=MaterialConfig(mode=mode),
                               fit=FitConfig(model=model, optimizer="lm", max_iterations=args.iterations))
        t0 = time.perf_counter()
        s = fit_single_view_stage(args.out / "cap", normals, args.out / name.replace(", ", "_").replace(" ", "_"),
                                  cfg, progress=False).summary
        rows[name] = {"heldout_pooled_db": s["heldout"]["pooled_psnr_db"], "heldout_worst_db": s["heldout"]["worst_psnr_db"],
                      "materials": (s.get("materials") or {}).get("reason"),
                      "selection": (s.get("selection") or {}).get("reason"), "seconds": time.perf_counter() - t0}
    print(json.dumps({"size": args.size, "lights": args.lights, "holdout_every": args.holdout_every,
                      "iterations": args.iterations, "fits": rows}, indent=1))


if __name__ == "__main__":
    main()
