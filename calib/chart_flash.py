"""The flash's intensity in absolute units from a ColorChecker in view (issue 39).

Without it a flash capture's albedos have no scale: the intensity is a number the user guesses, taken as the
irradiance at the object's median distance. The chart has known reflectances, so its patches measure the flash's
irradiance where it lies, once their codes are linear (the capture's response, fitted to the same chart:
:mod:`.colour_chart`) and the chart's distance and angle to the flash are known:

1. **The chart's pose in each photo**: ``cv2.solvePnP`` on the 24 patch centres the detector found against the
   chart's patch grid (a square grid: its pitch is the model's unit, so a Classic, a Mini or a Passport alike),
   with the photo's intrinsics: the chart's rotation and its position in pitch units.
2. **Its scale in the capture's units**: every registered camera puts the chart's centre at
   ``R^T (s C - t)`` (``C`` its PnP position, ``s`` world units per pitch): one least-squares solve for ``s`` and
   the centre makes them agree (SfM's arbitrary scale included), and their spread says how well they do.
3. **The intensity**: each usable patch (code within the response's range) of each photo gives
   ``pi L / (rho exposure) = I cos / r^2 + E_room`` (``L`` the linearised code, ``rho`` the patch's reflectance,
   ``r`` and ``cos`` the patch's distance and angle to the flash at the camera plus its offset): a line per
   channel in ``x = cos / r^2``, whose slope is the flash's intensity and whose intercept is the room's light on
   the chart, solved robustly (patches the object hides in a photo are outliers). When the photos' ``x`` barely
   varies the intercept is not told apart from the slope: the room's term is then left out, and the summary says so.
   A photo taken with the flash off (capture_json.py ``no_flash``) has ``x = 0``: its patches measure the room's
   light alone, the line's intercept, and leave the slope (the flash) to the flash photos.

The intensity is in the capture's world units and the response's radiance units: the units the fit's lights
need, so fitted albedos come out absolute. OpenCV is imported inside the functions that need it.
"""

from __future__ import annotations

import dataclasses
import math
import os
from pathlib import Path

import numpy as np

from texstream.capture.capture_json import Capture, flash_fired, read_capture, write_capture
from texstream.core.errors import InputError
from texstream.core.outputs import StageResult, atomic_output_dir, write_json_atomic

from .colour_chart import USABLE_CODES, ChartSighting, chart_reflectance
from .lights import colocated_light

MIN_X_SPREAD = 1.3
"""the ratio of the largest to the smallest ``cos / r^2`` over the patches from which the room's light on the chart
is fitted beside the flash (below it the two are nearly one unknown)"""
OUTLIER_RELATIVE = 0.05
"""a patch whose value misses the fitted line by more than this fraction (and 3 median deviations) is dropped:
the object or the chart's stand hides it, or a highlight on the chart"""


MAX_PNP_RMS_PX = 1.5
"""a sighting whose patch centres miss the planar pose by more than this (RMS, pixels) is misread (a chart partly
hidden by the object: the detector fills in the patches it cannot see)"""
MAX_CENTRE_DEVIATION = 0.03
"""a photo whose chart centre lies further than this fraction of its distance from the others' (and 3 median
deviations) is left out of the scale and the intensity"""


def chart_grid() -> np.ndarray:
    """(24, 3) the patch centres on the chart's plane in patch-pitch units, centred, in the detector's patch order
    (row-major, 6 columns by 4 rows), z = 0."""
    i = np.arange(24)
    return np.stack([(i % 6) - 2.5, (i // 6) - 1.5, np.zeros(24)], axis=1).astype(np.float64)


def chart_pose(sighting: ChartSighting, intrinsics) -> tuple[np.ndarray, np.ndarray, float]:
    """(R, t, reprojection RMS in pixels): the chart's plane in the camera's axes (OpenCV), ``t`` in patch-pitch
    units, from its patch centres (planar PnP, then refined)."""
    import cv2

    if sighting.patch_centres is None:
        raise InputError("the chart sighting has no patch centres", fix="re-run the ingest with this version")
    k = intrinsics.matrix().astype(np.float64)
    obj = chart_grid()
    # the detector's pixels have their centres at integers, the capture's at + 0.5 (capture/conventions.py)
    img = np.ascontiguousarray(sighting.patch_centres + 0.5, np.float64).reshape(-1, 1, 2)
    ok, rvec, tvec = cv2.solvePnP(obj, img, k, None, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        raise InputError("the chart's pose could not be solved from its patches")
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, k, None, rvec, tvec)
    proj, _ = cv2.projectPoints(obj, rvec, tvec, k, None)
    rms = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - img.reshape(-1, 2)) ** 2, axis=1))))
    return cv2.Rodrigues(rvec)[0], tvec.reshape(3), rms


@dataclasses.dataclass
class FlashFromChart:
    """What :func:`flash_from_chart` found: the flash's ``intensity`` (3,) in the capture's world and response
    units, the room's ``room_irradiance`` (3,) on the chart (zeros when not fitted), ``scale`` (world units per
    patch pitch), the chart's world ``centre``, how well the cameras agree on it (``centre_spread``: RMS over
    their distance), the patches used and dropped, the fit's RMS relative residual, per photo (name, distance
    to the chart, cos of the flash's angle on it, PnP reprojection RMS), and the photos left out (a chart partly
    hidden or misread: its pose disagrees with the others')."""

    intensity: np.ndarray
    room_irradiance: np.ndarray
    room_fitted: bool
    scale: float
    centre: np.ndarray
    centre_spread: float
    patches_used: int
    patches_dropped: int
    residual_percent: float
    photos: list
    dropped_photos: list

    def to_json(self) -> dict:
        return {"intensity": self.intensity.tolist(), "room_irradiance_on_chart": self.room_irradiance.tolist(),
                "room_fitted": self.room_fitted, "world_units_per_patch_pitch": self.scale,
                "chart_centre": self.centre.tolist(), "centre_spread": self.centre_spread,
                "patches_used": self.patches_used, "patches_dropped": self.patches_dropped,
                "residual_percent": self.residual_percent, "photos": self.photos,
                "dropped_photos": self.dropped_photos}


def _robust_line(x: np.ndarray, y: np.ndarray, with_intercept: bool) -> tuple[float, float, np.ndarray]:
    """(slope, intercept, kept rows) of y = a x + b by least squares relative to y (each row weighted 1 / y),
    refitted once without the outliers."""
    keep = np.ones(len(x), bool)
    for _ in range(3):
        a_mat = np.stack([x, np.ones_like(x)] if with_intercept else [x], axis=1) / y[:, None]
        sol, *_ = np.linalg.lstsq(a_mat[keep], np.ones(int(keep.sum())), rcond=None)
        rel = np.abs(a_mat @ sol - 1.0)
        mad = float(np.median(rel[keep]))
        new = rel <= max(OUTLIER_RELATIVE, 3.0 * 1.4826 * mad)
        if np.array_equal(new, keep):
            break
        keep = new
    return float(sol[0]), float(sol[1]) if with_intercept else 0.0, keep


def _chart_scale(seen: list, poses: list) -> tuple[float, np.ndarray]:
    """(world units per pitch, the chart's centre): s R_p^T C_p - X = R_p^T t_p over the photos, least squares."""
    rows, rhs = [], []
    for (f, _), (_, c, _) in zip(seen, poses):
        rt = np.asarray(f.R, np.float64).T
        block = np.zeros((3, 4))
        block[:, 0] = rt @ c
        block[:, 1:] = -np.eye(3)
        rows.append(block)
        rhs.append(rt @ np.asarray(f.t, np.float64))
    sol, *_ = np.linalg.lstsq(np.concatenate(rows), np.concatenate(rhs), rcond=None)
    if not sol[0] > 0:
        raise InputError("the chart's sightings put it behind the cameras", fix="check the photos' registration")
    return float(sol[0]), sol[1:]


def flash_from_chart(frames: list, sightings: dict, response, offset=(0.0, 0.0, 0.0)) -> FlashFromChart:
    """The flash's intensity (module doc) from ``sightings`` ({frame name: ChartSighting}) of the registered
    ``frames`` (capture Frames: poses, intrinsics, exposures), their codes linearised by ``response`` (a
    PhotoResponse), the flash at ``offset`` (camera axes, world units) from each camera centre.

    Raises:
        InputError: fewer than 2 photos see the chart (its scale needs two viewpoints), or too few usable patches.
    """
    by_name = {f.name: f for f in frames}
    seen = [(by_name[n], s) for n, s in sightings.items() if n in by_name]
    if len(seen) < 2:
        raise InputError(f"the colour chart is seen in {len(seen)} registered photo(s): its distance to the flash "
                         "needs 2 or more", fix="photograph the chart in view from several positions, or give "
                                                "--colocated-light")
    poses = [chart_pose(s, f.intrinsics) for f, s in seen]
    keep = np.array([rms <= MAX_PNP_RMS_PX for _, _, rms in poses])
    for _ in range(4):
        if keep.sum() < 2:
            raise InputError(f"the colour chart's pose is consistent in {int(keep.sum())} photo(s), fewer than 2",
                             fix="photograph the chart unobstructed from several positions, or give "
                                 "--colocated-light")
        scale, centre = _chart_scale([x for x, k in zip(seen, keep) if k], [p for p, k in zip(poses, keep) if k])
        dev = np.array([np.linalg.norm(np.asarray(f.R).T @ (scale * c - np.asarray(f.t)) - centre)
                        / (scale * np.linalg.norm(c)) for (f, _), (_, c, _) in zip(seen, poses)])
        new = keep & (dev <= max(MAX_CENTRE_DEVIATION, 3.0 * 1.4826 * float(np.median(dev[keep]))))
        if np.array_equal(new, keep):
            break
        keep = new
    spread = float(np.sqrt(np.mean(np.square(dev[keep]))))
    dropped_photos = [f.name for (f, _), k in zip(seen, keep) if not k]
    seen = [x for x, k in zip(seen, keep) if k]
    poses = [p for p, k in zip(poses, keep) if k]
    refl = chart_reflectance()
    off = np.asarray(offset, np.float64).reshape(3)
    xs, ys, chans, per_photo = [], [], [], []
    for (f, s), (r, t, rms) in zip(seen, poses):
        pts = scale * (chart_grid() @ r.T + t) - off  # patch centres from the flash, camera axes, world units
        dist = np.linalg.norm(pts, axis=1)
        cos = np.abs(pts @ r[:, 2]) / dist
        per_photo.append({"photo": f.name, "distance": float(np.mean(dist)), "cos": float(np.mean(cos)),
                          "pnp_rms_px": rms, "flash": flash_fired(f)})
        codes = np.asarray(s.patches, np.float64)
        usable = (codes >= USABLE_CODES[0]) & (codes <= USABLE_CODES[1])
        lin = np.asarray(response.linearise(codes), np.float64)
        y = math.pi * lin / refl / float(f.exposure)
        flash_x = cos / dist ** 2 * (1.0 if flash_fired(f) else 0.0)  # no flash: the room's light alone
        for ch in range(3):
            u = usable[:, ch]
            xs.append(flash_x[u])
            ys.append(y[u, ch])
            chans.append(np.full(int(u.sum()), ch))
    x, y, ch = np.concatenate(xs), np.concatenate(ys), np.concatenate(chans)
    if len(x) < 12:
        raise InputError(f"the colour chart gives {len(x)} usable patch values, too few for the flash's intensity",
                         fix="photograph the chart larger, exposed so its patches are neither black nor clipped")
    if not np.any(x > 0):
        raise InputError("the colour chart is seen only in photos taken with the flash off: the flash's intensity "
                         "needs it under the flash", fix="photograph the chart in view of flash photos too, or give "
                                                         "--colocated-light")
    room_fitted = float(x.max() / max(x.min(), 1e-30)) >= MIN_X_SPREAD
    intensity, room, kept = np.zeros(3), np.zeros(3), np.zeros(len(x), bool)
    resid = []
    for c in range(3):
        on = ch == c
        a, b, k = _robust_line(x[on], y[on], room_fitted)
        intensity[c], room[c] = a, b
        kept[np.flatnonzero(on)[k]] = True
        resid.append((a * x[on][k] + b) / y[on][k] - 1.0)
    resid = np.concatenate(resid)
    return FlashFromChart(intensity, room, room_fitted, scale, centre, spread, int(kept.sum()), int((~kept).sum()),
                          float(100.0 * np.sqrt(np.mean(resid ** 2))), per_photo, dropped_photos)


def camera_flash_offset(capture) -> list[float] | None:
    """The offset (camera axes) of a flash fixed to the camera, or None: ingest's ``colocated_light`` before the
    cameras are registered, else every frame's point light at one offset from its camera centre (what the
    registration gives a capture ingested with ``--colocated-light``)."""
    coloc = capture.extra.get("colocated_light")
    if isinstance(coloc, dict):
        return [float(v) for v in coloc.get("offset", [0.0, 0.0, 0.0])]
    lights = [f.light for f in capture.frames]
    if not lights or any(lt is None or lt.type != "point" for lt in lights):
        return None
    offsets = np.array([np.asarray(f.R) @ (np.asarray(f.light.position) - f.center) for f in capture.frames])
    span = max(float(np.ptp([f.center for f in capture.frames], axis=0).max()), 1e-12)
    if np.abs(offsets - offsets[0]).max() > 1e-6 * span:
        return None
    return offsets[0].tolist()


def chart_flash_applies(capture) -> bool:
    """Whether a posed capture can have its flash's intensity from the chart: a flash fixed to the camera
    (:func:`camera_flash_offset`), chart sightings (``colour_chart``, ingest's ``--response auto``) and the
    response fitted to the same chart (the patches' codes made linear in the fit's units)."""
    return (bool(capture.extra.get("colour_chart")) and capture.response is not None
            and camera_flash_offset(capture) is not None)


def flash_lit_capture(posed_dir: Path, out: Path) -> StageResult:
    """The run's lights stage for a flash capture with a chart in view: the flash's intensity from the chart
    (:func:`flash_from_chart`), ``OUT/flash.json`` (what it found) and ``OUT/capture.json``, the posed capture with
    every frame's flash at that intensity (image and mask paths relative to ``OUT``: nothing is copied)."""
    cap = read_capture(posed_dir)
    sightings = {n: ChartSighting.from_json(d) for n, d in cap.extra["colour_chart"].items()}
    offset = camera_flash_offset(cap)
    found = flash_from_chart(cap.frames, sightings, cap.response, offset)
    lit = [f for f in cap.frames if f.light is not None and flash_fired(f)]
    old = [float(v) for v in np.ravel(lit[0].light.intensity)] if lit else None

    def rel(p: str) -> str:
        return os.path.relpath(posed_dir / p, out)

    frames = [dataclasses.replace(f, file_path=rel(f.file_path), mask_path=None if f.mask_path is None else rel(f.mask_path),
                                  light=colocated_light(f.R, f.t, found.intensity, offset, flash_fired(f)))
              for f in cap.frames]
    summary = {"kind": "flash at the camera", "intensity": found.intensity.tolist(), "replaced": old,
               "photos_with_chart": len(sightings) - len(found.dropped_photos), "photos": len(frames),
               "room_irradiance_on_chart": found.room_irradiance.tolist(), "room_fitted": found.room_fitted,
               "residual_percent": found.residual_percent, "centre_spread": found.centre_spread,
               "why": (f"the colour chart in {len(sightings) - len(found.dropped_photos)} photos: its pose (solvePnP "
                       f"on its patches, scaled by the registered cameras to {found.centre_spread:.1%}) and its "
                       f"linearised patches fix the flash's intensity ({found.residual_percent:.2f}% RMS), so "
                       "albedos are absolute; replaces the intensity guessed from the object's distance")}
    extra = {**cap.extra, "lights_source": "flash at the camera, intensity from the colour chart"}
    with atomic_output_dir(out, overwrite=True) as tmp:
        write_json_atomic(tmp / "flash.json", {**found.to_json(), "why": summary["why"]})
        write_capture(Capture(root=tmp, frames=frames, extra=extra), tmp)
    return StageResult(output=out, summary=summary)
