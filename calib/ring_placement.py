"""Registration's second chance for photos SfM left out: a turntable's ring, its focal length, the silhouettes.

Called by :func:`texstream.calib.register.register` when incremental mapping leaves photos out:

- :func:`focal_by_ring`: with estimated intrinsics, SfM on a few neighbouring photos of a long lens cannot tell
  the focal length (the Middlebury dino, f = 3310 px for 640 px wide photos, came out at 517 px from 5 photos,
  and a wrong focal length bends the poses too). Mapping is rerun with the focal length fixed on a grid; the
  models it gives are merged into one ring (:func:`texstream.calib.turntable.merge_models`), and the focal
  length whose cameras fit a ring best (the RMS angle between the SfM rotations and the ring's) is kept. On the
  dino the ring's misfit is 2.6 deg at 1000 px, 0.32 deg at 3000-3310 px, 0.55 deg at 5000 px, and every focal
  length from 1000 px on registers 12 photos in two models instead of 5 in one.
- :func:`place_on_ring`: the left-out photos get the ring's cameras at their indices; when the ring fits the
  registered cameras well, every camera is taken from the ring (its rotations came out closer to the truth
  than SfM's own on the dino: 0.2-0.3 deg against 0.1-0.7 deg); then each camera is checked against the
  visual hull of the others (:class:`texstream.calib.silhouettes.SilhouetteSet`) and a left-out photo whose
  silhouette overlap is under the bar is dropped with its reason.
"""

from __future__ import annotations

import dataclasses
import shutil
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from texstream.capture.imageio import read_mask
from texstream.core.config import option
from texstream.core.progress import say

from .colmap_log import colmap_quiet
from .silhouettes import SilhouetteSet
from .turntable import RingFit, merge_models, photo_indices


@dataclasses.dataclass
class RingConfig:
    """Options of the placement of photos registration left out on a turntable ring."""

    max_ring_misfit_deg: float = option(1.0, help="largest RMS angle between the registered cameras' rotations and "
                                        "the fitted ring's (and of their angles about the axis against an even "
                                        "step) for the ring to be used (the dino's fits 0.3 deg at the right "
                                        "focal length, 2.6 deg at a third of it)")
    min_iou: float = option(0.7, help="smallest IoU of a placed photo's mask with the visual hull of the others, "
                            "projected, for the placement to be kept (the dino's true cameras give 0.80-0.96)")
    max_first_misfit_deg: float = option(10.0, help="the focal length is searched only when the first mapping's "
                                         "cameras fit a ring within this (the dino's, at SfM's 517 px for 3310, "
                                         "fit one within 3.6 deg)")
    silhouette_resolution: int = option(96, help="voxels along the side of the grid the silhouettes are checked on")
    focal_grid: tuple = option((0.6, 0.9, 1.35, 2.0, 3.0, 4.5, 6.75, 10.0, 15.0),
                               help="focal lengths tried, in image widths, when the intrinsics are estimated")


def _models(recs, names: list[str]) -> list[dict[int, tuple[np.ndarray, np.ndarray]]]:
    """Each reconstruction's registered cameras as index -> (world-to-camera R, centre), largest first."""
    index = dict(zip(names, photo_indices(names)))
    out = []
    for rec in sorted(recs, key=lambda r: -r.num_reg_images()):
        m = {}
        for im in rec.images.values():
            if im.has_pose and im.name in index:
                m[index[im.name]] = (np.asarray(im.cam_from_world().rotation.matrix()), np.asarray(im.projection_center()))
        out.append(m)
    return out


def ring_of(recs, names: list[str]) -> tuple[RingFit | None, dict, list[dict]]:
    """The ring of every model with at least 3 cameras merged into the largest's frame (None: no ring)."""
    models = [m for m in _models(recs, names) if len(m) >= 2]
    if not models or len(models[0]) < 3:
        return None, {}, []
    try:
        return merge_models(models)
    except (ValueError, np.linalg.LinAlgError):
        return None, {}, []


def set_focal(db_path: Path, focal: float) -> None:
    """Fix every camera of a COLMAP database at ``focal`` px (distortion 0) before mapping again."""
    import pycolmap

    db = pycolmap.Database.open(str(db_path))
    try:
        for cam in db.read_all_cameras():
            params = np.asarray(cam.params, np.float64).copy()
            for i in cam.focal_length_idxs():
                params[i] = focal
            for i in cam.extra_params_idxs():
                params[i] = 0.0
            cam.params = params.tolist()
            cam.has_prior_focal_length = True
            db.update_camera(cam)
    finally:
        db.close()


def focal_by_ring(recs: dict, remap: Callable[[float], dict], names: list[str], width: int, cfg: RingConfig,
                  report: dict) -> tuple[dict, float | None]:
    """The models of the focal length whose cameras fit a turntable ring best (see the module doc).

    Args:
        recs: the models mapping gave with the estimated focal length.
        remap: focal length (px) -> the models of mapping again with it fixed.
        names: the photos' names in capture order.
        width: the photos' width (px), the scale of the grid.

    Returns:
        (the models to keep, the fixed focal length or None when the first mapping's stay).
    """
    t0 = time.perf_counter()

    def score(rs) -> tuple[bool, int, float]:
        """(fits a ring within the bar, cameras on it, -misfit): the larger the better."""
        ring, merged, _ = ring_of(list(rs.values()), names)
        if ring is None:
            return False, 0, -np.inf
        misfit = max(ring.rotation_rms_deg, ring.step_rms_deg)
        return misfit <= cfg.max_ring_misfit_deg, len(merged), -misfit

    first = score(recs)
    largest = max(recs.values(), key=lambda r: r.num_reg_images())
    alone = score({0: largest})  # the other models, in a wrong focal length's frames, may merge badly
    why_not = None
    if largest.num_reg_images() >= 0.75 * len(names):
        why_not = (f"the largest model holds {largest.num_reg_images()} of {len(names)} photos (3/4 or more: not "
                   "worth mapping again)")
    elif -alone[2] > cfg.max_first_misfit_deg:
        why_not = (f"the registered cameras are far from a ring (misfit {-alone[2]:.1f} deg > "
                   f"{cfg.max_first_misfit_deg:g}) even before the focal length is changed")
    if why_not:
        report["ring_focal"] = {"focal": None, "decision": f"focal length not searched: {why_not}"}
        return recs, None
    tried: dict[float, tuple] = {}
    best_key, best_focal = first, None
    grid = [width * g for g in cfg.focal_grid]
    for _ in range(2):
        for f in grid:
            if round(f, 1) not in tried:
                key = tried[round(f, 1)] = score(remap(f))
                if key > best_key:
                    best_key, best_focal = key, f
        if best_focal is None:
            break
        grid = [best_focal * g for g in (0.8, 0.9, 1.1, 1.25)]  # second round: around the best
    if best_focal is not None and best_key[0]:
        recs = remap(best_focal)  # the database and the models of the kept focal length (the same seed)
        verdict = f"focal length {best_focal:.0f} px: its cameras fit a ring within {-best_key[2]:.2f} deg"
    else:
        best_focal = None
        verdict = "no focal length gave cameras on a ring: the first mapping's models kept"
    tried = {k: (v[1], -v[2]) for k, v in tried.items()}
    report["ring_focal"] = {"tried": {str(f): {"cameras": v[0], "ring_misfit_deg": None if not np.isfinite(v[1])
                                               else round(v[1], 3)} for f, v in sorted(tried.items())},
                            "focal": best_focal, "decision": verdict, "seconds": time.perf_counter() - t0}
    say("register", verdict)
    return recs, best_focal


def place_on_ring(recs: list, photos: list, posed: dict, intrinsics_of: Callable[[Any], Any], cfg: RingConfig,
                  report: dict) -> dict:
    """Cameras for the photos SfM left out, from the ring of the registered ones, checked by the silhouettes.

    Args:
        recs: every model mapping gave (the largest first sets the frame; ``posed`` was made from it).
        photos: the photos (``name``, ``mask``, ``width``, ``height``) in capture order.
        posed: name -> (R, t, Intrinsics) of the registered photos.
        intrinsics_of: photo -> the Intrinsics of its size among the registered cameras, or None.

    Returns:
        name -> (R, t, Intrinsics) of every photo kept (registered and placed); ``report["ring"]`` says how
        each was placed and how well.
    """
    names = [p.name for p in photos]
    ring, merged, model_reports = ring_of(recs, names)
    info: dict[str, Any] = {"models": model_reports}
    report["ring"] = info
    if ring is None:
        info["decision"] = "not placed: fewer than 3 registered photos in the largest model"
        return posed
    info["fit"] = ring.report()
    misfit = max(ring.rotation_rms_deg, ring.step_rms_deg)
    if misfit > cfg.max_ring_misfit_deg:
        info["decision"] = (f"not placed: the registered cameras are not on an evenly stepped ring (misfit "
                            f"{misfit:.2f} deg > {cfg.max_ring_misfit_deg:g})")
        return posed
    if any(p.mask is None for p in photos):
        info["decision"] = "not placed: every photo needs a mask to check the placements by their silhouettes"
        return posed
    index = dict(zip(names, photo_indices(names)))
    kept = [p for p in photos if intrinsics_of(p) is not None]
    cams = {p.name: ring.pose(index[p.name]) for p in kept}
    intr = {p.name: intrinsics_of(p) for p in kept}
    i0 = intr[kept[0].name]
    masks = [read_mask(p.mask, (p.height, p.width)) for p in kept]
    sil = SilhouetteSet((i0.fx, i0.fy, i0.cx, i0.cy), masks, [cams[p.name][0] for p in kept],
                        [-cams[p.name][0].T @ cams[p.name][1] for p in kept], resolution=cfg.silhouette_resolution)
    # the silhouettes check, not move: a coordinate search of small turns raising each photo's IoU against the
    # others' hull moved the dino's cameras 0.3-2.4 deg and doubled their median rotation error (0.26 -> 0.43 deg
    # against the calibration); the photometric refinement of the run's refine stage moves them instead
    ious, _ = sil.consistent_ious(cfg.min_iou)
    per_photo = {p.name: {"iou": round(ious[i], 4)} for i, p in enumerate(kept)}
    out = {}
    placed, dropped = 0, []
    for i, p in enumerate(kept):
        r = sil.rotations[i]
        entry = per_photo[p.name]
        entry["method"] = "sfm, snapped to the ring" if p.name in posed else (
            "sfm in a merged model, snapped to the ring" if index[p.name] in merged else "ring")
        if p.name not in posed and entry["iou"] < cfg.min_iou:
            entry["dropped"] = f"silhouette IoU {entry['iou']:.2f} under {cfg.min_iou:g}"
            dropped.append(p.name)
            continue
        placed += p.name not in posed
        out[p.name] = (r, -r @ sil.centres[i], intr[p.name])
    merged_in = sum(1 for e in per_photo.values() if e["method"].startswith("sfm in a merged"))
    ious = [e["iou"] for n, e in per_photo.items() if n in out]
    info.update(photos=per_photo, placed=placed, dropped=dropped,
                decision=f"{placed} left-out photo(s) placed ({merged_in} from other SfM models merged by the ring, "
                f"{placed - merged_in} by the ring alone; step {np.degrees(ring.step):.2f} deg, misfit {misfit:.2f} "
                f"deg), {len(dropped)} dropped; every camera taken from the ring; silhouette IoU against the others' "
                f"hull {min(ious):.2f}-{max(ious):.2f}")
    say("register", info["decision"])
    return out


def map_at_focal(work: Path, img_dir: Path, focal: float, threads: int, seed: int, min_model_size: int) -> dict:
    """Incremental mapping again over the matches in ``work/database.db``, the focal length fixed at ``focal``."""
    import pycolmap

    set_focal(work / "database.db", focal)
    op = pycolmap.IncrementalPipelineOptions()
    op.num_threads, op.random_seed, op.min_model_size = threads, seed, min_model_size
    op.ba_refine_focal_length = op.ba_refine_principal_point = op.ba_refine_extra_params = False
    op.mapper.abs_pose_refine_focal_length = op.mapper.abs_pose_refine_extra_params = False
    out = work / "sparse_ring"
    shutil.rmtree(out, ignore_errors=True)
    with colmap_quiet():
        return pycolmap.incremental_mapping(work / "database.db", img_dir, out, options=op)
