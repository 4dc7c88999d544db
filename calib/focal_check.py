"""Registration's focal-length prior checked against what the mapping did with it (:mod:`.register` calls it).

An EXIF focal length several times too long (a raw converter's stale full-sensor tags that no cross-check
in :mod:`.sensors` could catch) leaves COLMAP's mapper stuck at the wrong focal length with few photos
registered; a guessed one must not count as a prior at all.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from texstream.core.progress import say


def drop_focal_priors(db: Path, names: list[str]) -> None:
    """Mark the cameras of these images as having no focal-length prior (COLMAP marks explicitly given
    parameters as one; a guess is not)."""
    import pycolmap

    database = pycolmap.Database.open(str(db))
    try:
        ids = {im.camera_id for im in database.read_all_images() if im.name in set(names)}
        for cam in database.read_all_cameras():
            if cam.camera_id in ids:
                cam.has_prior_focal_length = False
                database.update_camera(cam)
    finally:
        database.close()


def _model_quality(recs: dict[int, Any]) -> tuple[int, float]:
    """(registered photos of the largest model, minus its mean reprojection error): larger is better."""
    if not recs:
        return 0, -np.inf
    rec = max(recs.values(), key=lambda r: r.num_reg_images())
    return rec.num_reg_images(), -float(rec.compute_mean_reprojection_error())


def _error_or_none(quality: tuple[int, float]) -> float | None:
    return -quality[1] if np.isfinite(quality[1]) else None


def _quality_text(quality: tuple[int, float]) -> str:
    return (f"{quality[0]} photos, {-quality[1]:.3f} px" if np.isfinite(quality[1])
            else "no model")


def check_focal_prior(recs: dict[int, Any], db: Path, n_photos: int, report: dict,
                      remap: Callable[[], dict[int, Any]]) -> dict[int, Any]:
    """Mapping again without the EXIF focal prior when the mapping with it looks wrong; the better model kept.

    A prior several times too long (stale focal-plane tags no cross-check caught) leaves the mapper stuck:
    the textured sphere with a 6x prior registered 2 of 20 photos at 5.9x the true focal length. It looks
    wrong when photos are left out, or the focal length ends more than 25% from the prior (bundle adjustment
    pulled it away: the prior was off) or within 10% of the mapper's bounds (``min/max_focal_length_ratio``
    of the longer side). The second mapping (``remap``, on the same database) starts from COLMAP's default
    guess (1.2 x the longer side) with no prior; the model with more registered photos, then the lower mean
    reprojection error, is kept; the decision goes to ``report["focal_prior"]`` and one line to the log.
    """
    import pycolmap

    op = pycolmap.IncrementalPipelineOptions()
    lo, hi = op.mapper.min_focal_length_ratio, op.mapper.max_focal_length_ratio
    database = pycolmap.Database.open(str(db))
    try:
        priors = {c.camera_id: c for c in database.read_all_cameras() if c.has_prior_focal_length}
    finally:
        database.close()
    n_reg, _ = _model_quality(recs)
    why = []
    if n_reg < n_photos:
        why.append(f"{n_reg} of {n_photos} photos registered")
    if recs:
        rec = max(recs.values(), key=lambda r: r.num_reg_images())
        for cid, cam in rec.cameras.items():
            prior = priors.get(cid)
            size = max(cam.width, cam.height)
            f, f0 = float(cam.mean_focal_length()), float(prior.mean_focal_length()) if prior else None
            if f0 and not 0.8 <= f / f0 <= 1.25:
                why.append(f"camera {cid}'s focal length went from the prior {f0:.0f} px to {f:.0f} px")
            if f < 1.1 * lo * size or f > hi * size / 1.1:
                why.append(f"camera {cid}'s focal length {f:.0f} px is at the mapper's bound")
    info: dict[str, Any] = {"prior_focal_px": {str(k): round(float(c.mean_focal_length()), 2)
                                               for k, c in priors.items()}}
    report["focal_prior"] = info
    if not why:
        info.update(retried=False,
                    reason="the mapping with the EXIF prior registered every photo and kept its focal length")
        return recs
    database = pycolmap.Database.open(str(db))
    try:
        for cam in priors.values():
            guess = 1.2 * max(cam.width, cam.height)
            cam.params = [guess if i in cam.focal_length_idxs() else float(v) for i, v in enumerate(cam.params)]
            cam.has_prior_focal_length = False
            database.update_camera(cam)
    finally:
        database.close()
    say("register", f"EXIF focal prior doubtful ({'; '.join(why)}): mapping again from COLMAP's guess, no prior")
    t0 = time.perf_counter()
    again = remap()
    q0, q1 = _model_quality(recs), _model_quality(again)
    keep = "no_prior" if q1 > q0 else "prior"
    line = (f"focal prior: kept the mapping {'without' if keep == 'no_prior' else 'with'} the EXIF prior "
            f"(with: {_quality_text(q0)}; without: {_quality_text(q1)})")
    say("register", line)
    # a mapping that made no model has no reprojection error: None in the report (JSON has no infinity; the
    # report of a failed registration must still be written)
    info.update(retried=True, reason="; ".join(why), kept=keep, decision=line,
                retry_s=round(time.perf_counter() - t0, 2),
                with_prior={"registered": q0[0], "reprojection_error": _error_or_none(q0)},
                without_prior={"registered": q1[0], "reprojection_error": _error_or_none(q1)})
    return again if keep == "no_prior" else recs
