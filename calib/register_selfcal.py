"""Self-calibration's choices after incremental mapping (:mod:`.register`): whether the estimated lens
distortion and a refined principal point are kept, each only where it lowers the reprojection error enough."""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from texstream.core.progress import phase

from .colmap_log import colmap_quiet


PINHOLE_OF = {"SIMPLE_RADIAL": ("SIMPLE_PINHOLE", 3), "RADIAL": ("SIMPLE_PINHOLE", 3),
              "OPENCV": ("PINHOLE", 4), "FULL_OPENCV": ("PINHOLE", 4)}  # model -> (pinhole model, params kept)


def bundle_adjust(rec: Any, focal: bool, principal_point: bool, extra: bool) -> None:
    import pycolmap

    bo = pycolmap.BundleAdjustmentOptions()
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
    bundle_adjust(pin, focal=True, principal_point=False, extra=False)
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
        bundle_adjust(out, focal=True, principal_point=True, extra=True)
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
