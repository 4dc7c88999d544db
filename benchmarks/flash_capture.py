"""The synthetic flash capture from its photos alone against the same fit given the true cameras, mesh and
response (issue 39; JSON).

    python benchmarks/flash_capture.py --out out/flash_capture [--scene flash_sphere|flash_sphere_resolved]
        [--photos 0] [--image-size 400] [--iterations 15] [--variant-iterations 40] [--atlas-resolution 0] [--reuse]
        [--mesh-ab] [--no-flash-pairs]

Renders ``texstream synth flash_capture`` (a glossy textured sphere, a flash at each camera, the room's light,
a ColorChecker on a stand beside it, 8-bit photos through a tone curve: capture/synthetic/flash_capture.py), writes
its photos as a camera leaves them (EXIF focal length; no capture.json, masks, cameras or response), and runs
``texstream run`` on them with ``--response auto`` (the curve from the chart), ``--colocated-light 1`` (a guess the
chart replaces), ``--ambient auto``, the Lafortune model, every 8th photo held out. The reference runs the same
options on the capture with the true cameras, the true mesh (its atlas) and the true response; a second reference
(``true_inputs_pipeline_atlas``) the same with the true mesh charted by the run's atlas stage as a mesh from the photos
is (:func:`true_mesh_without_uvs` says why that is the fair one); ``gap_true_units_db`` gives both gaps in the truth's
units.

Measured: held-out pooled and worst PSNR of both (in the same linear units: both responses put code 1 at radiance 1;
the photos-only figure also given corrected by the two curves' scale ratio); the chart (photos where found, the
fitted curve against the true one over the patches' codes); the flash's intensity from the chart against the truth
(in the run's units: the true intensity x the curves' scale ratio x the SfM scale squared); per texel, the fitted
albedo (pi rho_d), rho_s and n against the truth at the same surface point (the run's texels mapped into the truth's
frame by the cameras' similarity, the nearest true texel, or with a fit atlas coarser than the truth's the mean of
the true texels nearest each fitted texel: the texture a coarser atlas can hold), on the texels the photos saw and on those that saw their
highlight in 5+ photos, and on the texels the training photos constrain (``CONSTRAINED``, against
docs/accuracy.md's per-texel bounds); the same fit without the ambient term; the mesh's vertices near the chart's quad (none
wanted) and its distance to the true sphere. Writes ``OUT/flash_capture.json``.

With ``--no-flash-pairs`` every camera also takes a photo with the flash off (``texstream synth flash_capture
--no-flash-pairs``), which the run tells apart by their EXIF Flash tag: the run's ambient term is then on without
the validation comparison, and the forced-off variant is left out (refused with no-flash photos). ``heldout_flash``
pools the held-out flash photos alone (the held-out views without pairs), and the albedo is also given on the texels
4 or more training flash photos face.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import platform
import shutil
import subprocess
import time
from pathlib import Path

import numpy as np


def _radiance_units(run_frames, truth_frames, scale_fitted_over_true: float) -> float:
    """A photos-only model's radiance per unit exposure over the truth's: its response from the chart reads
    ``scale_fitted_over_true`` times the true one, and its exposures (1 from EXIF-less PNGs) stand where the truth's
    (1 / the tone curve's white) do."""
    exposure_ratio = float(np.median([f.exposure for f in truth_frames]) / np.median([f.exposure for f in run_frames]))
    return scale_fitted_over_true * exposure_ratio


def _fitted_inputs(run: Path) -> tuple[Path, Path]:
    """(capture folder, geometry) the run's fit read (run.json's fit stage ``fitted_on``: the refinement's, or the
    registered ones where the refinement was not kept); older runs: the latest stages' that exist."""
    stages = json.loads((run / "run.json").read_text())["stages"]
    fitted = next((s.get("summary") or {} for s in stages if s["name"] == "fit"), {}).get("fitted_on")
    if fitted:
        return Path(fitted["capture"]), Path(fitted["geometry"])
    source = next(d for d in (run / "refine", run / "lights", run / "posed") if (d / "capture.json").is_file())
    return source, run / "refine" if (run / "refine" / "bake.npz").is_file() else run / "atlas"


def _similarity(run_frames, truth_frames):
    """(s, R, t): truth ~ s R run + t from the cameras' centres (matched by name)."""
    from texstream.geometry.align import umeyama

    truth = {f.name: f.center for f in truth_frames}
    names = [f.name for f in run_frames if f.name in truth]
    src = np.array([f.center for f in run_frames if f.name in truth])
    dst = np.array([truth[n] for n in names])
    s, r, t = umeyama(src, dst)
    rms = float(np.sqrt(np.mean(np.sum((s * src @ r.T + t - dst) ** 2, axis=1))))
    return s, r, t, rms


def _stats(err: np.ndarray) -> dict:
    if err.size == 0:
        return {"texels": 0}
    return {"texels": int(err.shape[0]), "median": float(np.median(err)), "p90": float(np.percentile(err, 90)),
            "within_2pct": float(np.mean(err <= 0.02))}


def _facing_counts(frames, pos: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Per surface point, how many of ``frames`` face it (the view's cosine above 0.1, the fit's grazing limit)."""
    counts = np.zeros(len(pos), np.int64)
    for f in frames:
        view = np.asarray(f.center)[None] - pos
        counts += (np.sum(view * normal, axis=1) / np.linalg.norm(view, axis=1) > 0.1).astype(np.int64)
    return counts


CONSTRAINED = ("texels faced by 4+ training flash photos (view cosine > 0.1) whose true highlight 2+ of them show at "
               ">= 10% of its peak; bounds of docs/accuracy.md: albedo 1%, rho_s 3%, n 5%")
"""the texels whose parameters the photos constrain, chosen before measuring: the lobe seen twice fixes its height
and width, 4 photos the albedo beside the ambient term"""


def _constrained(albedo: np.ndarray, rho_s: np.ndarray, n: np.ndarray, mask: np.ndarray) -> dict:
    """The parameters' errors on the constrained texels (:data:`CONSTRAINED`) and the shares within the bounds."""
    if not mask.any():
        return {"definition": CONSTRAINED, "texels": 0}
    a, r, e = albedo[mask], rho_s[mask], n[mask]
    return {"definition": CONSTRAINED, "texels": int(mask.sum()), "albedo": _stats(a), "rho_s": _stats(r),
            "n": _stats(e), "albedo_within_1pct": float(np.mean(a <= 0.01)),
            "rho_s_within_3pct": float(np.mean(r <= 0.03)), "n_within_5pct": float(np.mean(e <= 0.05)),
            "all_three_within": float(np.mean((a <= 0.01) & (r <= 0.03) & (e <= 0.05)))}


def _truth_over_fit_texels(fit_pos: np.ndarray, fit_seen: np.ndarray, truth_pos: np.ndarray, truth: np.ndarray,
                           nearest: np.ndarray) -> np.ndarray:
    """(seen fit texels, P) the mean of the true texels nearest each fitted texel (its footprint on the surface,
    in the truth's frame): what a texel of a coarser atlas can hold of a finer texture; ``nearest`` (the nearest
    true texel's values) where no true texel falls to it."""
    from scipy.spatial import cKDTree

    owner = cKDTree(fit_pos).query(truth_pos)[1]
    total = np.zeros((len(fit_pos), truth.shape[1]))
    np.add.at(total, owner, truth.astype(np.float64))
    count = np.bincount(owner, minlength=len(fit_pos))
    mean = total / np.maximum(count, 1)[:, None]
    return np.where((count > 0)[fit_seen][:, None], mean[fit_seen], nearest).astype(np.float32)


def _neighbourhood_error(pos: np.ndarray, fitted: np.ndarray, truth: np.ndarray) -> dict:
    """The albedo's error with the fit and the truth both averaged over each texel and its neighbours (those within
    1.5 texel spacings on the surface, about 3x3): the error at a scale the reference's convention (nearest or
    averaged true texels, tap weights) no longer sets."""
    from scipy.spatial import cKDTree

    tree = cKDTree(pos)
    spacing = float(np.median(tree.query(pos, k=2)[0][:, 1]))
    groups = tree.query_ball_point(pos, 1.5 * spacing)
    f = np.array([fitted[g].mean(axis=0) for g in groups])
    t = np.array([truth[g].mean(axis=0) for g in groups])
    return _stats(np.abs(f / t - 1.0).max(axis=1))


def _texel_errors(model_dir: Path, truth_dir: Path, sim, truth_frames, training_frames=None,
                  units_over_true: float = 1.0) -> dict:
    """Per texel, the fitted albedo, rho_s and n against the truth at the same surface point (module doc); with
    ``training_frames`` (truth frames) also the albedo on the texels 4 or more of them face, and the ambient's.
    ``units_over_true``: the model's radiance units over the truth's (:func:`_radiance_units`): the ambient, a
    radiance per unit exposure, is compared after dividing by it; the albedos are absolute (the chart's flash is
    in the same units)."""
    from scipy.spatial import cKDTree

    from texstream.capture.imageio import read_image
    from texstream.capture.synthetic.synth import load_ground_truth
    from texstream.fit.common.setup import load_model
    from texstream.fit.diagnostics.accuracy import highlight_counts
    from texstream.geometry.bake import TexelBake

    _, truth, tlay, tbake, _ = load_ground_truth(truth_dir)
    _, grid, lay, _ = load_model(model_dir)
    bake = TexelBake.load(model_dir / "bake.npz")
    seen = bake.covered & (read_image(model_dir / "seen.png", channels=3)[..., 0] > 0.5)
    s, r, t = sim[:3]
    pos = s * bake.position[seen].astype(np.float64) @ r.T + t
    tpos = tbake.position[tbake.covered].astype(np.float64)
    dist, idx = cKDTree(tpos).query(pos)
    tp = truth[tbake.covered][idx]
    coarser = bake.covered.sum() < 0.75 * tbake.covered.sum()
    if coarser:  # a fit atlas coarser than the truth's: the truth averaged over each fitted texel (module doc)
        tp = _truth_over_fit_texels(s * bake.position[bake.covered].astype(np.float64) @ r.T + t,
                                    seen[bake.covered], tpos, truth[tbake.covered], tp)
    fp = grid[seen]
    tl, fl = tlay.lobe_offset(0), lay.lobe_offset(0) if lay.n_lobes else None
    tnormal = tbake.normal[tbake.covered][idx].astype(np.float64)
    counts = highlight_counts(truth_frames, tpos[idx], tnormal, tp, tl)
    hl = counts >= 5  # docs/accuracy.md's highlight texels; with ~24 photos few texels see a lobe 5 times
    out = {"truth": "averaged over each fitted texel" if coarser else "the nearest true texel",
           "texels_seen": int(seen.sum()), "texels_with_highlight_5_photos": int(hl.sum()),
           "texels_with_highlight_2_photos": int((counts >= 2).sum()), "match_distance_median": float(np.median(dist))}
    ratio = fp[:, 0:3] / tp[:, 0:3]  # albedo = pi rho_d: the ratio is the same
    alb = np.abs(ratio - 1.0).max(axis=1)
    out["albedo_rel_error"] = _stats(alb)
    out["albedo_rel_error_neighbourhood"] = _neighbourhood_error(pos, fp[:, 0:3], tp[:, 0:3])
    # the albedos' common scale (what the flash's intensity sets): the median ratio, per channel
    out["albedo_ratio_median"] = np.median(ratio, axis=0).tolist()
    out["albedo_rel_error_highlight"] = _stats(alb[hl])
    if training_frames is not None:
        faced = _facing_counts(training_frames, tpos[idx], tnormal)
        out["albedo_rel_error_seen_4"] = _stats(alb[faced >= 4])
        train_hl = highlight_counts(training_frames, tpos[idx], tnormal, tp, tl)
        for k, m in (("none", train_hl == 0), ("once", train_hl == 1), ("twice_or_more", train_hl >= 2)):
            out[f"albedo_rel_error_training_highlight_{k}"] = _stats(alb[m])
        if lay.ambient and tlay.ambient:
            amb = np.abs(fp[:, lay.ambient_offset:lay.ambient_offset + 3] / units_over_true
                         / tp[:, tlay.ambient_offset:tlay.ambient_offset + 3] - 1.0).max(axis=1)
            out["ambient_rel_error"] = _stats(amb)
    if fl is not None:
        rs = np.abs(fp[:, fl:fl + 3] / tp[:, tl:tl + 3] - 1.0).max(axis=1)
        n = np.abs(fp[:, fl + lay.lobe_stride - 1] / tp[:, tl + tlay.lobe_stride - 1] - 1.0)
        out["rho_s_rel_error_highlight"] = _stats(rs[hl])
        out["n_rel_error_highlight"] = _stats(n[hl])
        out["rho_s_rel_error_highlight_2_photos"] = _stats(rs[counts >= 2])
        out["n_rel_error_highlight_2_photos"] = _stats(n[counts >= 2])
        if training_frames is not None:
            out["constrained"] = _constrained(alb, rs, n, (train_hl >= 2) & (faced >= 4))
        out["bounds_docs_accuracy"] = {"diffuse_within_1pct": float(np.mean(alb[hl] <= 0.01)) if hl.any() else None,
                                       "rho_s_within_3pct": float(np.mean(rs[hl] <= 0.03)) if hl.any() else None,
                                       "n_within_5pct": float(np.mean(n[hl] <= 0.05)) if hl.any() else None}
    return out


def _mesh_checks(mesh_path: Path, sim) -> dict:
    """Vertices of the run's mesh near the chart's quad (in the truth's frame), and its distance to the sphere."""
    from texstream.capture.synthetic.flash_capture import chart_corners_world, chart_normal
    from texstream.geometry.mesh_io import load_mesh

    v = load_mesh(mesh_path).vertices.astype(np.float64)
    s, r, t = sim[:3]
    w = s * v @ r.T + t
    corners = chart_corners_world()
    centre, normal = corners.mean(0), chart_normal()
    u_axis, v_axis = corners[1] - corners[0], corners[3] - corners[0]
    rel = w - corners[0]
    a, b = rel @ u_axis / (u_axis @ u_axis), rel @ v_axis / (v_axis @ v_axis)
    near_plane = np.abs((w - centre) @ normal) < 0.15
    in_quad = (a > -0.1) & (a < 1.1) & (b > -0.1) & (b < 1.1)
    off_sphere = np.abs(np.linalg.norm(w, axis=1) - 1.0)
    return {"vertices": int(len(w)), "vertices_near_chart": int((near_plane & in_quad).sum()),
            "vertices_off_sphere_over_0.1": int((off_sphere > 0.1).sum()),
            "sphere_distance_median": float(np.median(off_sphere)), "sphere_distance_p99": float(np.percentile(off_sphere, 99))}


def _curve_check(run_capture_dir: Path, truth_dir: Path) -> dict:
    """The chart-fitted curve against the true one over the codes the chart's patches cover: their ratio's spread
    about its median (the linearised patch values' error; a common scale is the chart's freedom) and the scale."""
    from texstream.capture.capture_json import read_capture

    fitted, true = read_capture(run_capture_dir).response, read_capture(truth_dir).response
    report = json.loads((run_capture_dir / "ingest_report.json").read_text())["response"]
    codes = np.concatenate([np.ravel(r["sighting"]["patches"]) for r in report["per_photo"] if r.get("sighting")])
    codes = codes[(codes >= 0.03) & (codes <= 0.97)]
    ratio = fitted.linearise(codes) / true.linearise(codes)
    scale = float(np.median(ratio))
    dev = np.abs(ratio / scale - 1.0)
    grid = np.linspace(0.05, 1.0, 20)
    return {"scale_fitted_over_true": scale, "patch_codes": int(codes.size), "code_range": [float(codes.min()), float(codes.max())],
            "linearised_error_median": float(np.median(dev)), "linearised_error_p95": float(np.percentile(dev, 95)),
            "linearised_within_1pct": float(np.mean(dev <= 0.01)),
            "curve_ratio_on_grid": {f"{c:.2f}": float(fitted.linearise(c) / true.linearise(c) / scale) for c in grid},
            "photos_with_chart": len(report.get("charts_found", [])), "photos": len(report["per_photo"])}


def _heldout(summary: dict) -> dict:
    h = summary.get("heldout") or {}
    return {k: h.get(k) for k in ("pooled_psnr_db", "worst_psnr_db", "views")}


def heldout_flash(model_dir: Path) -> dict:
    """Pooled PSNR of the held-out flash photos alone (model.json's per-view scores, no-flash photos left out)."""
    from texstream.fit.common.model_folder import pooled_psnr

    views = json.loads((Path(model_dir) / "model.json").read_text()).get("render_eval", [])
    return pooled_psnr([v for v in views if v.get("held_out") and "noflash" not in v["frame"]])


def _ambient_choice(model_dir: Path) -> dict:
    """model.json's ambient report: what --ambient auto chose and its validation scores with and without."""
    amb = json.loads((model_dir / "model.json").read_text()).get("ambient") or {}
    return {"chosen": amb.get("chosen"), "reason": amb.get("reason"),
            "validation_pooled_db": {k: v.get("pooled_psnr_db") for k, v in (amb.get("candidates") or {}).items()}}


def _fit_ambient(run_dir: Path, out: Path, ambient: str, device: str, iterations: int) -> dict:
    """The photos-only run's fit again, on the same cameras, mesh and lights, with ``--ambient`` forced."""
    from texstream.fit.optim.fitter import FitConfig
    from texstream.fit.stages.stage import FitStageConfig, fit_stage

    source, geometry = _fitted_inputs(run_dir)
    cfg = FitStageConfig(device=device, holdout_every=8, fit=FitConfig(model="lafortune", ambient=ambient,
                                                                      max_iterations=iterations))
    t0 = time.perf_counter()
    fit_stage(source, geometry, out, cfg, progress=False)
    man = json.loads((out / "model.json").read_text())
    return {"heldout": {k: man["heldout"].get(k) for k in ("pooled_psnr_db", "worst_psnr_db", "views")},
            "training_psnr_db": man["final"].get("psnr_db"), "seconds": time.perf_counter() - t0}


def _mesh_with_and_without_chart_masks(out: Path, truth_frames, device: str) -> dict:
    """Ingest, registration and mesh of the photos with no object masks (``--auto-masks none``, as in a room whose
    background is no plain colour), once with the chart masked (``--response auto``: the chart found, its quad cleared
    from masks of every pixel) and once without (``--response srgb``: no chart looked for): what the chart masks
    keep out of the mesh."""
    from texstream.calib.ingest import IngestConfig, ingest
    from texstream.calib.register import RegisterConfig, register
    from texstream.capture.capture_json import read_capture
    from texstream.geometry.make_mesh import MeshConfig, make_mesh
    from texstream.geometry.mesh_frame import mesh_alignment

    result = {}
    for name, response in (("chart_masks", "auto"), ("no_chart_masks", "srgb")):
        root = out / f"mesh_{name}"
        t0 = time.perf_counter()
        ingest(out / "photos", root / "capture", IngestConfig(response=response, colocated_light=1.0,
                                                               auto_masks="none"))
        register(root / "capture", root / "posed", RegisterConfig(), mesh_alignment=mesh_alignment)
        make_mesh(root / "posed", root / "mesh", MeshConfig(device=device))
        sim = _similarity(read_capture(root / "posed").frames, truth_frames)
        result[name] = {**_mesh_checks(root / "mesh" / "mesh.ply", sim), "seconds": time.perf_counter() - t0}
    return result


def _run(photos_or_capture: Path, out: Path, device: str, iterations: int, atlas: int, *, photos_only: bool,
         mesh: str | None = None) -> tuple[dict, float]:
    from texstream.pipelines.run import RunConfig, run_pipeline

    cfg = RunConfig(device=device, model="lafortune", progress=False, mesh_file=mesh)
    if photos_only:
        cfg.ingest = dataclasses.replace(cfg.ingest, response="auto", colocated_light=1.0)
    cfg.atlas = dataclasses.replace(cfg.atlas, resolution=atlas)
    cfg.fit = dataclasses.replace(cfg.fit, fit=dataclasses.replace(cfg.fit.fit, max_iterations=iterations,
                                                                   ambient="auto"))
    t0 = time.perf_counter()
    summary = run_pipeline(photos_or_capture, out, cfg, log=lambda m: print(m, flush=True))
    return summary, time.perf_counter() - t0


def true_mesh_without_uvs(truth_dir: Path, out: Path) -> Path:
    """The truth's mesh, welded along its UV seam, without its UVs (``out``, a PLY with its normals): what the run's
    atlas stage charts with xatlas as it charts a mesh made from the photos. The truth's own lat-long atlas is laid on
    the grid its texture was drawn on (2x2 of the truth's texels a fitted texel), an alignment no atlas made from a
    mesh has: the texture finer than the atlas then averages exactly, where a chart at any other angle aliases it."""
    from texstream.geometry.mesh_io import load_mesh, save_mesh
    from texstream.render.mesh import SurfaceMesh

    if not out.is_file():
        mesh = load_mesh(truth_dir / "ground_truth" / "mesh.obj")
        key = mesh.weld_key()
        first = np.unique(key, return_index=True)[1]
        welded = SurfaceMesh(vertices=np.asarray(mesh.vertices)[first], faces=key[mesh.faces].astype(np.int32),
                             normals=np.asarray(mesh.vertex_normals())[first])
        save_mesh(out, welded)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="out/flash_capture")
    ap.add_argument("--scene", default="flash_sphere", choices=("flash_sphere", "flash_sphere_resolved"),
                    help="the capture's object (capture/synthetic/flash_capture.py's module doc)")
    ap.add_argument("--photos", type=int, default=0, help="photos (0: the scene's, 24 or 72)")
    ap.add_argument("--image-size", type=int, default=400)
    ap.add_argument("--iterations", type=int, default=15)
    ap.add_argument("--variant-iterations", type=int, default=40,
                    help="LM iterations of the fits with the ambient term forced on and off (0: --iterations; at 15 "
                         "the term's fit is unconverged and loses on held-out photos); the "
                         "term's extra unknowns converge more slowly")
    ap.add_argument("--atlas-resolution", type=int, default=0,
                    help="the photos-only run's atlas side (0: the width of the scene's fit atlas, 320, or 160 for "
                         "the resolved scene, whose photos give about 2x2 pixels a texel of 160)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--reuse", action="store_true",
                    help="keep OUT's capture, photos and the runs' stages whose inputs did not change (the pipeline's "
                         "stamps); default: start afresh")
    ap.add_argument("--no-flash-pairs", action="store_true", help="each camera also takes a no-flash photo")
    ap.add_argument("--mesh-ab", action="store_true",
                    help="only the meshes with and without chart masks, no object masks (OUT/mesh_*, "
                         "OUT/flash_capture_mesh_ab.json; needs OUT's photos: run without it first, then with --reuse)")
    a = ap.parse_args()

    import warp as wp

    from texstream.capture.capture_json import flash_fired, read_capture, split_holdout
    from texstream.capture.synthetic.flash_capture import FlashCaptureConfig, fit_geometry, synthesize_flash_capture
    from texstream.capture.synthetic.flash_sampling import scene_sampling
    from texstream.capture.synthetic.photos_only import write_photos_only

    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=Path(__file__).parent).stdout.strip()  # read before the run
    load_before = os.getloadavg()  # the box is shared: its load says how far the times are inflated
    wp.config.quiet = True
    wp.config.log_level = wp.LOG_WARNING
    out = Path(a.out)
    truth_dir = out / "truth"
    if not (a.reuse and (out / "photos").is_dir()):
        shutil.rmtree(out, ignore_errors=True)
        synthesize_flash_capture(truth_dir, FlashCaptureConfig(scene=a.scene, photos=a.photos,
                                                               image_size=a.image_size, device=a.device,
                                                               progress=False, no_flash_pairs=a.no_flash_pairs))
        write_photos_only(truth_dir, out / "photos")
    truth = read_capture(truth_dir)
    train_flash = [f for f in split_holdout(truth.frames, 8)[0] if flash_fired(f)]
    flash_truth = json.loads((truth_dir / "ground_truth" / "flash.json").read_text())
    if flash_truth.get("scene", "flash_sphere") != a.scene:
        raise SystemExit(f"{truth_dir} holds {flash_truth.get('scene', 'flash_sphere')}, not --scene {a.scene}: "
                         "run without --reuse")
    a.atlas_resolution = a.atlas_resolution or int((flash_truth.get("fit_atlas") or flash_truth["atlas"])[0])
    if a.mesh_ab:
        ab = {"commit": commit, "machine": f"{platform.node()} ({os.cpu_count()} cores)",
              "command": f"python benchmarks/flash_capture.py --reuse --mesh-ab --photos {a.photos} "
                         f"--image-size {a.image_size}",
              "auto_masks_none": _mesh_with_and_without_chart_masks(out, truth.frames, a.device)}
        (out / "flash_capture_mesh_ab.json").write_text(json.dumps(ab, indent=2, default=float))
        print(json.dumps(ab, indent=1, default=float))
        return

    run, run_s = _run(out / "photos", out / "run", a.device, a.iterations, a.atlas_resolution, photos_only=True)
    ref, ref_s = _run(truth_dir, out / "reference", a.device, a.iterations, a.atlas_resolution, photos_only=False,
                      mesh=str(fit_geometry(truth_dir, out / "fit_geometry", a.device)))
    # the same, the truth's mesh charted by the run's atlas stage (true_mesh_without_uvs): the fair reference
    ref_pa, ref_pa_s = _run(truth_dir, out / "reference_pipeline_atlas", a.device, a.iterations, a.atlas_resolution,
                            photos_only=False, mesh=str(true_mesh_without_uvs(truth_dir, out / "true_mesh_no_uvs.ply")))
    fit_dir = _fitted_inputs(out / "run")[0]
    sim = _similarity(read_capture(fit_dir).frames, truth.frames)
    curve = _curve_check(out / "run" / "capture", truth_dir)
    result = {"commit": commit, "machine": f"{platform.node()} ({os.cpu_count()} cores)", "device": a.device,
              "command": f"python benchmarks/flash_capture.py --scene {a.scene} --photos {a.photos} "
                         f"--image-size {a.image_size} "
                         f"--iterations {a.iterations} --variant-iterations {a.variant_iterations} "
                         f"--atlas-resolution {a.atlas_resolution}" + (" --no-flash-pairs" if a.no_flash_pairs else ""),
              "truth": flash_truth, "chart": curve, "similarity": {"scale": sim[0], "camera_rms": sim[3]},
              "sampling": scene_sampling(a.scene, sum(map(flash_fired, truth.frames)), truth.frames[0].intrinsics.width),
              "load_before": load_before}
    lights = run.get("lights") or {}
    if lights.get("source") == "colour chart":
        # the run's units: response (fitted = scale x true) and SfM lengths (1 / s of the truth's)
        expected = np.asarray(flash_truth["flash_intensity_response_units"]) * curve["scale_fitted_over_true"] / sim[0] ** 2
        result["flash"] = {"fitted": lights["intensity"], "expected_in_run_units": expected.tolist(),
                           "relative_error": (np.asarray(lights["intensity"]) / expected - 1.0).tolist(),
                           "room_irradiance_on_chart": lights.get("room_irradiance_on_chart"), "why": lights.get("why")}
    shift = 20 * math.log10(curve["scale_fitted_over_true"])
    units = _radiance_units(read_capture(fit_dir).frames, truth.frames, curve["scale_fitted_over_true"])
    po = _heldout(run)
    result["photos_only"] = {"heldout": po, "pooled_psnr_db_in_true_units": (po["pooled_psnr_db"] or 0) + shift,
                             "heldout_flash": heldout_flash(out / "run" / "model"),
                             "seconds": run_s, "inputs": run["inputs"], "model": run["model"],
                             "stages": [{k: st[k] for k in ("name", "status", "reason", "seconds")} for st in run["stages"]],
                             "registered": len(read_capture(fit_dir).frames),
                             "ambient": _ambient_choice(out / "run" / "model"),
                             "texels": _texel_errors(out / "run" / "model", truth_dir, sim, truth.frames, train_flash,
                                                     units),
                             "mesh": _mesh_checks(out / "run" / "mesh" / "mesh.ply", sim)}
    result["true_inputs"] = {"heldout": _heldout(ref), "seconds": ref_s, "inputs": ref["inputs"],
                             "heldout_flash": heldout_flash(out / "reference" / "model"),
                             "ambient": _ambient_choice(out / "reference" / "model"),
                             "texels": _texel_errors(out / "reference" / "model", truth_dir, (1.0, np.eye(3), np.zeros(3)),
                                                     truth.frames, train_flash)}
    result["true_inputs_pipeline_atlas"] = {
        "heldout": _heldout(ref_pa), "seconds": ref_pa_s, "inputs": ref_pa["inputs"],
        "heldout_flash": heldout_flash(out / "reference_pipeline_atlas" / "model"),
        "texels": _texel_errors(out / "reference_pipeline_atlas" / "model", truth_dir, (1.0, np.eye(3), np.zeros(3)),
                                truth.frames, train_flash)}
    result["gap_db"] = result["true_inputs"]["heldout"]["pooled_psnr_db"] - po["pooled_psnr_db"]
    # in the truth's units (the photos-only figures shifted by the chart's response scale), all held-out views and
    # the flash views alone, against the true inputs with the truth's atlas and with the pipeline's
    flash_true_units = result["photos_only"]["heldout_flash"]["pooled_psnr_db"] + shift
    result["gap_true_units_db"] = {
        ref_name: {"all_views": result[ref_name]["heldout"]["pooled_psnr_db"]
                   - result["photos_only"]["pooled_psnr_db_in_true_units"],
                   "flash_views": result[ref_name]["heldout_flash"]["pooled_psnr_db"] - flash_true_units}
        for ref_name in ("true_inputs", "true_inputs_pipeline_atlas")}
    # the term forced either way, whatever auto chose: held-out error and albedos (off is refused with pairs)
    for mode in ("on",) if a.no_flash_pairs else ("on", "off"):
        key = f"photos_only_ambient_{mode}"
        result[key] = _fit_ambient(out / "run", out / f"run_ambient_{mode}", mode, a.device,
                                   a.variant_iterations or a.iterations)
        result[key]["heldout_flash"] = heldout_flash(out / f"run_ambient_{mode}")
        result[key]["texels"] = _texel_errors(out / f"run_ambient_{mode}", truth_dir, sim, truth.frames, train_flash,
                                              units)
    if not a.no_flash_pairs:
        result["ambient_gain_db"] = (result["photos_only_ambient_on"]["heldout"]["pooled_psnr_db"]
                                     - result["photos_only_ambient_off"]["heldout"]["pooled_psnr_db"])
    result["load_after"] = os.getloadavg()
    (out / "flash_capture.json").write_text(json.dumps(result, indent=2, default=float))
    print(json.dumps({k: result.get(k) for k in ("gap_db", "gap_true_units_db", "ambient_gain_db")}, indent=1))


if __name__ == "__main__":
    main()
