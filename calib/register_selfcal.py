"""Self-calibration's choices after incremental mapping (:mod:`.register`): whether the estimated lens
distortion, a refined principal point and a focal length refined away from its EXIF prior are kept, each only
where it lowers the reprojection error enough."""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from texstream.core.progress import phase

from .colmap_log import colmap_quiet


PINHOLE_OF = {"SIMPLE_RADIAL": ("SIMPLE_PINHOLE", 3), "RADIAL": ("SIMPLE_PINHOLE", 3),
              "OPENCV": ("PINHOLE", 4), "FULL_OPENCV": ("PINHOLE", 4)}  # model -> (pinhole model, params kept)


def bundle_adjust(rec: Any, focal: bool, principal_point: bool, extra: bool, threads: int) -> None:
    """Global bundle adjustment of ``rec`` in place on ``threads`` Ceres threads (-1: all; the registration's
    ``mapping_threads``: threaded sums add in another order, so only a fixed count repeats itself exactly)."""
    import pycolmap

    bo = pycolmap.BundleAdjustmentOptions()
    bo.ceres.solver_options.num_threads = threads
    bo.refine_focal_length = focal
    bo.refine_principal_point = principal_point
    bo.refine_extra_params = extra
    bo.print_summary = os.environ.get("TEXSTREAM_COLMAP_LOG") == "1"
    with colmap_quiet():  # pycolmap's bundle adjustment resets glog's level on every call
        pycolmap.bundle_adjustment(rec, bo)


def select_distortion(rec: Any, cfg, free: bool) -> tuple[Any, dict]:
    """Self-calibration's model choice: the cameras made pinhole (distortion 0, focal length and poses
    re-adjusted) unless the estimated distortion lowers the mean reprojection error by at least
    ``cfg.min_self_calibration_gain``. Radial distortion and focal length trade against each other
    on tracks that do not reach the image corners; a term the tracks do not need then bends the
    focal length and the poses (see the option's help). Returns (the reconstruction to keep, report)."""
    import pycolmap

    info: dict[str, Any] = {"min_gain": cfg.min_self_calibration_gain}
    distorted = {cid: c for cid, c in rec.cameras.items()
                 if c.model.name in PINHOLE_OF and any(abs(float(v)) > 0 for v in
                                                       np.asarray(c.params)[PINHOLE_OF[c.model.name][1]:])}
    if not free:
        info.update(kept="given", reason="intrinsics are calibrated and fixed")
        return rec, info
    if not distorted:
        info.update(kept="pinhole", reason="no camera has an estimated distortion")
        return rec, info
    if cfg.min_self_calibration_gain <= 0:
        info.update(kept="distortion", reason="--min-self-calibration-gain 0: every estimate kept")
        return rec, info
    pin = pycolmap.Reconstruction(rec)
    for cid, c in distorted.items():
        model, n = PINHOLE_OF[c.model.name]
        cam = pin.cameras[cid]
        params = np.asarray(c.params, np.float64)
        cam.model = getattr(pycolmap.CameraModelId, model)
        cam.params = params[:n].tolist()
    bundle_adjust(pin, focal=True, principal_point=False, extra=False, threads=cfg.mapping_threads)
    err_d, err_p = float(rec.compute_mean_reprojection_error()), float(pin.compute_mean_reprojection_error())
    gain = (err_p - err_d) / err_p if err_p > 0 else 0.0
    info.update(reprojection_error_distortion=err_d, reprojection_error_pinhole=err_p, gain=gain,
                distortion={str(cid): [float(v) for v in np.asarray(c.params)[PINHOLE_OF[c.model.name][1]:]]
                            for cid, c in distorted.items()})
    if gain >= cfg.min_self_calibration_gain:
        info.update(kept="distortion", reason=f"the distortion lowers the mean reprojection error by {100 * gain:.2f}% "
                    f"(at least {100 * cfg.min_self_calibration_gain:g}% asked)")
        return rec, info
    info.update(kept="pinhole", reason=f"the distortion lowers the mean reprojection error by only {100 * gain:.3f}% "
                f"(less than {100 * cfg.min_self_calibration_gain:g}%): pinhole cameras, focal length re-adjusted")
    return pin, info


def refine_principal_point(rec: Any, cfg, free: bool) -> tuple[Any, dict]:
    """Final global bundle adjustment that also refines the principal point (and focal length and
    distortion); returns (the reconstruction to keep, report entry with the decision and its reason)."""
    import pycolmap

    n_img, n_pts = rec.num_reg_images(), rec.num_points3D()
    info: dict[str, Any] = {"mode": cfg.refine_principal_point}
    if not free:
        info.update(refined=False, reason="intrinsics are calibrated and fixed (pass --refine-intrinsics to free them)")
        return rec, info
    if cfg.refine_principal_point == "off":
        info.update(refined=False, reason="off")
        return rec, info
    if cfg.refine_principal_point == "auto" and (n_img < 8 or n_pts < 500):
        info.update(refined=False, reason=f"auto: {n_img} photo(s) and {n_pts} point(s) registered, fewer than 8 and "
                    "500 needed to pin the principal point down")
        return rec, info
    before = {cid: (float(c.principal_point_x), float(c.principal_point_y)) for cid, c in rec.cameras.items()}
    out = pycolmap.Reconstruction(rec)
    err0 = float(rec.compute_mean_reprojection_error())
    with phase("register", "global bundle adjustment with the principal point free"):
        bundle_adjust(out, focal=True, principal_point=True, extra=True, threads=cfg.mapping_threads)
    err1 = float(out.compute_mean_reprojection_error())
    cams = {}
    for cid, c in out.cameras.items():
        off = max(abs(c.principal_point_x - c.width / 2) / c.width, abs(c.principal_point_y - c.height / 2) / c.height)
        cams[str(cid)] = {"before": [round(v, 3) for v in before[cid]],
                          "after": [round(float(c.principal_point_x), 3), round(float(c.principal_point_y), 3)],
                          "off_centre_fraction": round(float(off), 4)}
        if not off <= 0.1:
            info.update(refined=False, cameras=cams,
                        reason=f"rejected: camera {cid}'s principal point went {100 * off:.0f}% of the image off centre")
            return rec, info
    gain = (err0 - err1) / err0 if err0 > 0 else 0.0
    info.update(cameras=cams, reprojection_error_before=err0, reprojection_error_after=err1)
    if cfg.refine_principal_point == "auto" and gain < cfg.min_self_calibration_gain:
        # the image centre explains the tracks as well: a free principal point only trades against the poses
        # (the synthetic sphere's cy moved 2.6 px at 0.01% lower error)
        info.update(refined=False, reason=f"auto: the refined principal point lowers the mean reprojection error by "
                    f"only {100 * gain:.3f}% (less than {100 * cfg.min_self_calibration_gain:g}%): kept at the centre")
        return rec, info
    info.update(refined=True, reason=f"{cfg.refine_principal_point}: {n_img} photos, {n_pts} points registered, "
                f"mean reprojection error {100 * gain:.2f}% lower")
    return out, info


def hold_focal_prior(rec: Any, priors: dict[int, float], cfg, principal_point: bool,
                     extra: bool) -> tuple[Any, dict]:
    """The focal length held at the EXIF prior (poses and points re-adjusted) unless refining it lowers the mean
    reprojection error by at least ``cfg.min_self_calibration_gain``.

    On an object in the middle of the frame, seen from cameras at about one distance, the focal length trades
    against that distance: the tracks barely tell them apart, and bundle adjustment drifts along the valley. The
    flash sphere (72 cameras on two rings) came out 2.9% short at a 0.26% lower error than at the EXIF value,
    which was 0.5% off; the mesh then came out 2.5% too large against the cameras. A stale or wrong prior
    costs far more than the threshold when held (held 3% off: 6-9% higher error on that capture), so the
    photos free it. ``priors``: camera id -> the prior's focal length (px); held only when every camera of the
    model has one. ``principal_point`` / ``extra``: whether the chosen model refines them (they stay free).
    Returns (the reconstruction to keep, report)."""
    import pycolmap

    info: dict[str, Any] = {"min_gain": cfg.min_self_calibration_gain}
    missing = [cid for cid in rec.cameras if cid not in priors]
    if missing:
        info.update(held=False, reason=f"camera(s) {missing} have no EXIF focal prior: the focal length refined")
        return rec, info
    held = pycolmap.Reconstruction(rec)
    free_focal = {}
    for cid, cam in held.cameras.items():
        free_focal[str(cid)] = round(float(cam.mean_focal_length()), 2)
        idx = set(cam.focal_length_idxs())
        cam.params = [priors[cid] if i in idx else float(v) for i, v in enumerate(cam.params)]
    with phase("register", "bundle adjustment with the focal length held at the EXIF prior"):
        bundle_adjust(held, focal=False, principal_point=principal_point, extra=extra,
                      threads=cfg.mapping_threads)
    err_free, err_held = float(rec.compute_mean_reprojection_error()), float(held.compute_mean_reprojection_error())
    gain = (err_held - err_free) / err_held if np.isfinite(err_held) and err_held > 0 else np.inf
    info.update(prior_focal_px={str(k): round(float(v), 2) for k, v in priors.items()}, free_focal_px=free_focal,
                reprojection_error_free=err_free,
                reprojection_error_held=err_held if np.isfinite(err_held) else None,
                gain=gain if np.isfinite(gain) else None)
    if gain < cfg.min_self_calibration_gain:
        info.update(held=True, reason=f"refining the focal length lowers the mean reprojection error by only "
                    f"{100 * gain:.3f}% (less than {100 * cfg.min_self_calibration_gain:g}%): held at the EXIF prior")
        return held, info
    info.update(held=False, reason=("refining the focal length lowers the mean reprojection error by "
                                    f"{100 * gain:.2f}%" if np.isfinite(gain) else "bundle adjustment at the prior "
                                    "failed") + ": the EXIF prior is off, the focal length refined")
    return rec, info
