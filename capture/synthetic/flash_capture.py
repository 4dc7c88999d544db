"""A synthetic flash capture as a photographer leaves it (issue 39): a glossy object photographed with a flash on
the camera in a lit room, a ColorChecker on a stand beside it, exported as 8-bit PNGs through a tone curve.

``texstream synth flash_capture -o DIR`` writes it. The object is the ``flash_sphere`` scene (a sphere with a
value-noise albedo, SIFT's features, and one Lafortune lobe; the room's light adds rho_d E_room to every texel)
rendered by texstream's renderer with a point light at each camera centre. The chart stands on the table the
sphere stands on (z = -1, beside it), so it never hides the object while the object hides it from the far side;
it is drawn here by ray-plane intersection: each pixel's patch reflectance / pi x (the flash's irradiance there,
I cos / r^2, plus the room's on the chart). Each photo is the object where the renderer's mask says, the chart
(on black) elsewhere, with a little sensor noise in linear radiance, then :func:`filmic_codes` (a soft shoulder,
then sRGB's encoding) and 8-bit quantisation: the stored codes are neither linear nor sRGB.

Ground truth beside the photos, as for every synthetic set (``ground_truth/``: mesh, parameter maps, bake), and:

- ``capture.json``: the true cameras, the flash (its true intensity), masks of the object alone, and the true
  response (``response``: the tone curve's inverse, scaled so code 1 is radiance 1) with every frame's exposure
  1 / ``TONE_WHITE`` to match, so a fit of this capture works in the units a chart-fitted response gives (its
  curve is scaled the same way, :func:`texstream.calib.colour_chart.fit_response`) and their held-out PSNRs
  compare;
- ``ground_truth/flash.json``: the flash's intensity (scene units, and in those response units), the tone
  curve, the chart's corners in the world, the room's irradiance on the chart, the photo and atlas sizes;
- ``ground_truth/response.json``: the true response as ``texstream chart`` writes one (``--response FILE``).

With ``no_flash_pairs`` (``--no-flash-pairs``) every camera also takes a photo with the flash off, from the same
pose at the same exposure, as a photographer takes a flash/no-flash pair: ``images/frame_noflash_00003.png``
the pair of ``frame_00003.png``, the room's light alone on the sphere and the chart, its frame's flash at intensity 0
and marked ``no_flash`` (capture_json.py), the EXIF Flash tag written into both PNGs (0x9: fired; 0x10: not fired,
flash suppressed) so that ingest tells them apart without ``--no-flash``. The no-flash frames follow all the flash
frames in capture.json, as they do in name order (a photos-only run's), so a hold-out of every 8th frame with a
multiple of 8 photos holds out the flash photos it holds out without pairs and their pairs.

Two objects (``scene``). ``flash_sphere``, the first, is sampled more coarsely than issue 39 asks: its 24 photos of
400 px give about 1.3 pixels a texel of its 320x160 atlas in the median photo facing a texel (the issue: 4x the
pixels the atlas needs), and with cameras 18-27 degrees apart along its rings no texel sees its exponent-40
highlight in two photos: under a flash at the camera the lobe's 10%-of-peak cone about the normal is
acos(0.1^(1/40)) / 2 = 9.7 degrees. ``flash_sphere_resolved`` is the same sphere, texture, lobe, room and rings
photographed as the issue asks: 72 cameras, 36 a ring, so that neighbours along a ring are at most 8.8 degrees
apart, within the highlight's 9.7 (48% of the texels that see their highlight see it in 2+ training photos; more
rings would be needed for every texel; real flash captures of heritage objects take 50-200 photos), and a fit atlas
of 160x80 (:data:`FIT_ATLAS`, in ``ground_truth/flash.json``), which the photos cover at 5.0 pixels a texel in the
median facing photo. Its texture stays finer than that atlas, as a real object's is: the value noise changes
within a texel of the truth's 320x160 atlas, and SIFT registers the photos on it (340 features on the sphere a
photo). A texture band-limited to the fit's atlas left SIFT 12-29 (two soft octaves of 24x12 cells) or 80 (one
octave of 48x24 cells) features a photo, and the 80 registered every photo at a focal length 13% short (camera
RMS 0.21 against 0.01-0.03 on this texture); so the benchmarks score the albedo against the truth averaged over
each fitted texel. ``flash_sampling.scene_sampling`` computes these figures.
"""

from __future__ import annotations

import dataclasses
import math
import shutil
from pathlib import Path

import numpy as np

from texstream.capture.capture_json import NO_FLASH_KEY, Frame, Light, read_capture, write_capture
from texstream.capture.imageio import read_image, write_image
from texstream.capture.response import PhotoResponse
from texstream.core.config import option
from texstream.core.outputs import StageResult, atomic_output_dir, read_json, write_json_atomic
from texstream.geometry.bake import bake_texels
from texstream.geometry.mesh_io import load_mesh
from texstream.render.renderer import Renderer

from .colour_chart import chart_plane, filmic_codes, paste_chart
from .synth import GROUND_TRUTH, SynthConfig, load_ground_truth, synthesize

FLASH_CAPTURE = "flash_capture"
"""the name ``texstream synth`` takes for it"""
FLASH_SCENE = "flash_sphere"
"""the first object (module doc: its photos resolve neither its texture nor its highlights)"""
FLASH_SCENES = (FLASH_SCENE, "flash_sphere_resolved")
"""the objects the capture can show (module doc)"""
FIT_ATLAS = {FLASH_SCENE: None, "flash_sphere_resolved": (160, 80)}
"""the atlas a fit of each object is meant to use (None: the truth's own), the truth's mesh and UVs (module doc)"""
TONE_WHITE = 4.0
"""the tone curve's white: linear radiance 4 maps to code 1 (highlights keep some headroom, mid-tones are bent)"""
CHART_CENTRE = (0.0, -2.15, -0.8)
"""the chart's centre: on a low stand on the table beside the sphere"""
CHART_TILT_DEG = 15.0
"""the stand tilts the chart from lying flat towards -y (the cameras on that side see it nearly square on, those
across the sphere at a grazing angle or not at all)"""
CHART_WIDTH = 1.9
"""the chart's long side in scene units (the sphere's radius is 1); its short side follows the Classic's
layout (:func:`texstream.capture.synthetic.colour_chart.chart_plane`)"""
EXIF_FLASH_FIRED = 0x9
"""the EXIF Flash tag of a flash photo: fired (bit 0), compulsory flash mode (bits 3-4 = 1)"""
EXIF_FLASH_OFF = 0x10
"""the EXIF Flash tag of a no-flash photo: not fired, flash suppressed (bits 3-4 = 2)"""
NO_FLASH_NAME = "frame_noflash_"
"""a no-flash photo's name: its flash photo's ``frame_`` replaced by this, so the pairs share their number and, in
name order (ingest's), the no-flash photos follow the flash photos as they do in capture.json"""


@dataclasses.dataclass
class FlashCaptureConfig:
    """Options of the synthetic flash capture (``texstream synth flash_capture``: ``--photos``, ``--image-size``,
    ``--seed``, ``--noise``, ``--room-light``, ``--device``, ``--no-flash-pairs`` map onto these)."""

    scene: str = option(FLASH_SCENE, help="the object: flash_sphere (the first: coarser than the issue asks) or "
                                          "flash_sphere_resolved (sampled as issue 39 asks; module doc)",
                        choices=FLASH_SCENES)
    photos: int = option(0, help="photos, on two rings about the sphere and its chart (0: the scene's, 24 or 72)",
                         min=3, max=10000, also=(0,))
    image_size: int = option(400, help="photo width and height in pixels", min=64, max=16384)
    noise: float = option(0.002, help="sensor noise sigma in linear radiance before the tone curve", min=0.0, max=1.0)
    room_light: float = option(0.6, help="the room's irradiance (0: the flash alone)", min=0.0)
    flash: float = option(40.0, help="the flash's intensity (point light at each camera centre)", min=1e-6)
    seed: int = option(0, help="random seed of the sensor noise", min=0)
    no_flash_pairs: bool = option(False, help="each camera also takes a photo with the flash off (same pose and "
                                              "exposure): flash/no-flash pairs (module doc)")
    device: str = option("cpu", help="Warp device for baking and rendering")
    progress: bool = option(True, help="show a progress bar while rendering")


def flash_config(synth: SynthConfig) -> FlashCaptureConfig:
    """The flash capture's options from ``texstream synth``'s (those it has; the rest stay the defaults)."""
    d = FlashCaptureConfig()
    return FlashCaptureConfig(photos=synth.photos or d.photos, image_size=synth.image_size or d.image_size,
                              noise=d.noise if synth.noise is None else synth.noise,
                              room_light=d.room_light if synth.room_light is None else synth.room_light,
                              seed=synth.seed, device=synth.device, progress=synth.progress)


def chart_corners_world() -> np.ndarray:
    """(4, 3) the chart's corners on its stand in the order :func:`paste_chart` takes them (top-left, top-right,
    bottom-right, bottom-left of :func:`chart_plane`'s image), its top edge towards the sphere."""
    h, w = chart_plane().shape[:2]
    hx, hy = CHART_WIDTH / 2, CHART_WIDTH * h / w / 2
    tilt = math.radians(CHART_TILT_DEG)
    down = np.array([0.0, -math.cos(tilt), -math.sin(tilt)])  # from the top edge to the bottom edge
    right = np.array([1.0, 0.0, 0.0])
    c = np.asarray(CHART_CENTRE, np.float64)
    return np.array([c - hx * right - hy * down, c + hx * right - hy * down, c + hx * right + hy * down,
                     c - hx * right + hy * down])


def chart_normal() -> np.ndarray:
    """The chart's unit normal, towards the side it faces (up and towards -y)."""
    tilt = math.radians(CHART_TILT_DEG)
    return np.array([0.0, -math.sin(tilt), math.cos(tilt)])


def true_response(white: float = TONE_WHITE) -> PhotoResponse:
    """The inverse of :func:`filmic_codes` as a capture records a response, scaled so code 1 is radiance 1
    (radiance = the scene's / ``white``): knots spaced by ratio in the shadows and evenly over the shoulder, so the
    curve's interpolation between them (linear in log code) stays within ~0.05% of the exact inverse."""
    codes = np.unique(np.concatenate([np.geomspace(0.01, 0.5, 64), np.linspace(0.5, 1.0, 65)]))
    tone = np.where(codes <= 0.04045, codes / 12.92, ((codes + 0.055) / 1.055) ** 2.4)
    w2 = white * white
    # tone = x (1 + x / w^2) / (1 + x)  =>  x^2 / w^2 + x (1 - tone) - tone = 0
    x = (-(1.0 - tone) + np.sqrt((1.0 - tone) ** 2 + 4.0 * tone / w2)) * w2 / 2.0
    return PhotoResponse(tuple(float(c) for c in codes), tuple(float(v) for v in np.log(x / white)),
                         "colour_chart", f"the synthetic tone curve's inverse (white {white:g})")


def _chart_light(frame, flash: np.ndarray, room: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(H, W, 3) the irradiance / pi on the chart's plane seen through each pixel (flash at the camera centre:
    I cos / r^2; plus the room's), 0 where the pixel's ray meets the plane's back or misses it."""
    h, w = shape
    j, i = np.mgrid[0:h, 0:w]
    pix = np.stack([i.ravel() + 0.5, j.ravel() + 0.5, np.ones(h * w)], 1)
    dirs = (pix @ np.linalg.inv(frame.intrinsics.matrix()).T) @ np.asarray(frame.R)
    c = np.asarray(frame.center, np.float64)
    n = chart_normal()
    height = float(n @ (c - np.asarray(CHART_CENTRE)))  # the camera's distance in front of the chart's plane
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -height / (dirs @ n)
    ok = (t > 0) & (height > 0)
    r = np.where(ok, t * np.linalg.norm(dirs, axis=1), 1.0)
    cos = np.clip(height / r, 0.0, 1.0)
    e = np.where(ok[:, None], flash[None] * (cos / r ** 2)[:, None] + room[None], 0.0)
    return (e / math.pi).reshape(h, w, 3)


def _project(frame, pts: np.ndarray) -> tuple[np.ndarray, bool]:
    cam = pts @ np.asarray(frame.R).T + np.asarray(frame.t)
    uv = cam[:, :2] / cam[:, 2:3] @ np.diag([frame.intrinsics.fx, frame.intrinsics.fy]) + [frame.intrinsics.cx,
                                                                                              frame.intrinsics.cy]
    return uv, bool(np.all(cam[:, 2] > 0))


def develop_codes(linear: np.ndarray, rng: np.random.Generator, noise: float) -> np.ndarray:
    """The stored 8-bit codes of a linear photo: sensor noise, the tone curve, quantisation."""
    x = linear + (rng.normal(0.0, noise, linear.shape) if noise > 0 else 0.0)
    return np.clip(np.floor(filmic_codes(x, TONE_WHITE) * 255.0 + 0.5), 0, 255).astype(np.uint8)


def _write_photo(tmp: Path, name: str, f, radiance: np.ndarray, mask: np.ndarray, flash: np.ndarray,
                 chart_room: np.ndarray, rng: np.random.Generator, noise: float, exif_flash: int | None) -> list[bool]:
    """Develop one photo (the object's ``radiance`` inside ``mask``, the chart lit by ``flash`` and the room
    elsewhere) into ``images/NAME.png`` with its mask; returns [whether the whole chart is in view] when its front
    faces the camera, else []."""
    uv, front = _project(f, chart_corners_world())
    h, w = mask.shape
    linear = np.zeros((h, w, 3))
    in_view = []
    if front:
        # paste_chart's pixel centres are at integers (OpenCV), the capture's at + 0.5
        linear = paste_chart(linear, uv - 0.5, _chart_light(f, flash, chart_room, (h, w)))
        in_view.append(bool(np.all((uv >= 0) & (uv < [w, h]))))
    linear = np.where(mask[..., None], radiance, linear)
    write_image(tmp / "images" / f"{name}.png", develop_codes(linear, rng, noise), bits=8,
                metadata=None if exif_flash is None else {"Exif:Flash": exif_flash})
    write_image(tmp / "masks" / f"{name}.png", np.where(mask, np.uint8(255), np.uint8(0)), bits=8)
    return in_view


def _no_flash_photos(tmp: Path, frames: list[Frame], chart_room: np.ndarray, cfg: FlashCaptureConfig) -> list[Frame]:
    """Each flash frame's no-flash pair (module doc): the ground truth rendered with the flash at intensity 0 (the
    room's light alone, which the scene's ambient columns hold), the chart lit by the room; the sensor noise drawn
    after the flash photos' (seeds ``[seed, photos + k]``), so those stay as without pairs."""
    mesh, params, layout, _, _ = load_ground_truth(tmp)
    rend = Renderer(mesh, params, layout, device=cfg.device, shadows=SynthConfig().shadows)
    pairs = []
    for k, f in enumerate(frames):
        off = dataclasses.replace(f, light=Light.point(f.light.position, np.zeros(3)),
                                  extra={**f.extra, NO_FLASH_KEY: True})
        res = rend.render_frame(off)
        name = Path(f.file_path).stem.replace("frame_", NO_FLASH_NAME, 1)
        _write_photo(tmp, name, off, np.asarray(res.radiance, np.float64), np.asarray(res.mask, bool), np.zeros(3),
                     chart_room, np.random.default_rng([cfg.seed, len(frames) + k]), cfg.noise, EXIF_FLASH_OFF)
        off.file_path, off.mask_path = f"images/{name}.png", f"masks/{name}.png"
        pairs.append(off)
    return pairs


def synthesize_flash_capture(out: str | Path, cfg: FlashCaptureConfig | None = None) -> StageResult:
    """Write the flash capture (module doc) to ``out`` atomically. Returns its counts."""
    cfg = cfg or FlashCaptureConfig()
    out = Path(out)
    flash = np.full(3, cfg.flash)
    # the room's light on the chart: the scene's room irradiance at the table's height (its gradient in z,
    # amount 0.5, puts the table at the dim end: 1 - 0.5)
    room_rgb = np.full(3, cfg.room_light)
    chart_room = room_rgb * (1.0 - 0.5)
    with atomic_output_dir(out) as tmp:
        floats = tmp / "_float"
        scfg = SynthConfig(photos=cfg.photos, image_size=cfg.image_size, bits=32, noise=0.0, exposure=1.0,
                           room_light=cfg.room_light, device=cfg.device, progress=cfg.progress, preview=False)
        res = synthesize(cfg.scene, floats, scfg)
        cap = read_capture(floats)
        shutil.move(str(floats / GROUND_TRUTH), str(tmp / GROUND_TRUTH))
        in_view = []
        for k, f in enumerate(cap.frames):
            radiance = read_image(cap.image_path(f), channels=3)
            mask = read_image(cap.mask_path(f), channels=1)[..., 0] > 0.5
            name = Path(f.file_path).stem
            in_view += _write_photo(tmp, name, f, radiance, mask, flash, chart_room, np.random.default_rng([cfg.seed, k]),
                                    cfg.noise, EXIF_FLASH_FIRED if cfg.no_flash_pairs else None)
            f.file_path, f.mask_path = f"images/{name}.png", f"masks/{name}.png"
            f.exposure, f.saturation = 1.0 / TONE_WHITE, 1.0
        if cfg.no_flash_pairs:
            cap.frames += _no_flash_photos(tmp, cap.frames, chart_room, cfg)
        response = true_response()
        cap.root = tmp
        cap.extra = {**cap.extra, "texstream_synthetic": "flash_capture", "response": response.to_json()}
        write_capture(cap, tmp)
        shutil.rmtree(floats)
        gt = tmp / GROUND_TRUTH
        write_json_atomic(gt / "response.json", response.to_json())
        truth = {"flash_intensity": flash.tolist(), "flash_intensity_response_units": (flash / TONE_WHITE).tolist(),
                 "tone_white": TONE_WHITE, "room_irradiance": room_rgb.tolist(),
                 "room_irradiance_on_chart": chart_room.tolist(), "chart_corners_world": chart_corners_world().tolist(),
                 "chart_in_full_view": int(sum(in_view)), "photos": len(cap.frames), "scene": cfg.scene,
                 "fit_atlas": FIT_ATLAS.get(cfg.scene),
                 "image_size": cfg.image_size, "atlas": [res.summary["texture_width"], res.summary["texture_height"]],
                 "units": "intensity in the scene's units (irradiance = I cos / r^2); response units = scene / "
                          "tone_white, the units of capture.json's response and exposures"}
        if cfg.no_flash_pairs:  # absent without pairs: the capture's files stay as they were
            truth["no_flash_pairs"] = True
        write_json_atomic(gt / "flash.json", truth)
    return StageResult(output=out, summary={**res.summary, "chart_in_full_view": int(sum(in_view))})


def fit_geometry(capture_dir: str | Path, out: str | Path, device: str = "cpu") -> Path:
    """The geometry a fit of the capture is meant to use (``fit --mesh`` / ``run --mesh-file``): its ``ground_truth``
    folder when the truth's atlas is the fit's, else ``out`` written with the truth's mesh (its UVs) baked at
    :data:`FIT_ATLAS`'s size (module doc)."""
    gt = Path(capture_dir) / GROUND_TRUTH
    size = read_json(gt / "flash.json").get("fit_atlas")
    if not size:
        return gt
    out = Path(out)
    if not (out / "bake.npz").is_file():
        mesh = load_mesh(gt / "mesh.obj").with_normals()
        with atomic_output_dir(out) as tmp:
            shutil.copy(gt / "mesh.obj", tmp / "mesh.obj")
            bake_texels(mesh, int(size[0]), int(size[1]), device=device, padding=2).save(tmp / "bake.npz")
    return out
