"""The room's light on the synthetic flash capture with the TRUE cameras, mesh and response: the Lafortune fit with
``--ambient`` off, on (a free per-texel ambient radiance) and room (one global SH room light lighting the same
albedo, fit/models/per_texel/room_light.py); albedo error against the truth, held-out PSNR (issue 39; JSON).

    python benchmarks/flash_room_light.py --out out/flash_room [--scene flash_sphere|flash_sphere_resolved]
        [--photos 0] [--image-size 400] [--iterations 15] [--modes off,on,room] [--model lafortune] [--reuse]
        [--no-flash-pairs]

The capture is benchmarks/flash_capture.py's (``texstream synth flash_capture``: a glossy textured sphere, a flash
at each camera, the room's light E (1 + a (2 s - 1)) along z, which on a sphere is an order-1 SH irradiance);
each fit is ``fit_stage`` on the truth's capture.json and ground-truth mesh, every 8th photo held out. With
``--no-flash-pairs`` every camera also takes a photo with the flash off (``texstream synth flash_capture
--no-flash-pairs``; the capture in ``OUT/truth_pairs``): with 24 photos the held-out flash photos are those held out
without pairs, plus their pairs; ``heldout_flash`` pools the flash photos alone, which compares with and without.
The albedo error is also given on the texels that 4 or more training flash photos face (``albedo_rel_error_seen_4``:
the view's cosine above 0.1, a convex sphere hiding nothing else), and broken down by what limits it
(``albedo_breakdown``): the true albedo's contrast to its 8 atlas neighbours (the value noise changes at the
texel's scale in flash_sphere, whose photos give about one pixel a texel), the fitted and true albedos both averaged over 3x3 and
5x5 texels (the error at the photos' resolution), whether a training flash photo saw the texel's highlight (its
true lobe at 10% of its peak or more: a lobe seen once is emptied and the albedo takes its light), how many training
flash photos face it, and its normal's elevation. ``--score-only`` scores OUT's fits again without fitting
(``OUT/flash_room_light_<model>[_resolved][_pairs]_scored.json``, no times). Writes
``OUT/flash_room_light_<model>[_resolved][_pairs].json``. ``--scene flash_sphere_resolved`` is the capture sampled as
the issue asks (72 photos, a 160x80 atlas, band-limited noise: capture/synthetic/flash_capture.py's module doc; its
folders end in ``_resolved``); ``constrained`` gives the parameters against docs/accuracy.md's per-texel bounds on
the texels 4+ training flash photos face and 2+ show the highlight of (flash_capture.py's ``CONSTRAINED``).
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
from flash_capture import _facing_counts, _stats, _texel_errors  # noqa: E402  (the benchmark's albedo comparison)


def _box_mean(a: np.ndarray, covered: np.ndarray, radius: int) -> np.ndarray:
    """(H, W, C) the mean of ``a`` over the covered texels of each texel's (2 radius + 1)^2 atlas box."""
    total, count = np.zeros_like(a, np.float64), np.zeros(covered.shape)
    masked = np.where(covered[..., None], a, 0.0)
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            total += np.roll(masked, (dy, dx), (0, 1))
            count += np.roll(covered, (dy, dx), (0, 1))
    return total / np.maximum(count, 1)[..., None]


def albedo_breakdown(fit_dir: Path, truth_dir: Path, train_flash: list) -> dict:
    """The per-texel albedo error (the largest channel's relative error) split by what limits it (module doc)."""
    from texstream.capture.imageio import read_image
    from texstream.capture.synthetic.synth import load_ground_truth
    from texstream.fit.diagnostics.accuracy import highlight_counts
    from texstream.fit.stages.stage import load_model

    _, truth, tlay, bake, _ = load_ground_truth(truth_dir)
    _, grid, _, _ = load_model(fit_dir)
    seen = bake.covered & (read_image(fit_dir / "seen.png", channels=3)[..., 0] > 0.5)
    rho, fit = truth[..., 0:3].astype(np.float64), grid[..., 0:3].astype(np.float64)
    err = np.abs(fit / np.where(bake.covered[..., None], rho, 1.0) - 1.0).max(axis=2)
    lum = np.where(bake.covered, rho.max(axis=2), np.nan)
    contrast = np.zeros(lum.shape)
    for dy, dx in [(dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1) if dy or dx]:
        contrast = np.fmax(contrast, np.abs(np.roll(lum, (dy, dx), (0, 1)) / lum - 1.0))
    pos, nrm = bake.position[seen].astype(np.float64), bake.normal[seen].astype(np.float64)
    highlight = np.zeros(err.shape, np.int64)
    highlight[seen] = highlight_counts(train_flash, pos, nrm, truth[seen], tlay.lobe_offset(0))
    facing = np.zeros(err.shape, np.int64)
    facing[seen] = _facing_counts(train_flash, pos, nrm)
    out = {"all": _stats(err[seen])}
    for radius in (1, 2):
        boxed = np.abs(_box_mean(fit, bake.covered, radius) / _box_mean(rho, bake.covered, radius) - 1.0).max(axis=2)
        out[f"box_{2 * radius + 1}x{2 * radius + 1}"] = _stats(boxed[seen])
    for lo, hi in ((0.0, 0.05), (0.05, 0.15), (0.15, np.inf)):
        out[f"contrast_{lo:g}_to_{hi:g}"] = _stats(err[seen & (contrast >= lo) & (contrast < hi)])
    signed = (fit / np.where(bake.covered[..., None], rho, 1.0) - 1.0).mean(axis=2)
    for name, m in (("no_highlight", highlight == 0), ("highlight_seen", highlight > 0)):
        out[f"{name}"] = {**_stats(err[seen & m]), "signed_median": float(np.median(signed[seen & m]))
                          if np.any(seen & m) else None}
    out["no_highlight_contrast_under_0.15"] = _stats(err[seen & (highlight == 0) & (contrast < 0.15)])
    for lo, hi in ((0, 4), (4, 8), (8, 12), (12, 99)):
        out[f"facing_{lo}_to_{hi}"] = _stats(err[seen & (facing >= lo) & (facing < hi)])
    nz = bake.normal[..., 2]
    for lo, hi in ((-1.0, -0.5), (-0.5, 0.5), (0.5, 1.01)):
        out[f"normal_z_{lo:g}_to_{hi:g}"] = _stats(err[seen & (nz >= lo) & (nz < hi)])
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="out/flash_room")
    ap.add_argument("--scene", default="flash_sphere", choices=("flash_sphere", "flash_sphere_resolved"),
                    help="the capture's object (capture/synthetic/flash_capture.py's module doc)")
    ap.add_argument("--photos", type=int, default=0, help="photos (0: the scene's, 24 or 72)")
    ap.add_argument("--image-size", type=int, default=400)
    ap.add_argument("--iterations", type=int, default=15)
    ap.add_argument("--modes", default="off,on,room")
    ap.add_argument("--model", default="lafortune", help="lafortune, or diffuse (no lobe to trade with the albedo)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--reuse", action="store_true", help="keep OUT's synthesized capture")
    ap.add_argument("--no-flash-pairs", action="store_true", help="each camera also takes a no-flash photo")
    ap.add_argument("--score-only", action="store_true", help="score OUT's fits again (no fitting)")
    a = ap.parse_args()

    import warp as wp

    from texstream.capture.capture_json import flash_fired, read_capture, split_holdout
    from texstream.fit.common.model_folder import pooled_psnr
    from texstream.capture.synthetic.flash_capture import FlashCaptureConfig, fit_geometry, synthesize_flash_capture
    from texstream.capture.synthetic.flash_sampling import scene_sampling
    from texstream.fit.optim.fitter import FitConfig
    from texstream.fit.stages.stage import FitStageConfig, fit_stage

    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=Path(__file__).parent).stdout.strip()
    wp.config.quiet = True
    out = Path(a.out)
    tag = ("" if a.scene == "flash_sphere" else "_resolved") + ("_pairs" if a.no_flash_pairs else "")
    truth_dir = out / f"truth{tag}"
    if not ((a.reuse or a.score_only) and (truth_dir / "capture.json").is_file()):
        synthesize_flash_capture(truth_dir, FlashCaptureConfig(scene=a.scene, photos=a.photos,
                                                               image_size=a.image_size, device=a.device,
                                                               progress=False, no_flash_pairs=a.no_flash_pairs))
    truth = read_capture(truth_dir)
    result = {"commit": commit, "machine": f"{platform.node()} ({os.cpu_count()} cores)", "device": a.device,
              "load_before": os.getloadavg(),
              "command": f"python benchmarks/flash_room_light.py --scene {a.scene} --photos {a.photos} "
                         f"--image-size {a.image_size} "
                         f"--iterations {a.iterations} --modes {a.modes} --model {a.model}"
                         + (" --no-flash-pairs" if a.no_flash_pairs else ""), "modes": {}}
    train_flash = [f for f in split_holdout(truth.frames, 8)[0] if flash_fired(f)]
    geometry = fit_geometry(truth_dir, out / f"fit_geometry{tag}", a.device)
    result["sampling"] = scene_sampling(a.scene, sum(map(flash_fired, truth.frames)), truth.frames[0].intrinsics.width)
    for mode in a.modes.split(","):
        cfg = FitStageConfig(device=a.device, holdout_every=8, renders=0,
                             fit=FitConfig(model=a.model, ambient=mode, max_iterations=a.iterations))
        t0 = time.perf_counter()
        fit_dir = out / f"fit_{a.model}_{mode}{tag}"
        if not a.score_only:
            fit_stage(truth_dir, geometry, fit_dir, cfg, progress=False)
        man = json.loads((fit_dir / "model.json").read_text())
        tex = _texel_errors(fit_dir, truth_dir, (1.0, np.eye(3), np.zeros(3)), truth.frames, train_flash)
        flash_views = [v for v in man.get("render_eval", []) if v.get("held_out") and "noflash" not in v["frame"]]
        amb = man.get("ambient") or {}
        result["modes"][mode] = {"seconds": None if a.score_only else time.perf_counter() - t0,
                                 "load_after": os.getloadavg(),
                                 "heldout": {k: man["heldout"].get(k) for k in ("pooled_psnr_db", "worst_psnr_db",
                                                                                 "views")},
                                 "heldout_flash": pooled_psnr(flash_views),
                                 "training_psnr_db": man["final"].get("psnr_db"),
                                 "albedo_rel_error": tex["albedo_rel_error"],
                                 "albedo_rel_error_seen_4": tex["albedo_rel_error_seen_4"],
                                 "albedo_rel_error_neighbourhood": tex["albedo_rel_error_neighbourhood"],
                                 "albedo_breakdown": albedo_breakdown(fit_dir, truth_dir, train_flash)
                                 if geometry.name == "ground_truth" else None,  # it compares the same atlas's texels
                                 "truth": tex["truth"],
                                 "constrained": tex.get("constrained"),
                                 "albedo_by_training_highlights": {k: tex.get(f"albedo_rel_error_training_highlight_{k}")
                                                                   for k in ("none", "once", "twice_or_more")},
                                 "ambient_rel_error": tex.get("ambient_rel_error"),
                                 "ambient_choice": {k: v for k, v in amb.items() if k in ("mode", "chosen", "reason")},
                                 "albedo_ratio_median": tex["albedo_ratio_median"],
                                 "room": {k: v for k, v in (amb.get("room") or {}).items() if k != "convention"}}
        print(mode, json.dumps(result["modes"][mode], default=float), flush=True)
    scored = "_scored" if a.score_only else ""  # a rescoring leaves the fitting run's file (its times) as it was
    (out / f"flash_room_light_{a.model}{tag}{scored}.json").write_text(json.dumps(result, indent=2, default=float))


if __name__ == "__main__":
    main()
