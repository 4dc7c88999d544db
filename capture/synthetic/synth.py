"""Synthetic capture sets with ground truth, rendered by texstream's Warp renderer.

A *scene* is a small declarative JSON file (built-ins in ``capture/synthetic/scenes/``: ``sphere``,
``flat_sample``, ``bunny``, ``ornament``, ``star`` (a fixed-light surface light field for light field
mapping), ...); more scenes need no code. Keys (full-scale values):

``mesh``
    ``{"procedural": NAME, "params": {...}}`` (:mod:`texstream.capture.synthetic.procedural`, analytic UVs) or
    ``{"file": PATH, "faces": N, "atlas": {AtlasConfig fields}}``: a mesh file (``$TEXSTREAM_DATA``
    is expanded; default ``../shared/data`` beside the repository), decimated to about N faces
    (pymeshlab, 0 = keep) and given a UV atlas (xatlas) unless it has usable UVs. Optional
    ``"rotate_deg": [rx, ry, rz]`` (applied x, then y, then z) and ``"normalize": true`` (centre the
    bounding box at the origin and scale its half-diagonal to 1).
``texture``
    ``{"width": W, "height": H, "padding": 2}`` for meshes with UVs, or ``{"resolution": N}`` (the
    atlas' largest side) for atlas meshes.
``model``
    ``{"kind": "lafortune" | "diffuse", "n_lobes": K, "anisotropic": false}`` (render/layout.py).
``materials``
    name -> ``{"rho_d": [r, g, b], "lobes": [{"rho_s": [r, g, b], "c_z": 1.0, "c_y": -1.0, "n": 60}],
    "gradient": {"axis": "x"|"y"|"z"|"u"|"v", "amount": a, "n_amount": b}}``: BRDF values in 1/sr
    (capture/conventions.py). ``gradient`` varies the material smoothly: rho_d and rho_s are scaled
    by 1 + a (2 s - 1) and n by 1 + b (2 s - 1), s in [0, 1] the texel's coordinate along the axis
    (fraction of the mesh's bounding box, or the texel's u / v). Missing lobes have rho_s = 0.
    Optional ``"noise": {"amount": a, "cells": c | [cu, cv], "octaves": k, "seed": s, "sharpness": h}``
    multiplies rho_d (only) by max(0, 1 + a * N(u, v)): N is value noise in [-1, 1] over the texel's
    UV, c x c cells at the coarsest of k octaves (each octave twice as fine, half as strong),
    periodic in u (no edge at a surface of revolution's seam); h > 0 sharpens it to
    tanh(h N) / tanh(h) (blotches with crisp edges). A high-frequency albedo texture gives SIFT
    features for registration tests (calib/register.py).
``room_light``
    optional ``{"irradiance": E or [r, g, b], "gradient": {"axis": "z", "amount": a}}``: the room's own light
    beside the scene's ``light`` (a flash), a diffuse irradiance E (1 + a (2 s - 1)) on every texel, seen from
    every view and by every photo alike: each texel adds an ambient radiance rho_d E (render/layout.py
    ``ModelLayout.ambient``; the model gets its ambient columns, the ground truth its ambient.exr).
    ``SynthConfig.room_light`` overrides E (0: no room light).
``assignment``
    which material each texel gets: ``{"rule": "uniform", "material": NAME}``,
    ``{"rule": "bands", "axis": "z", "bands": [[upper_s, NAME], ..., [1.0, NAME]]}`` (the first band
    whose upper bound exceeds s), or ``{"rule": "checker", "space": "uv", "cells": [cu, cv],
    "materials": [A, B]}``.
``cameras``
    ``{"layout": "fibonacci" | "ring", "count": N, "distance": d, "fov_deg": f, "width": w,
    "height": h, "target": [x, y, z], "min_elevation_deg": e0, "max_elevation_deg": e1,
    "rings": [elevations in degrees] (ring layout), "azimuth_offset_deg": a}``. Cameras look at
    ``target`` with world +z up; the offset turns them all about the vertical axis through it.
``light``
    ``{"type": "point" | "directional", "mode": "fixed" | "camera" | "orbit", "intensity": [r,g,b]
    or a number, ...}``. fixed: ``position`` (point) or ``direction`` (directional, the direction
    the light travels). camera: the light moves with the camera, at ``offset`` in camera axes
    (OpenCV: x right, y down, z forward) for a point light or travelling along ``direction`` in
    camera axes for a directional one; ``spin_turns`` turns that offset about the optical axis over
    the sequence (the light moves around the camera). orbit: a point light at ``radius`` from the
    target axis and ``height`` above the target, turning ``turns`` times over the sequence.
``photo``
    ``{"exposure": x or [lo, hi] (log-uniform per photo), "noise_sigma": s (Gaussian, linear units,
    after exposure), "bits": 8 | 16 | 32, "saturation": v (float output only: clip at v; null = no
    clipping)}``. 8-bit photos are sRGB PNG, 16-bit linear PNG, 32-bit float EXR; integer photos
    clip at 1, which is their ``saturation`` in capture.json.

``--env NAME|FILE`` lights the scene by an environment map instead of ``light`` (a Lambertian object, frames
without lights: :mod:`~texstream.capture.synthetic.env_capture`).

``--scale s`` (:class:`SynthConfig`) shrinks a scene: photo count x s, image sides x sqrt(s),
texture sides (or atlas resolution, kept at least 64 texels so the charts still pack) x sqrt(s),
so texel count x s; the mesh is unchanged. A
pixel's value is ``exposure * radiance + noise``, then clipped / quantised (see ``photo``).

:func:`render_scene` renders in memory (no OpenImageIO needed; no xatlas / pymeshlab for
procedural meshes), :func:`synthesize` writes a capture folder plus ``ground_truth/`` (its parameter
maps: :mod:`~texstream.capture.synthetic.param_maps`; the texels' materials:
:mod:`~texstream.capture.synthetic.materials`).
"""

from __future__ import annotations

import collections
import concurrent.futures
import dataclasses
import json
import math
import os
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from texstream.core.errors import ConfigError, InputError
from texstream.core.config import option, save_config
from texstream.core.outputs import StageResult, atomic_output_dir, write_json_atomic

from texstream.capture.capture_json import Capture, Frame, Intrinsics, Light, write_capture
from texstream.capture.conventions import look_at_w2c
from texstream.capture.synthetic import env_capture, procedural
from texstream.capture.synthetic.materials import add_room_light, material_params
from texstream.capture.synthetic.param_maps import read_param_maps, write_param_maps
from texstream.capture.imageio import linear_to_srgb, srgb_to_linear, write_image
from texstream.capture.preview import write_contact_sheet
from texstream.core.outputs import read_json
from texstream.core.progress import bar
from texstream.geometry import atlas  # called through the module: a test replaces build_atlas there
from texstream.geometry.bake import TexelBake, bake_texels
from texstream.geometry.clean import CleanConfig, clean_mesh
from texstream.geometry.mesh_io import load_mesh, save_mesh
from texstream.render.layout import ModelLayout
from texstream.render.mesh import SurfaceMesh
from texstream.render.renderer import Renderer

SCENES_DIR = Path(__file__).resolve().parent / "scenes"
GROUND_TRUTH = "ground_truth"


@dataclasses.dataclass
class SynthConfig:
    """Options of ``texstream synth`` (overrides of the scene's own values)."""

    scene: str = option("ornament", help="built-in scene name (sphere, flat_sample, bunny, ornament, star, ...) or "
                                         "a scene JSON path",
                        cli=False)
    scale: float = option(1.0, help="shrink the scene: photos x s, image sides and texture sides x sqrt(s)",
                          min=0.001, max=16)
    device: str = option("cpu", help="Warp device for baking and rendering: cpu or cuda:N")
    seed: int = option(0, help="random seed for noise and per-photo exposure", min=0)
    noise: float | None = option(None, help="Gaussian camera noise sigma in linear units (None: the scene's)",
                                 min=0.0, max=1.0)
    bits: int | None = option(None, help="photo bit depth: 8 (sRGB PNG), 16 (linear PNG), 32 (float EXR); "
                                         "None: the scene's", choices=(8, 16, 32))
    exposure: float | None = option(None, help="one linear exposure for every photo (None: the scene's)",
                                    min=1e-6, max=1e6)
    saturation: float | None = option(None, help="float photos: clip at this value (integer photos clip at 1)",
                                      min=1e-6)
    photos: int = option(0, help="photo count after scaling (0: the scene's count x scale)",
                         min=0, max=100000)
    azimuth_offset: float = option(0.0, help="turn every camera this many degrees about the target's vertical "
                                             "axis (e.g. held-out views between the training views)",
                                             min=-360.0, max=360.0)
    image_size: int = option(0, help="image width and height in pixels after scaling (0: the scene's x sqrt(scale))",
                             min=8, max=16384, also=(0,))
    save_clean: bool = option(False, help="also write the noise-free float renders to ground_truth/clean/ "
                                          "(for the noise-floor PSNR)")
    shadows: bool = option(True, help="render cast shadows")
    env: str | None = option(None, help="light the scene by this environment instead of its lights: a built-in "
                                        "(sky, room, studio) or a lat-long EXR; the object turns Lambertian "
                                        "(its rho_d) and the frames carry no light (capture/synthetic/env_capture.py)")
    env_grid: int = option(32, help="--env: rows of the lat-long grid the environment is integrated on "
                                    "(columns twice that)", min=4, max=512)
    room_light: float | None = option(None, help="the room's irradiance beside the scene's light, the same on every "
                                                 "texel up to the scene's room_light gradient (0: none; None: the "
                                                 "scene's): each texel adds an ambient radiance rho_d x this",
                                      min=0.0)
    preview: bool = option(True, help="write previews/contact_sheet.png and parameter map previews")
    progress: bool = option(True, help="show a progress bar while rendering")


# ---------------------------------------------------------------------------------------- scenes


def builtin_scenes() -> list[str]:
    """Names of the scenes shipped in capture/synthetic/scenes/."""
    return sorted(p.stem for p in SCENES_DIR.glob("*.json"))


def load_scene(scene: str | os.PathLike | dict) -> dict:
    """A scene dict from a built-in name, a JSON path, or a dict (validated, copied).

    Raises:
        InputError: unknown name or unreadable file. ConfigError: a missing or bad key.
    """
    if isinstance(scene, dict):
        data, where = json.loads(json.dumps(scene)), None
    else:
        s = str(scene)
        path = Path(s)
        if not path.suffix and not path.exists():
            path = SCENES_DIR / f"{s}.json"
            if not path.is_file():
                raise InputError(f"unknown scene {s!r}", fix=f"use one of {builtin_scenes()} or a scene JSON path")
        if not path.is_file():
            raise InputError("scene file not found", path, "check the path")
        try:
            data = json.loads(path.read_text())
        except (UnicodeDecodeError, json.JSONDecodeError) as e:
            raise InputError(f"scene is not valid JSON ({e})", path, "repair the file") from None
        where = path
    _validate_scene(data, where)
    data.setdefault("name", Path(str(scene)).stem if not isinstance(scene, dict) else "scene")
    return data


def _validate_scene(d: Any, where) -> None:
    def bad(msg: str, fix: str = "see the key list in texstream.capture.synthetic.synth's module doc"):
        raise ConfigError(f"scene {msg}", where, fix)

    if not isinstance(d, dict):
        bad("is not a JSON object")
    for key in ("mesh", "model", "materials", "assignment", "cameras", "light"):
        if key not in d:
            bad(f"lacks {key!r}")
    m = d["mesh"]
    if not isinstance(m, dict) or ("procedural" in m) == ("file" in m):
        bad("'mesh' must have exactly one of 'procedural' or 'file'")
    if "texture" not in d:
        bad("lacks 'texture'")
    if not isinstance(d["materials"], dict) or not d["materials"]:
        bad("'materials' must be a non-empty object")
    for name, mat in d["materials"].items():
        if not isinstance(mat, dict) or "rho_d" not in mat:
            bad(f"material {name!r} lacks 'rho_d'")
    a = d["assignment"]
    rule = a.get("rule") if isinstance(a, dict) else None
    if rule not in ("uniform", "bands", "checker"):
        bad(f"assignment rule {rule!r} unknown", "use uniform, bands or checker")
    used = ([a.get("material")] if rule == "uniform" else
            [b[1] for b in a.get("bands", [])] if rule == "bands" else list(a.get("materials", [])))
    for u in used:
        if u not in d["materials"]:
            bad(f"assignment names material {u!r}, which is not in 'materials'")
    c = d["cameras"]
    if c.get("layout", "fibonacci") not in ("fibonacci", "ring"):
        bad(f"camera layout {c.get('layout')!r} unknown", "use fibonacci or ring")
    for key in ("count", "distance", "fov_deg", "width", "height"):
        if key not in c:
            bad(f"cameras lack {key!r}")
    lt = d["light"]
    if lt.get("type") not in ("point", "directional") or lt.get("mode", "fixed") not in ("fixed", "camera", "orbit"):
        bad("light needs type point|directional and mode fixed|camera|orbit")
    if lt.get("type") == "directional" and lt.get("mode", "fixed") == "orbit":
        bad("an orbiting light must be a point light")


def _data_root() -> Path:
    return Path(os.environ.get("TEXSTREAM_DATA", Path(__file__).resolve().parents[3] / "shared" / "data"))


def _rotation(deg) -> np.ndarray:
    rx, ry, rz = np.radians(np.asarray(deg, dtype=np.float64))
    cx, sx, cy, sy, cz, sz = math.cos(rx), math.sin(rx), math.cos(ry), math.sin(ry), math.cos(rz), math.sin(rz)
    mx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    my = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    mz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return mz @ my @ mx


# Smallest atlas side a scaled scene asks xatlas for: a few dozen charts (the bunny's 36) no longer
# pack into ~36x36 texels, the bunny's 256 at --scale 0.02. A scene asking for less keeps its own.
MIN_ATLAS_RESOLUTION = 64


def _scaled_texture(scene: dict, scale: float) -> dict:
    t = dict(scene["texture"])
    f = math.sqrt(scale)
    for k in ("width", "height"):
        if k in t:
            t[k] = max(8, int(round(t[k] * f)))
    if "resolution" in t:
        full = int(t["resolution"])
        t["resolution"] = max(8, min(full, MIN_ATLAS_RESOLUTION), int(round(full * f)))
    return t


def build_mesh(scene: dict, scale: float = 1.0):
    """The scene's mesh with UVs and normals, and the texture size (W, H).

    Returns:
        (SurfaceMesh, (width, height), info dict).
    """

    m = scene["mesh"]
    tex = _scaled_texture(scene, scale)
    info: dict = {}
    if "procedural" in m:
        mesh = procedural.make(m["procedural"], **m.get("params", {}))
        info["source"] = f"procedural:{m['procedural']}"
    else:

        path = Path(os.path.expandvars(str(m["file"]).replace("$TEXSTREAM_DATA", str(_data_root()))))
        if not path.is_file():
            raise InputError("scene mesh not found", path,
                             "set TEXSTREAM_DATA to the folder holding the data (see ../shared/data/README.md)")
        mesh = load_mesh(path)
        info["source"] = str(path)
        if int(m.get("faces", 0)) > 0 and mesh.n_faces > int(m["faces"]):

            mesh, rep = clean_mesh(mesh, CleanConfig(target_faces=int(m["faces"]), hausdorff=False), path=path)
            info["clean"] = rep.summary()
        mesh = SurfaceMesh(vertices=mesh.vertices, faces=mesh.faces, uvs=mesh.uvs,
                           source_vertex=mesh.source_vertex)
    if "rotate_deg" in m:
        rot = _rotation(m["rotate_deg"])
        mesh.vertices = mesh.vertices @ rot.T
        if mesh.normals is not None:
            mesh.normals = mesh.normals @ rot.T
    if m.get("normalize", False):
        lo, hi = mesh.bbox()
        mesh.vertices = (mesh.vertices - (lo + hi) / 2) / (np.linalg.norm(hi - lo) / 2)
    if mesh.uvs is None or "resolution" in tex:

        cfg = atlas.AtlasConfig(**{**m.get("atlas", {}), "resolution": int(tex.get("resolution", 512)),
                             "padding": int(tex.get("padding", 2))})
        try:
            mesh, ainfo = atlas.build_atlas(mesh, cfg)
        except ConfigError as e:
            # the atlas' own fix names `texstream atlas` options; synth sets them from the scene and --scale
            raise ConfigError(f"scene {scene.get('name', '')!r} at scale {scale:g}: {e.message}",
                              None if "procedural" in m else info.get("source"),
                              "raise --scale, or the texture's resolution in a scene JSON") from None
        tex["width"], tex["height"] = ainfo.width, ainfo.height
        info["atlas"] = ainfo.to_dict()
    if mesh.normals is None:
        mesh = mesh.with_normals()
    return mesh, (int(tex["width"]), int(tex["height"])), info


def camera_poses(cams: dict, count: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """World-to-camera (R, t) of ``count`` cameras looking at the target (world +z up)."""
    target = np.asarray(cams.get("target", [0.0, 0.0, 0.0]), dtype=np.float64)
    dist = float(cams["distance"])
    if cams.get("layout", "fibonacci") == "fibonacci":
        e0 = math.radians(float(cams.get("min_elevation_deg", -90.0)))
        e1 = math.radians(float(cams.get("max_elevation_deg", 90.0)))
        i = np.arange(count)
        z = math.sin(e0) + (math.sin(e1) - math.sin(e0)) * (i + 0.5) / count
        phi = i * math.pi * (3.0 - math.sqrt(5.0))  # golden angle
        rxy = np.sqrt(np.maximum(1.0 - z * z, 0.0))
        dirs = np.stack([rxy * np.cos(phi), rxy * np.sin(phi), z], 1)
    else:
        rings = [math.radians(e) for e in cams.get("rings", [20.0])]
        per = [count // len(rings) + (1 if k < count % len(rings) else 0) for k in range(len(rings))]
        dirs = []
        for k, (el, n) in enumerate(zip(rings, per)):
            az = 2 * math.pi * (np.arange(n) + 0.5 * (k % 2)) / max(n, 1)
            dirs += [[math.cos(el) * math.cos(a), math.cos(el) * math.sin(a), math.sin(el)] for a in az]
        dirs = np.asarray(dirs, dtype=np.float64).reshape(-1, 3)
    off = math.radians(float(cams.get("azimuth_offset_deg", 0.0)))
    if off:
        rz = np.array([[math.cos(off), -math.sin(off), 0.0], [math.sin(off), math.cos(off), 0.0], [0.0, 0.0, 1.0]])
        dirs = dirs @ rz.T
    return [look_at_w2c(target + dist * d, target, up=(0.0, 0.0, 1.0)) for d in dirs]


def _intensity(v) -> np.ndarray:
    a = np.asarray(v, dtype=np.float64).reshape(-1)
    return np.repeat(a, 3) if a.size == 1 else a


def frame_light(lt: dict, r: np.ndarray, t: np.ndarray, i: int, n: int, target: np.ndarray) -> Light:
    """The light of photo ``i`` of ``n`` (see the module doc, ``light``)."""
    inten = _intensity(lt.get("intensity", 1.0))
    mode = lt.get("mode", "fixed")
    if mode == "fixed":
        if lt["type"] == "point":
            return Light.point(lt["position"], inten)
        return Light.directional(lt["direction"], inten)
    if mode == "camera":
        ang = 2 * math.pi * float(lt.get("spin_turns", 0.0)) * i / max(n, 1)
        spin = np.array([[math.cos(ang), -math.sin(ang), 0.0], [math.sin(ang), math.cos(ang), 0.0], [0, 0, 1.0]])
        if lt["type"] == "point":
            off = spin @ np.asarray(lt.get("offset", [0.0, 0.0, 0.0]), dtype=np.float64)
            return Light.point(-r.T @ t + r.T @ off, inten)
        return Light.directional(r.T @ (spin @ np.asarray(lt.get("direction", [0.0, 0.0, 1.0]), dtype=np.float64)), inten)
    ang = math.radians(float(lt.get("phase_deg", 0.0))) + 2 * math.pi * float(lt.get("turns", 1.0)) * i / max(n, 1)
    rad = float(lt.get("radius", 3.0))
    return Light.point(target + np.array([rad * math.cos(ang), rad * math.sin(ang), float(lt.get("height", 2.0))]), inten)


def _photo_settings(scene: dict, config: SynthConfig) -> dict:
    p = dict(scene.get("photo", {}))
    if config.noise is not None:
        p["noise_sigma"] = config.noise
    if config.bits is not None:
        p["bits"] = config.bits
    if config.exposure is not None:
        p["exposure"] = config.exposure
    if config.saturation is not None:
        p["saturation"] = config.saturation
    p.setdefault("exposure", 1.0)
    p.setdefault("noise_sigma", 0.0)
    p.setdefault("bits", 32)
    p.setdefault("saturation", None)
    if int(p["bits"]) not in (8, 16, 32):
        raise ConfigError(f"photo bits {p['bits']} unsupported", fix="use 8, 16 or 32")
    if float(p["noise_sigma"]) < 0:
        raise ConfigError("noise sigma must be >= 0")
    return p


def _exposures(p: dict, n: int, seed: int) -> np.ndarray:
    e = p["exposure"]
    if isinstance(e, (list, tuple)):
        lo, hi = float(e[0]), float(e[1])
        if not 0 < lo <= hi:
            raise ConfigError(f"exposure range {e} invalid", fix="use [lo, hi] with 0 < lo <= hi")
        rng = np.random.default_rng([seed, 7])
        return np.exp(rng.uniform(math.log(lo), math.log(hi), size=n))
    if not float(e) > 0:
        raise ConfigError(f"exposure {e} must be positive")
    return np.full(n, float(e))


def develop(radiance: np.ndarray, exposure: float, p: dict, rng: np.random.Generator) -> np.ndarray:
    """Turn a clean radiance image into the stored photo, returned as linear float32 values exactly as
    they read back from the file: exposure, Gaussian noise, clipping, and 8-bit sRGB / 16-bit
    linear quantisation."""
    img = radiance.astype(np.float64) * exposure
    sigma = float(p["noise_sigma"])
    if sigma > 0:
        img = img + rng.normal(0.0, sigma, size=img.shape)
    bits = int(p["bits"])
    if bits == 8:

        codes = np.floor(np.clip(linear_to_srgb(np.clip(img, 0.0, 1.0)), 0.0, 1.0) * 255 + 0.5)
        return srgb_to_linear(codes / 255.0).astype(np.float32)
    if bits == 16:
        return (np.floor(np.clip(img, 0.0, 1.0) * 65535 + 0.5) / 65535).astype(np.float32)
    if p.get("saturation") is not None:
        img = np.minimum(img, float(p["saturation"]))
    return img.astype(np.float32)


@dataclasses.dataclass
class RenderedScene:
    """What :func:`render_scene` returns (iterating yields mesh, bake, params, frames, images).

    Attributes:
        mesh: the SurfaceMesh with UVs and normals.
        bake: the TexelBake of the texture.
        params: (H, W, P) float32 ground-truth parameter grid (padding filled).
        frames: capture Frames (pose, intrinsics, light, exposure, saturation; file paths as
            :func:`synthesize` names them).
        images: per frame, (h, w, 3) float32 linear photo values exactly as stored (exposure,
            noise, clipping, quantisation applied).
        masks: per frame, (h, w) bool object masks.
        clean: per frame, (h, w, 3) float32 noise-free exposure x radiance, or None unless asked.
        layout: the ModelLayout of ``params``.
        material_id: (H, W) int32 material index per texel (-1 off the surface).
        material_names: names of the materials, in index order.
        scene: the resolved scene dict (after scaling and overrides).
        environment: with ``--env``, the :class:`~texstream.capture.synthetic.env_capture.EnvLighting` (the map, its
            SH, the texels' radiance and SH transfer); ``params`` and ``layout`` are then the diffuse ground truth.
    """

    mesh: Any
    bake: Any
    params: np.ndarray
    frames: list
    images: list
    masks: list
    clean: list | None
    layout: Any
    material_id: np.ndarray
    material_names: list
    scene: dict
    environment: Any = None

    def __iter__(self) -> Iterator:
        return iter((self.mesh, self.bake, self.params, self.frames, self.images))


def resolve_scene(scene, config: SynthConfig) -> dict:
    """The scene with scale and config overrides applied to cameras, texture and photo settings."""
    sc = load_scene(scene)
    if not config.scale > 0:
        raise ConfigError(f"scale {config.scale} must be positive", fix="use e.g. --scale 0.05")
    cams = dict(sc["cameras"])
    f = math.sqrt(config.scale)
    cams["count"] = config.photos if config.photos > 0 else max(1, int(round(cams["count"] * config.scale)))
    if config.image_size > 0:
        cams["width"] = cams["height"] = int(config.image_size)
    else:
        cams["width"] = max(16, int(round(cams["width"] * f)))
        cams["height"] = max(16, int(round(cams["height"] * f)))
    if config.azimuth_offset:
        cams["azimuth_offset_deg"] = float(cams.get("azimuth_offset_deg", 0.0)) + float(config.azimuth_offset)
    sc["cameras"] = cams
    sc["photo"] = _photo_settings(sc, config)
    sc["scale"] = config.scale
    if config.room_light is not None:
        sc["room_light"] = {**sc.get("room_light", {}), "irradiance": float(config.room_light)}
    if not np.any(np.asarray(sc.get("room_light", {}).get("irradiance", 0.0)) > 0):
        sc.pop("room_light", None)  # no room light: no ambient columns
    return sc


def prepare_scene(scene, config: SynthConfig):
    """Resolve, build the mesh, bake the texture and assign materials (no rendering).

    Returns:
        (resolved scene, mesh, bake, layout, params (H, W, P), material ids, material names, info).
    """

    sc = resolve_scene(scene, config)
    md = sc["model"]
    layout = ModelLayout(md.get("kind", "lafortune"), int(md.get("n_lobes", 1)), bool(md.get("anisotropic", False)),
                         ambient="room_light" in sc)
    mesh, (tw, th), info = build_mesh(sc, config.scale)
    pad = int(sc["texture"].get("padding", 2))
    bake = bake_texels(mesh, tw, th, device=config.device, padding=pad)
    params, mid, names = material_params(sc, layout, mesh, bake)
    if layout.ambient:
        params = add_room_light(params, layout, sc["room_light"], mesh, bake)
    sc["texture"] = {**sc["texture"], "width": tw, "height": th}
    return sc, mesh, bake, layout, params, mid, names, info


def _frames(sc: dict, image_ext: str) -> list[Frame]:
    cams = sc["cameras"]
    n, w, h = int(cams["count"]), int(cams["width"]), int(cams["height"])
    fx = (w / 2) / math.tan(math.radians(float(cams["fov_deg"])) / 2)
    intr = Intrinsics(width=w, height=h, fx=fx, fy=fx, cx=w / 2, cy=h / 2)
    p = sc["photo"]
    exps = _exposures(p, n, int(sc.get("_seed", 0)))
    sat = 1.0 if int(p["bits"]) in (8, 16) else (None if p.get("saturation") is None else float(p["saturation"]))
    target = np.asarray(cams.get("target", [0.0, 0.0, 0.0]), dtype=np.float64)
    frames = []
    for i, (r, t) in enumerate(camera_poses(cams, n)):
        name = f"frame_{i:05d}"
        frames.append(Frame(file_path=f"images/{name}{image_ext}", R=r, t=t, intrinsics=intr,
                            light=frame_light(sc["light"], r, t, i, n, target), exposure=float(exps[i]),
                            mask_path=f"masks/{name}.png", saturation=sat))
    return frames


def _image_ext(bits: int) -> str:
    return ".exr" if int(bits) == 32 else ".png"


def iter_renders(sc: dict, mesh, params: np.ndarray, layout, frames: list[Frame], config: SynthConfig,
                 ) -> Iterator[tuple[int, Frame, np.ndarray, np.ndarray, np.ndarray]]:
    """Render and develop every frame: yields (index, frame, photo, mask, clean) one at a time."""

    rend = Renderer(mesh, params, layout, device=config.device, shadows=config.shadows)

    for i in bar(range(len(frames)), f"synth {sc.get('name', '')}", unit="photo", enabled=config.progress):
        f = frames[i]
        res = rend.render_frame(f)
        rng = np.random.default_rng([int(config.seed), i])
        photo = develop(res.radiance, f.exposure, sc["photo"], rng)
        clean = (res.radiance * np.float32(f.exposure)).astype(np.float32)
        yield i, f, photo, res.mask, clean


def render_scene(scene, config: SynthConfig | None = None) -> RenderedScene:
    """Render a scene in memory (no files). Needs no OpenImageIO, and no xatlas / pymeshlab when the
    mesh is procedural (analytic UVs).

    Args:
        scene: built-in name, JSON path or dict.
        config: options (scale, device, seed, overrides); ``save_clean`` keeps the clean renders.

    Returns:
        A :class:`RenderedScene`; ``mesh, bake, params, frames, images = render_scene(...)`` works.
    """
    config = config or SynthConfig()
    sc, mesh, bake, layout, params, mid, names, _ = prepare_scene(scene, config)
    sc["_seed"] = config.seed
    frames = _frames(sc, _image_ext(sc["photo"]["bits"]))
    lit, shading = None, (params, layout)
    if config.env:
        lit = env_capture.light_scene(sc, mesh, bake, params, frames, config.env, config.env_grid, config.device)
        params, layout, frames, shading = lit.params, lit.layout, lit.frames, (lit.radiance, lit.render_layout)
    images, masks, cleans = [], [], ([] if config.save_clean else None)
    for _, _, photo, mask, clean in iter_renders(sc, mesh, *shading, frames, config):
        images.append(photo)
        masks.append(mask)
        if cleans is not None:
            cleans.append(clean)
    sc.pop("_seed", None)
    return RenderedScene(mesh=mesh, bake=bake, params=params, frames=frames, images=images, masks=masks,
                         clean=cleans, layout=layout, material_id=mid, material_names=names, scene=sc, environment=lit)


# ---------------------------------------------------------------------------------- ground truth


def load_ground_truth(folder: str | os.PathLike):
    """Read a synthetic set's ground truth back.

    Args:
        folder: the capture folder written by :func:`synthesize` (or its ground_truth/).

    Returns:
        (mesh, params (H, W, P) float32, ModelLayout, TexelBake, manifest dict).
    """

    g = Path(folder)
    if (g / GROUND_TRUTH).is_dir():
        g = g / GROUND_TRUTH
    man = read_json(g / "manifest.json", what="ground-truth manifest")
    layout = ModelLayout.from_json(man["layout"])
    bake = TexelBake.load(g / "bake.npz")
    return load_mesh(g / "mesh.obj"), read_param_maps(g, layout), layout, bake, man


def _write_previews(out: Path, params: np.ndarray, layout, bake) -> None:

    prev = out / "previews"
    # albedo-like views: pi * rho_d, and rho_s scaled to its maximum
    write_image(prev / "rho_d.png", np.clip(np.pi * params[..., 0:3], 0, 1), bits=8)
    if layout.n_lobes:
        o = layout.lobe_offset(0)
        rs = params[..., o:o + 3]
        write_image(prev / "lobe0_rho_s.png", np.clip(rs / max(float(rs.max()), 1e-12), 0, 1), bits=8)
    write_image(prev / "bake_normals.png", bake.normal_preview(), bits=8)

    write_contact_sheet(out, prev / "contact_sheet.png")


def synthesize(scene, out_dir: str | os.PathLike, config: SynthConfig | None = None) -> StageResult:
    """Render a synthetic capture set with ground truth into ``out_dir`` (atomically).

    Writes ``images/`` (EXR for 32-bit, PNG for 8/16-bit), ``masks/``, ``capture.json`` (lights,
    exposure, saturation, mask paths), ``ground_truth/`` (``mesh.obj`` with UVs, parameter EXR maps,
    ``bake.npz``, ``material_id.png``, ``manifest.json``, and ``clean/*.exr`` noise-free
    exposure x radiance renders when ``save_clean``), ``previews/`` and ``synth_config.json``.

    Args:
        scene: built-in scene name, JSON path or dict.
        out_dir: output capture folder (replaced if it exists).
        config: options; ``config.scene`` is ignored in favour of ``scene``.

    Returns:
        StageResult with counts in ``summary``.
    """


    config = dataclasses.replace(config or SynthConfig(), scene=str(scene) if not isinstance(scene, dict) else "<dict>")
    sc, mesh, bake, layout, params, mid, names, info = prepare_scene(scene, config)
    sc["_seed"] = config.seed
    bits = int(sc["photo"]["bits"])
    frames = _frames(sc, _image_ext(bits))
    sc.pop("_seed", None)
    lit, shading = None, (params, layout)
    if config.env:
        lit = env_capture.light_scene(sc, mesh, bake, params, frames, config.env, config.env_grid, config.device)
        params, layout, frames, shading = lit.params, lit.layout, lit.frames, (lit.radiance, lit.render_layout)
    out_dir = Path(out_dir)
    with atomic_output_dir(out_dir) as tmp:
        gt = tmp / GROUND_TRUTH
        (tmp / "images").mkdir(parents=True)
        (tmp / "masks").mkdir()
        gt.mkdir()
        n_fg = 0

        def write(f, photo, mask, clean):
            write_image(tmp / f.file_path, photo, bits=bits)
            write_image(tmp / f.mask_path, np.where(mask, np.uint8(255), np.uint8(0)), bits=8)
            if config.save_clean:
                write_image(gt / "clean" / f"{f.name}.exr", clean, bits=32)

        # encoding (EXR zip, PNG deflate) releases the GIL: photos are written on threads while the next ones
        # render; at most two per thread wait, so memory stays a few photos
        workers = max(1, min(8, os.cpu_count() or 1))
        with concurrent.futures.ThreadPoolExecutor(max_workers=workers) as pool:
            pending = collections.deque()
            for i, f, photo, mask, clean in iter_renders(sc, mesh, *shading, frames, config):
                # copies: the renderer may hand out views of buffers it reuses for the next frame
                pending.append(pool.submit(write, f, photo, np.array(mask), np.array(clean)))
                n_fg += int(mask.sum())
                while len(pending) > 2 * workers:
                    pending.popleft().result()
            for job in pending:
                job.result()
        write_capture(Capture(root=tmp, frames=frames, extra={"texstream_synthetic": sc.get("name", "")}), tmp)
        save_mesh(gt / "mesh.obj", mesh)
        files = write_param_maps(gt, params, layout)
        bake.save(gt / "bake.npz")
        write_image(gt / "material_id.png", (mid + 1).astype(np.uint8), bits=8)
        counts = {"photos": len(frames), "image_width": int(sc["cameras"]["width"]),
                  "image_height": int(sc["cameras"]["height"]), "triangles": mesh.n_faces,
                  "vertices": mesh.n_vertices, "texture_width": bake.width, "texture_height": bake.height,
                  "covered_texels": bake.n_covered, "foreground_pixels": n_fg,
                  "texels_per_material": {n: int((mid == k).sum()) for k, n in enumerate(names)}}
        manifest = {"kind": "texstream synthetic ground truth", "layout": layout.to_json(), "scene": sc,
                    "materials": names, "material_id_png": "material_id.png (value - 1 = index into materials; 0 = off surface)",
                    "counts": counts, "mesh": "mesh.obj", "maps": files, "bake": "bake.npz",
                    "clean": "clean/" if config.save_clean else None, "mesh_info": info,
                    "units": "BRDF values in 1/sr; photos = exposure * radiance (capture/conventions.py)"}
        if lit is not None:
            lit.write(gt)
            manifest["environment"] = lit.manifest()
        write_json_atomic(gt / "manifest.json", manifest)
        save_config(config, tmp / "synth_config.json")
        if config.preview:
            _write_previews(tmp, params, layout, bake)
    return StageResult(output=out_dir, summary=counts)
