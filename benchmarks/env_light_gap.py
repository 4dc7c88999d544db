"""The env_diffuse model's relighting gap on the ornament (issue 42): the light estimated with the albedo vs given.

    python benchmarks/env_light_gap.py WORK [--out result.json] [--env.OPTION VALUE ...]

The scene, the cheapest that has the ornament's albedo variation: ``synth ornament --scale 0.1`` (its cameras,
masks and atlas; 176 photos of 136 px), every photo re-rendered as a Lambertian object (albedo pi x the truth's
rho_d, clipped to 1, with its per-material gradients) under an order-2 SH light L1 with 1024-ray visibility;
capture.json without lights. ``texstream fit --model env_diffuse`` then runs twice on it (the light estimated;
``--env.light L1``), and both models are relit (``texstream relight``) under a second light L2 from 24 views at
another azimuth, scored against renders of the truth there: masked PSNR (peak: the truth renders' maximum), the
estimate's gauge (scale and colour, which no photo under one light can tell) fixed from the truth (``--env.scale
light_mean --env.scale-value`` the truth's mean radiance, ``--env.white light``: the truth's mean is grey).
Also: the light's relative error, the albedo's median relative error, the fits' times. Extra arguments go to the
estimated fit (``--env.material-weight-power 0`` ...). A few minutes on the 2-core CPU.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np

from gitinfo import commit

MEAN_RADIANCE = 0.8  # the true lights' mean radiance over the sphere (grey): the scale gauge given to the fit


def sh_light(seed: int) -> np.ndarray:
    """(9, 3) a physical SH light: grey mean, coloured directional bands 1 and 2 (tests/test_fit_env_diffuse.py's)."""
    from texstream.render import sh

    rng = np.random.default_rng(seed)
    light = np.zeros((9, 3))
    light[0] = MEAN_RADIANCE / sh.sh9_basis(np.array([0.0, 0.0, 1.0]))[0]
    light[1:4] = rng.normal(scale=0.3, size=(3, 3)) * light[0, 0]
    light[4:] = rng.normal(scale=0.08, size=(5, 3)) * light[0, 0]
    assert sh.latlong_from_sh(light, 32, 64).min() > 0.05  # no negative radiance anywhere
    return light


def render_capture(folder: Path, light, albedo, tgrid, mesh, device: str = "cpu") -> None:
    """Every photo of ``folder`` replaced by the Lambertian render under ``light``; capture.json without lights."""
    from texstream.capture.capture_json import read_capture, write_capture
    from texstream.capture.imageio import write_image
    from texstream.fit.models.env_diffuse.model import EnvDiffuseRenderer

    cap = read_capture(folder)
    renderer = EnvDiffuseRenderer(mesh, albedo, tgrid, light, device=device)
    for f in cap.frames:
        write_image(folder / f.file_path, renderer.render(f)[0], bits=32)
        f.light = None
    write_capture(cap, folder)


def make_scene(work: Path, device: str = "cpu") -> dict:
    from texstream.capture.synthetic.synth import SynthConfig, load_ground_truth, synthesize
    from texstream.fit.models.env_diffuse.light_file import write_light_json
    from texstream.fit.models.env_diffuse.model import transfer_grid
    from texstream.geometry.sh_transfer import sh_transfer

    t0 = time.perf_counter()
    cap, relit = work / "capture", work / "relit_truth"
    for d in (cap, relit):
        shutil.rmtree(d, ignore_errors=True)
    synthesize("ornament", cap, SynthConfig(scale=0.1, progress=False, device=device))
    synthesize("ornament", relit, SynthConfig(scale=0.1, photos=24, azimuth_offset=7.0, progress=False,
                                                   device=device))
    mesh, params, _, bake, _ = load_ground_truth(cap)
    mesh = mesh.with_normals()
    idx = np.nonzero(bake.covered.reshape(-1))[0]
    pos, nrm = bake.position.reshape(-1, 3)[idx], bake.normal.reshape(-1, 3)[idx]
    albedo = np.clip(np.pi * params[..., :3].astype(np.float64), 0.0, 1.0)
    tgrid = transfer_grid(bake, idx, sh_transfer(mesh.vertices, mesh.faces, pos, nrm, samples=1024,
                                                       device=device))
    lights = {"L1": sh_light(0), "L2": sh_light(7)}
    render_capture(cap, lights["L1"], albedo, tgrid, mesh, device)
    render_capture(relit, lights["L2"], albedo, tgrid, mesh, device)
    for name, light in lights.items():
        write_light_json(work / f"{name}.json", light)
    return {"albedo": albedo, "bake": bake, "lights": lights, "seconds": time.perf_counter() - t0}


def relit_psnr(renders: Path, truth: Path) -> float:
    from texstream.capture.capture_json import read_capture
    from texstream.capture.imageio import read_image

    se, n, peak = 0.0, 0, 0.0
    for f in read_capture(truth).frames:
        a, b = read_image(renders / f"{f.name}.exr"), read_image(truth / f.file_path)
        m = read_image(truth / f.mask_path, channels=1)[..., 0] > 0.5
        se += float(((a - b) ** 2)[m].sum())
        n += int(m.sum()) * 3
        peak = max(peak, float(b.max()))
    return float(10.0 * np.log10(peak ** 2 / (se / n)))


def fit_and_score(work: Path, scene: dict, name: str, extra: list[str], device: str) -> dict:
    from texstream.capture.imageio import read_image
    from texstream.pipelines.cli import main

    model, renders = work / f"model_{name}", work / f"relit_{name}"
    t0 = time.perf_counter()
    assert main(["fit", str(work / "capture"), "--mesh", str(work / "capture" / "ground_truth"), "-o", str(model),
                 "--model", "env_diffuse", "--device", device, "--env.directions", "256", "--env.scale",
                 "light_mean", "--env.scale-value", str(MEAN_RADIANCE), "--env.white", "light", *extra]) == 0
    fit_s = time.perf_counter() - t0
    assert main(["relight", str(model), "--env", str(work / "L2.json"), "--capture", str(work / "relit_truth"),
                 "--out", str(renders), "--device", device]) == 0
    manifest = json.loads((model / "model.json").read_text())
    light, truth_light = np.array(manifest["light"]["sh"]), scene["lights"]["L1"]
    cov = np.asarray(scene["bake"].covered, bool)
    a, t = read_image(model / "albedo.exr")[cov], scene["albedo"][cov]
    return {"relit_psnr_db": relit_psnr(renders, work / "relit_truth"),
            "light_rel_error": float(np.linalg.norm(light - truth_light) / np.linalg.norm(truth_light)),
            "albedo_median_rel_error": float(np.median(np.abs(a - t) / np.maximum(t, 1e-3))),
            "materials": manifest["light"]["gauge"].get("materials"), "fit_s": fit_s,
            "timings_s": manifest["timings_s"], "args": extra}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("work", type=Path)
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--reuse-scene", action="store_true", help="WORK already holds the scene: only fit and score")
    ap.add_argument("--scene-only", action="store_true", help="only make the scene (WORK/capture, L1.json, ...)")
    ap.add_argument("--device", default="cpu", help="the device of the scene's renders, the fits and the relights")
    a, extra = ap.parse_known_args()
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    a.work.mkdir(parents=True, exist_ok=True)
    if a.reuse_scene:
        from texstream.capture.synthetic.synth import load_ground_truth
        from texstream.fit.models.env_diffuse.light_file import read_light

        _, params, _, bake, _ = load_ground_truth(a.work / "capture")
        scene = {"albedo": np.clip(np.pi * params[..., :3].astype(np.float64), 0.0, 1.0), "bake": bake,
                 "lights": {n: read_light(a.work / f"{n}.json") for n in ("L1", "L2")}, "seconds": 0.0}
    else:
        scene = make_scene(a.work, a.device)
        if a.scene_only:
            print(f"scene in {a.work} ({scene['seconds']:.1f} s)")
            return
    given = fit_and_score(a.work, scene, "given", ["--env.light", str(a.work / "L1.json")], a.device)
    estimated = fit_and_score(a.work, scene, "estimated", extra, a.device)
    result = {"scene": "ornament --scale 0.1, Lambertian under SH light L1 (seed 0), 1024-ray visibility; relit "
                       "under L2 (seed 7) from 24 views at +7 deg azimuth",
              "scene_s": scene["seconds"], "given_light": given, "estimated_light": estimated,
              "gap_db": given["relit_psnr_db"] - estimated["relit_psnr_db"], "device": a.device, "commit": commit(),
              "argv": sys.argv[1:]}
    print(json.dumps({k: result[k] for k in ("gap_db",)} | {
        n: {k: result[n][k] for k in ("relit_psnr_db", "light_rel_error", "albedo_median_rel_error")}
        for n in ("given_light", "estimated_light")}, indent=1))
    if a.out:
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
