"""Lights: a lights file per photo, and a light fixed to the camera (flash / co-located).

Lights file (JSON, world frame, conventions of :mod:`texstream.capture.conventions`)::

    {"default": {"type": "point", "position": [x, y, z], "intensity": [r, g, b]},
     "frames": {"IMG_0001": {"type": "directional", "direction": [..], "intensity": [..]}}}

Frames are matched by file name or stem; ``default`` applies to the others. A co-located light
(``--colocated-light INTENSITY``) is a point light at the camera centre, or at ``offset`` in the
camera's OpenCV axes (a flash beside the lens), derived from each registered pose.

Mirror-ball light estimation (``texstream lights CAPTURE -o OUT``): photos of a mirror sphere with
known camera poses. The ball is a known world sphere (``--sphere X Y Z R``, several balls allowed)
or is found per photo from a ball mask (``--ball-masks DIR``: the silhouette's viewing cone gives
the ball's direction and angular radius exactly under perspective; ``--ball-radius`` gives its
distance). In each photo the highlight is the brightest blob inside the ball's disc (pixels above
``threshold`` x peak luminance connected to the peak), located to sub-pixel precision by its
intensity-weighted centroid. The view ray through it is reflected about the sphere's normal at
the hit point: the reflected ray points at the light. Several rays are intersected in the
least-squares sense for a point light; when they are (nearly) parallel the light is directional
(their mean). ``OUT/lights.json`` is a lights file (``default`` light) that ``ingest --lights``
accepts (this folder or the file); ``OUT/lights_report.json`` lists every highlight and ray.
"""

from __future__ import annotations

import dataclasses
import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from texstream.capture.capture_json import (Capture, Frame, Intrinsics, Light, _light_from, flash_fired,
                                            read_capture, write_capture)
from texstream.capture.imageio import read_image, read_mask
from texstream.core.errors import ConfigError, InputError, StageError
from texstream.core.config import option, save_config
from texstream.core.outputs import StageResult, atomic_output_dir, read_json, write_json_atomic
from texstream.core.progress import say
from .colmap_io import opencv_distortion

LIGHTS_FILE = "lights.json"
REPORT_FILE = "lights_report.json"


def load_lights_file(path: str | os.PathLike) -> tuple[Light | None, dict[str, Light]]:
    """Read a lights file (or a 'texstream lights' output folder): (default light or None, {frame name or stem: light})."""
    p = Path(path)
    if p.is_dir():  # the output folder of 'texstream lights'
        p = p / LIGHTS_FILE
    data = read_json(p, what="lights file")
    if not isinstance(data, dict) or not ("default" in data or "frames" in data):
        raise InputError("lights file needs a 'default' light and/or a 'frames' mapping", p,
                         'write {"default": {"type": "point", "position": [..], "intensity": [..]}}')
    default = _light_from(data["default"], "default", p) if data.get("default") else None
    frames = {str(k): _light_from(v, f"frames[{k!r}]", p) for k, v in (data.get("frames") or {}).items()}
    return default, frames


def photo_lights(path: str | os.PathLike | None, no_flash: set[str]):
    """``light(stem, file_name)``: a photo's light from the lights file ``path`` (None: none), its own entry (by
    stem or file name) else the file's default. A photo taken with the flash off (``no_flash``: their file names,
    capture_json.py ``no_flash``) is lit by the room alone, so the default (a blanket light for every photo) reaches
    it at intensity 0, said in one line; an entry of its own that gives it light contradicts the marking, and which
    of the two is wrong only the user knows: refused, before any photo is written."""
    default, frames = load_lights_file(path) if path else (None, {})
    zeroed = 0
    for file_name in sorted(no_flash):
        own = frames.get(Path(file_name).stem) or frames.get(file_name)
        if own is not None and np.any(own.intensity):
            raise InputError(f"photo {file_name} was taken with the flash off (no_flash) but the lights file gives "
                             "it a light of its own", path, "remove its entry from the lights file (the room lights "
                             "it alone), or mark the no-flash photos with --no-flash GLOB (it overrides the EXIF "
                             "Flash tag)")
        zeroed += own is None and default is not None and bool(np.any(default.intensity))
    if zeroed:
        say("ingest", f"--lights: the default light at intensity 0 on the {zeroed} photo(s) taken with the flash off "
                      "(the room lights them alone)")

    def light(stem: str, file_name: str) -> Light | None:
        chosen = frames.get(stem) or frames.get(file_name) or default
        return unlit(chosen) if chosen is not None and file_name in no_flash else chosen

    return light


def unlit(light: Light) -> Light:
    """``light`` at intensity 0 (in place, the same kind): a photo's light whose flash did not fire."""
    return dataclasses.replace(light, intensity=np.zeros(3))


def colocated_light(r: np.ndarray, t: np.ndarray, intensity, offset=(0.0, 0.0, 0.0), fired: bool = True) -> Light:
    """Point light fixed to a camera with world-to-camera (R, t): at the centre plus ``offset`` (camera axes);
    intensity 0 for a photo whose flash did not fire (``fired`` False: a no-flash photo, which the room lights
    alone; capture_json.py ``no_flash``)."""
    r = np.asarray(r, dtype=np.float64)
    pos = r.T @ (np.asarray(offset, dtype=np.float64).reshape(3) - np.asarray(t, dtype=np.float64).reshape(3))
    inten = np.broadcast_to(np.asarray(intensity, dtype=np.float64), (3,)) * (1.0 if fired else 0.0)
    return Light.point(pos, inten)



# ---------------------------------------------------------------------------------- mirror ball


@dataclasses.dataclass
class LightsConfig:
    """Options of mirror-ball light estimation (``texstream lights``)."""

    sphere: tuple[float, ...] | None = option(None, help="mirror ball(s) in world units: X Y Z RADIUS, repeated for "
                                              "several balls (else --ball-masks)")
    ball_masks: str | None = option(None, help="folder of ball masks NAME.png (one ball per photo, white on black) "
                                    "when the ball's position is not known")
    ball_radius: float | None = option(None, help="ball radius in world units for --ball-masks (needed for a point "
                                       "light; without it only a direction is found)", min=1e-12)
    frames: tuple[str, ...] | None = option(None, help="names or stems of the photos that show the ball (default: all)")
    kind: str = option("auto", help="light to estimate: point (triangulated), directional (mean reflected ray), "
                       "auto (point when the rays converge with enough parallax, else directional)",
                       choices=("auto", "point", "directional"))
    min_parallax_deg: float = option(2.0, help="smallest angle between reflected rays that triangulates a point light",
                                     min=0.0, max=180.0)
    threshold: float = option(0.5, help="highlight blob: pixels above this fraction of the peak luminance, "
                              "connected to the peak", min=0.0, max=1.0)
    min_contrast: float = option(4.0, help="a highlight's peak must exceed this multiple of the ball's median "
                                 "luminance (else the photo is reported as having no highlight)", min=0.0)
    rim_margin: float = option(0.03, help="ignore this fraction of the ball's angular radius at its rim "
                               "(grazing reflections of the background)", min=0.0, max=1.0)
    intensity: tuple[float, ...] = option((1.0,), help="intensity written for the light (one value or RGB); a "
                                          "mirror ball gives its position, not its strength", min=0.0)


@dataclasses.dataclass
class BallView:
    """One ball seen in one photo: its world sphere (or scale-free cone) and the highlight."""

    frame: str
    ball: int
    centre: np.ndarray       # (3,) world centre (world units; unit-scale guess when the radius is unknown)
    radius: float            # world units (1 / sin(alpha) scale when unknown)
    metric: bool             # centre/radius in world units (False: direction-only)
    pixel: np.ndarray        # (2,) highlight centroid, continuous pixel coordinates (centres at +0.5)
    peak: float              # highlight peak luminance
    contrast: float          # peak / median luminance on the ball
    blob_pixels: int
    origin: np.ndarray       # (3,) reflection point on the ball (world)
    direction: np.ndarray    # (3,) unit reflected ray: from the ball towards the light (world)

    def to_json(self) -> dict:
        return {"frame": self.frame, "ball": self.ball, "pixel": [float(x) for x in self.pixel],
                "peak": self.peak, "contrast": self.contrast, "blob_pixels": self.blob_pixels,
                "ball_centre": [float(x) for x in self.centre], "ball_radius": self.radius, "metric": self.metric,
                "origin": [float(x) for x in self.origin], "direction": [float(x) for x in self.direction]}


def pixel_rays(intr: Intrinsics, uv: np.ndarray) -> np.ndarray:
    """Unit viewing rays in camera (OpenCV) axes through continuous pixel coordinates.

    Args:
        intr: camera intrinsics (distortion removed with OpenCV when present).
        uv: (N, 2) pixel coordinates, pixel centres at +0.5 (capture/conventions.py).

    Returns:
        (N, 3) unit vectors.
    """
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    if intr.distortion and any(abs(v) > 0 for v in intr.distortion.values()):
        import cv2

        k, d = opencv_distortion(intr)
        pts = (uv - 0.5).reshape(-1, 1, 2)
        if intr.camera_model == "OPENCV_FISHEYE":
            xy = cv2.fisheye.undistortPoints(pts, k, d).reshape(-1, 2)
        else:
            xy = cv2.undistortPoints(pts, k, d).reshape(-1, 2)
    else:
        xy = np.stack([(uv[:, 0] - intr.cx) / intr.fx, (uv[:, 1] - intr.cy) / intr.fy], 1)
    rays = np.concatenate([xy, np.ones((len(xy), 1))], 1)
    return rays / np.linalg.norm(rays, axis=1, keepdims=True)


def _all_pixel_rays(intr: Intrinsics) -> np.ndarray:
    u, v = np.meshgrid(np.arange(intr.width) + 0.5, np.arange(intr.height) + 0.5)
    return pixel_rays(intr, np.stack([u.ravel(), v.ravel()], 1)).reshape(intr.height, intr.width, 3)


def ball_cone_from_mask(mask: np.ndarray, intr: Intrinsics, where: Any = None) -> tuple[np.ndarray, float]:
    """The viewing cone of a ball from its silhouette: centre direction (camera axes) and half-angle.

    Silhouette rays b satisfy b . c = cos(alpha) for the ball's centre direction c; the boundary
    points are the midpoints between neighbouring inside / outside pixel centres (unbiased), and
    b . x = 1 is solved in least squares with x = c / cos(alpha). Exact under perspective, unlike
    a circle fit of the (elliptical) image of the ball.

    Args:
        mask: (H, W) bool ball mask.
        intr: the photo's intrinsics.
        where: file named in errors.

    Returns:
        (c (3,) unit vector in OpenCV camera axes, alpha in radians).
    """
    m = np.asarray(mask, dtype=bool)
    if m.sum() < 20:
        raise InputError(f"ball mask has {int(m.sum())} pixel(s); the ball must cover at least 20", where,
                         "paint the whole ball white in its mask")
    ys, xs = np.nonzero(m[:, :-1] != m[:, 1:])
    yv, xv = np.nonzero(m[:-1, :] != m[1:, :])
    uv = np.concatenate([np.stack([xs + 1.0, ys + 0.5], 1), np.stack([xv + 0.5, yv + 1.0], 1)])
    touches = m[0].any() or m[-1].any() or m[:, 0].any() or m[:, -1].any()
    if len(uv) < 12 or touches:
        raise InputError("the ball's outline is not fully inside the photo" if touches else "ball mask too small",
                         where, "use photos that show the whole ball")
    b = pixel_rays(intr, uv)
    x, *_ = np.linalg.lstsq(b, np.ones(len(b)), rcond=None)
    n = float(np.linalg.norm(x))
    if not n > 1.0:
        raise InputError("ball mask is not a disc (its outline fits no sphere)", where, "check the mask")
    return x / n, math.acos(1.0 / n)


def highlight_centroid(image: np.ndarray, region: np.ndarray, threshold: float = 0.5
                       ) -> tuple[np.ndarray, float, float, int] | None:
    """Sub-pixel centroid of the brightest blob inside a region.

    Args:
        image: (H, W, 3) or (H, W) linear image.
        region: (H, W) bool, where to look (the ball's disc).
        threshold: blob = pixels above ``threshold * peak`` connected (8-neighbours) to the peak.

    Returns:
        (uv (2,) continuous pixel coordinates, peak luminance, contrast = peak / median luminance in
        the region, blob pixel count), or None when the region is empty or black.
    """
    from scipy import ndimage

    img = np.asarray(image, dtype=np.float64)
    lum = img if img.ndim == 2 else img[..., :3] @ np.array([0.2126, 0.7152, 0.0722])
    reg = np.asarray(region, dtype=bool)
    if not reg.any():
        return None
    vals = np.where(reg, lum, -np.inf)
    peak_idx = np.unravel_index(int(np.argmax(vals)), vals.shape)
    peak = float(lum[peak_idx])
    if not peak > 0:
        return None
    level = threshold * peak
    labels, _ = ndimage.label(reg & (lum >= level), structure=np.ones((3, 3)))
    blob = labels == labels[peak_idx]
    w = (lum - level)[blob]
    ys, xs = np.nonzero(blob)
    if w.sum() <= 0:  # flat (clipped) blob: plain centroid
        w = np.ones_like(w)
    uv = np.array([(xs + 0.5) @ w / w.sum(), (ys + 0.5) @ w / w.sum()])
    med = float(np.median(lum[reg]))
    return uv, peak, peak / max(med, 1e-12), int(blob.sum())


def reflect_at_sphere(origin: np.ndarray, ray: np.ndarray, centre: np.ndarray, radius: float
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Hit point of a ray on a sphere and the mirror-reflected direction there.

    A ray that just misses (a highlight centroid at the very rim) is taken at its closest approach,
    projected onto the sphere.

    Args:
        origin: (3,) ray origin (camera centre). ray: (3,) unit direction.
        centre, radius: the sphere.

    Returns:
        (hit point (3,), unit reflected direction (3,)).
    """
    o, d, c = (np.asarray(a, dtype=np.float64).reshape(3) for a in (origin, ray, centre))
    d = d / np.linalg.norm(d)
    oc = o - c
    b = float(oc @ d)
    disc = b * b - (float(oc @ oc) - radius * radius)
    s = -b - math.sqrt(disc) if disc >= 0 else -b
    p = o + s * d
    n = p - c
    n /= np.linalg.norm(n)
    p = c + radius * n
    r = d - 2.0 * float(d @ n) * n
    return p, r / np.linalg.norm(r)


def triangulate_rays(origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares closest point to several 3D lines, and each line's distance to it.

    Args:
        origins: (N, 3) points on the lines. directions: (N, 3) unit directions.

    Returns:
        (point (3,), distances (N,)).
    """
    o = np.asarray(origins, dtype=np.float64)
    d = np.asarray(directions, dtype=np.float64)
    proj = np.eye(3)[None] - d[:, :, None] * d[:, None, :]  # (N, 3, 3) projectors off each line
    x = np.linalg.solve(proj.sum(0), np.einsum("nij,nj->i", proj, o))
    dist = np.linalg.norm(np.einsum("nij,nj->ni", proj, x[None] - o), axis=1)
    return x, dist


def _world_balls(cfg: LightsConfig) -> list[tuple[np.ndarray, float]]:
    vals = list(cfg.sphere or ())
    if len(vals) % 4 or not vals:
        raise ConfigError(f"--sphere takes X Y Z RADIUS per ball, got {len(vals)} number(s)",
                          fix="give 4 numbers per ball, e.g. --sphere 0 0 0.5 0.05")
    balls = [(np.array(vals[i:i + 3], dtype=np.float64), float(vals[i + 3])) for i in range(0, len(vals), 4)]
    for c, r in balls:
        if not r > 0:
            raise ConfigError(f"ball radius {r} must be positive", fix="give X Y Z RADIUS with RADIUS > 0")
    return balls


def _ball_mask_file(folder: Path, frame: Frame) -> Path | None:
    stem, name = Path(frame.file_path).stem, Path(frame.file_path).name
    for c in (folder / f"{stem}.png", folder / f"{name}.png", folder / name):
        if c.is_file():
            return c
    return None


def observe_balls(frame: Frame, image: np.ndarray, cfg: LightsConfig, ball_mask: np.ndarray | None = None,
                  where: Any = None) -> list[BallView]:
    """Highlights and reflected rays of the ball(s) in one photo.

    Args:
        frame: posed frame (world-to-camera R, t; intrinsics).
        image: (H, W, 3) linear photo.
        cfg: options (world balls from ``cfg.sphere``, else ``ball_mask``).
        ball_mask: (H, W) bool mask of the ball when no world sphere is given.
        where: photo path named in errors.

    Returns:
        One :class:`BallView` per ball in view with a highlight. Raises InputError for a photo in
        which a ball is in view but has no highlight.
    """
    intr = frame.intrinsics
    if image.shape[:2] != (intr.height, intr.width):
        raise InputError(f"photo is {image.shape[1]}x{image.shape[0]}, its camera {intr.width}x{intr.height}", where,
                         "use the capture's own (undistorted) photos")
    cam_o = frame.center
    rays = _all_pixel_rays(intr)
    if cfg.sphere:
        balls = []
        for c, r in _world_balls(cfg):
            cc = frame.R @ c + frame.t
            dist = float(np.linalg.norm(cc))
            if cc[2] <= r or dist <= r:
                continue  # behind the camera or around it
            balls.append((cc / dist, math.asin(r / dist), c, r, True))
    else:
        if ball_mask is None:
            raise ConfigError("give the ball: --sphere X Y Z RADIUS, or --ball-masks DIR", where,
                              "see 'texstream lights --help'")
        cdir, alpha = ball_cone_from_mask(ball_mask, intr, where)
        # Without a radius the ball is placed at unit radius: directions are scale-free.
        r = float(cfg.ball_radius) if cfg.ball_radius else 1.0
        c_world = frame.R.T @ (cdir * r / math.sin(alpha) - frame.t)
        balls = [(cdir, alpha, c_world, r, bool(cfg.ball_radius))]
    out = []
    for k, (cdir, alpha, c_world, r, metric) in enumerate(balls):
        region = rays @ cdir > math.cos((1.0 - cfg.rim_margin) * alpha)
        if ball_mask is not None:
            region &= ball_mask
        if region.sum() < 20:
            continue  # the ball is out of frame or too small in this photo
        found = highlight_centroid(image, region, cfg.threshold)
        if found is None or found[2] < cfg.min_contrast:
            raise InputError(f"no highlight on ball {k} (peak/median {0 if found is None else found[2]:.2f} < "
                             f"{cfg.min_contrast:g})", where,
                             "check the ball's position (--sphere / mask) and that the light shows in the photo, "
                             "or lower --min-contrast")
        uv, peak, contrast, npx = found
        ray_w = frame.R.T @ pixel_rays(intr, uv[None])[0]
        p, refl = reflect_at_sphere(cam_o, ray_w, c_world, r)
        out.append(BallView(frame.name, k, c_world, r, metric, uv, peak, contrast, npx, p, refl))
    return out


def light_from_views(views: list[BallView], kind: str = "auto", min_parallax_deg: float = 2.0,
                     intensity=(1.0,)) -> tuple[Light, dict]:
    """One light from the reflected rays of all ball views.

    Args:
        views: observations (:func:`observe_balls`).
        kind: ``point``, ``directional`` or ``auto`` (point when the rays converge in front of every
            ball with at least ``min_parallax_deg`` between some pair, else directional).
        intensity: written into the light (one value or RGB).

    Returns:
        (Light, info) with ``kind``, ``parallax_deg`` (largest angle between rays), ``ray_distances``
        (point: each ray's distance to the point), ``spread_deg`` (directional: largest angle of a
        ray from the mean).
    """
    if not views:
        raise StageError("no ball with a highlight was seen in any photo",
                         fix="check --sphere / --ball-masks and --frames")
    inten = np.broadcast_to(np.asarray(intensity, dtype=np.float64).reshape(-1), (3,)) \
        if len(np.asarray(intensity).reshape(-1)) in (1, 3) else None
    if inten is None:
        raise ConfigError("--intensity takes one value or three (RGB)")
    d = np.stack([v.direction for v in views])
    o = np.stack([v.origin for v in views])
    cosines = np.clip(d @ d.T, -1.0, 1.0)
    parallax = float(np.degrees(np.arccos(cosines.min()))) if len(views) > 1 else 0.0
    info: dict[str, Any] = {"views": len(views), "parallax_deg": parallax}
    point_ok = len(views) >= 2 and parallax >= min_parallax_deg and all(v.metric for v in views)
    if kind == "point" or (kind == "auto" and point_ok):
        if not all(v.metric for v in views):
            raise ConfigError("a point light needs the balls' size: give --ball-radius (or --sphere)",
                              fix="or use --kind directional")
        if len(views) < 2 or parallax < min_parallax_deg:
            raise StageError(f"the reflected rays are {parallax:.2f} degrees apart (need {min_parallax_deg:g}) "
                             f"from {len(views)} view(s): the light is too far to triangulate",
                             fix="use --kind directional, or photograph the ball from farther apart / add a ball")
        x, dist = triangulate_rays(o, d)
        along = np.einsum("ni,ni->n", x[None] - o, d)
        if along.min() <= 0:
            if kind == "point":
                raise StageError("the reflected rays meet behind a ball (inconsistent highlights)",
                                 fix="check the ball positions and poses, or use --kind directional")
        else:
            info.update(kind="point", ray_distances=[float(v) for v in dist], rms_ray_distance=float(
                np.sqrt(np.mean(dist ** 2))))
            return Light.point(x, inten), info
    mean = d.mean(0)
    mean /= np.linalg.norm(mean)
    info.update(kind="directional", spread_deg=float(np.degrees(np.arccos(np.clip(d @ mean, -1, 1))).max()))
    return Light.directional(-mean, inten), info  # 'direction' is where the light travels


def estimate_lights(capture: str | os.PathLike, out: str | os.PathLike,
                    config: LightsConfig | None = None) -> StageResult:
    """Estimate the light from mirror-ball photos of a posed capture (see the module doc).

    Args:
        capture: posed capture folder (``capture.json`` with camera poses, e.g. from ``register``).
        out: output folder: ``lights.json``, ``lights_report.json``, ``lights_config.json``.
        config: options.

    Returns:
        StageResult; summary has ``light`` (its JSON), ``kind``, ``views``, ``parallax_deg``,
        ``skipped`` (photos with no ball in view).

    Raises:
        InputError: missing capture / photo / ball mask, a ball without a highlight. ConfigError:
        no ball given. StageError: no usable view, or a point light that cannot be triangulated.
    """
    cfg = config or LightsConfig()
    capture = Path(capture)
    if not cfg.sphere and not cfg.ball_masks:
        raise ConfigError("give the ball: --sphere X Y Z RADIUS (known position), or --ball-masks DIR", capture,
                          "see 'texstream lights --help'")
    if cfg.sphere:
        _world_balls(cfg)  # validate before reading photos
    cap = read_capture(capture)
    frames = cap.frames
    if cfg.frames:
        want = set(cfg.frames)
        frames = [f for f in frames if f.name in want or Path(f.file_path).name in want]
        missing = want - {f.name for f in frames} - {Path(f.file_path).name for f in frames}
        if missing:
            raise InputError(f"--frames names photo(s) not in the capture: {sorted(missing)[:5]}", capture / "capture.json",
                             "use frame names (file stems) from capture.json")
    mask_dir = Path(cfg.ball_masks) if cfg.ball_masks else None
    if mask_dir is not None and not mask_dir.is_dir():
        raise InputError("ball mask folder not found", mask_dir, "give the folder holding NAME.png ball masks")
    views: list[BallView] = []
    skipped: list[dict] = []
    for f in frames:
        path = cap.image_path(f)
        if not path.is_file():
            raise InputError("photo listed in capture.json is missing", path, "restore it or drop it with --frames")
        bm = None
        if mask_dir is not None:
            mp = _ball_mask_file(mask_dir, f)
            if mp is None:
                skipped.append({"frame": f.name, "reason": "no ball mask"})
                continue
            bm = read_mask(mp, (f.intrinsics.height, f.intrinsics.width)) > 0
        got = observe_balls(f, read_image(path, channels=3), cfg, bm, path)
        if not got:
            skipped.append({"frame": f.name, "reason": "no ball in view"})
        views += got
    light, info = light_from_views(views, cfg.kind, cfg.min_parallax_deg, cfg.intensity)
    report = {"capture": str(capture), "light": light.to_json(), **info, "skipped": skipped,
              "observations": [v.to_json() for v in views]}
    with atomic_output_dir(out) as tmp:
        write_json_atomic(tmp / LIGHTS_FILE, {"default": light.to_json()})
        write_json_atomic(tmp / REPORT_FILE, report)
        save_config(cfg, tmp / "lights_config.json")
    summary = {"light": light.to_json(), "kind": info["kind"], "views": len(views), "parallax_deg": info["parallax_deg"],
               "skipped": skipped, "rms_ray_distance": info.get("rms_ray_distance"), "spread_deg": info.get("spread_deg")}
    return StageResult(output=Path(out), summary=summary)


def lit_capture(posed_dir: Path, out: Path, lcfg: LightsConfig) -> StageResult:
    """The run's lights stage: estimate the light from the ball photos (``OUT/lights.json``, report) and
    write ``OUT/capture.json``: the posed capture's other photos, every one with that light (image paths
    relative to ``OUT``, so no image is copied)."""
    cap = read_capture(posed_dir)
    balls = set(lcfg.frames or ())
    keep = [f for f in cap.frames if not ({f.name, Path(f.file_path).name} & balls)]
    if len(keep) < 1:
        raise InputError("every photo is a ball photo (lights.frames): none is left to fit", posed_dir / "capture.json",
                         "name only the mirror-ball photos in --mirror-ball-frames")
    res = estimate_lights(posed_dir, out, lcfg)
    light = _light_from(res.summary["light"], "light", out / "lights.json")

    def rel(p: str) -> str:
        return os.path.relpath(posed_dir / p, out)

    frames = []
    for f in keep:  # the room alone lights a photo taken with the flash off: the ball's light at 0 there
        frames.append(dataclasses.replace(f, file_path=rel(f.file_path),
                                          light=light if flash_fired(f) else unlit(light),
                                          mask_path=None if f.mask_path is None else rel(f.mask_path)))
    dark = sum(not flash_fired(f) for f in keep)
    if dark:
        say("lights", f"the mirror ball's light at intensity 0 on the {dark} photo(s) taken with the flash off (the "
                      "room lights them alone)")
    extra = dict(cap.extra)
    extra["lights_source"] = f"mirror ball ({res.summary['kind']} light, {res.summary['views']} ball view(s))"
    write_capture(Capture(root=out, frames=frames, extra=extra), out)
    res.summary["photos"] = len(frames)
    res.summary["ball_photos"] = len(cap.frames) - len(frames)
    return res
