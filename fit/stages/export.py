"""Export a fitted model folder to files other tools open: glTF 2.0 binary and OBJ + MTL.

``texstream fit`` writes per-texel Lafortune parameters as float EXR maps (BRDF values in 1/sr,
capture/conventions.py). Viewers and DCC tools read a PBR metallic-roughness glTF or a Phong-style
OBJ/MTL instead, so this module converts (docs/export.md has the same text with the numbers):

materials
    Each model kind's plugin makes its material (fit/models/registry.py ``ExportMaterial``, from
    ``FittedModel.export_material``), and this module writes it by its features alone. A lit model's glTF
    material is the core metallic-roughness material fitted to the model (``ExportMaterial.pbr``: base colour,
    metallic and roughness chosen by least squares so that core viewers, which ignore extensions, render the
    model under a point light as texstream does; fit/models/lafortune/gltf_core.py) with
    ``KHR_materials_specular`` on top (its dielectric F0 fitted given the core maps: F0 / s as the texture,
    ``specularColorFactor = s / 0.04``); OBJ keeps the albedo (``map_Kd``) and the lobe energy (``Ks``,
    ``map_Ks``, ``Ns``, ``illum 2``; a diffuse model ``Ks 0``, ``illum 1``). An unlit colour is written with
    ``KHR_materials_unlit`` (fallback metallic 0, roughness 0.9 as the extension suggests; OBJ map_Kd with
    ``illum 0``). The conversions are the plugins': the Lafortune lobes' in fit/models/lafortune/export.py and
    gltf_core.py, the radiance models' clipped radiance in fit/models/radiance/export.py, the light field
    mapping models' unlit approximation in fit/models/lfm/export.py; docs/export.md has them all, with the
    glb's scores in three.js and Blender (benchmarks/gltf_viewer_check.py).

Geometry
    Positions, unit vertex normals, UVs. texstream UVs have v up (capture/conventions.py), glTF's
    origin is the top-left of the image: TEXCOORD_0 = (u, 1 - v); OBJ keeps v up. Texture images
    are written as stored (row 0 = top). The glTF scene turns the model's up axis to glTF's +y with
    a node rotation (``up_axis="z"``: -90 degrees about x; the vertex data stay in texstream's
    world frame, readers apply the node); OBJ has no node, so its vertices are rotated. The float
    EXR maps are copied into ``maps/`` beside the export.

Like the rest of ``texstream.fit`` this module imports no third-party package but numpy at module level;
pygltflib is imported inside the functions, OpenImageIO inside capture.imageio's.
"""

from __future__ import annotations

import dataclasses
import math
import tempfile
from pathlib import Path

import numpy as np

from texstream.capture.imageio import write_image
from texstream.core import outputs  # write_atomic_with through it: a test makes it fail there (full disk)
from texstream.core.config import option, save_config
from texstream.core.devices import DEVICE_HELP
from texstream.core.errors import ConfigError, InputError
from texstream.core.outputs import StageResult, atomic_output_dir, write_json_atomic
from texstream.core.progress import phase
from texstream.fit.models import registry
# the options' choices; the other names are the plugins' conversions that docs/export.md and the export tests
# read beside the export
from texstream.fit.models.lafortune.export import ROUGHNESS_CONVERSIONS
from texstream.fit.models.lafortune.export import (ggx_alpha_from_exponent, ggx_lobe_inplane, lobe_albedo,  # noqa: F401
                                                   lobe_conversion_table, roughness_from_exponent)
from texstream.fit.models.lfm.export import LFM_VIEW_MEANS
from texstream.fit.models.lfm.export import (lfm_atlas, lfm_unlit_radiance, lfm_unlit_renderer,  # noqa: F401
                                             view_mean_weights)

FORMATS = ("glb", "obj")
UP_AXES = ("z", "y")
DIELECTRIC_F0 = 0.04  # ((ior - 1) / (ior + 1))^2 at glTF's default ior 1.5

# glTF enums
_FLOAT, _UINT = 5126, 5125
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963
_LINEAR, _LINEAR_MIPMAP_LINEAR, _CLAMP = 9729, 9987, 33071


@dataclasses.dataclass
class ExportConfig:
    """Options of the export stage (``texstream export``)."""

    formats: tuple[str, ...] = option(("glb", "obj"), "files to write: glb (glTF 2.0 binary, PBR metallic-"
                                      "roughness + KHR_materials_specular) and/or obj (OBJ + MTL + PNG)")
    name: str = option("model", "file stem: NAME.glb, NAME.obj, NAME.mtl, NAME_*.png")
    up_axis: str = option("z", "the model's world up axis, turned to +y (glTF's up; OBJ importers assume "
                          "it too): z for texstream's synthetic scenes, y to keep the coordinates",
                          choices=UP_AXES)
    roughness: str = option("fitted", "Lafortune exponent n -> GGX alpha: fitted sqrt(0.72/(n+3)) or "
                            "blinn4 sqrt(2/(4n+2)) (docs/export.md)", choices=ROUGHNESS_CONVERSIONS)
    radiance_scale: float = option(1.0, "radiance models: multiply the radiance by this before clipping "
                                   "to [0, 1] (1 = photo units, where 1 is the photo's white)", min=1e-12)
    copy_maps: bool = option(True, "copy the float EXR parameter maps into maps/ (the exact fitted values)")
    device: str = option("auto", DEVICE_HELP + "; runs the glTF core-material fit of lit models")
    lfm_view_mean: str = option("cosine", "light field mapping models: unlit base colour = the view-"
                                "independent term plus each view-dependent term's mean over view "
                                "directions, cosine-weighted over the hemisphere (cosine), or the "
                                "view-independent term alone (none)", choices=LFM_VIEW_MEANS)


# ---------------------------------------------------------------------------------------------
# the material as images


def _png_bytes(img: np.ndarray) -> bytes:
    """8-bit PNG of a linear image (sRGB-encoded by capture.imageio) or of uint8 codes (stored as is)."""
    with tempfile.TemporaryDirectory(prefix="texstream_export_") as t:
        p = write_image(Path(t) / "tex.png", img, bits=8)
        return p.read_bytes()


def _roughness_codes(rough: np.ndarray, metallic: np.ndarray | None = None) -> np.ndarray:
    """glTF metallicRoughnessTexture (linear, not sRGB): R unused (255), G roughness, B metalness (None: 0)."""
    out = np.zeros((*rough.shape, 3), np.uint8)
    out[..., 0] = 255
    out[..., 1] = np.floor(np.clip(rough, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    if metallic is not None:
        out[..., 2] = np.floor(np.clip(metallic, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    return out


def _pbr_specular(mat: registry.ExportMaterial, covered: np.ndarray) -> tuple[np.ndarray | None, dict]:
    """KHR_materials_specular of a fitted core material: the dielectric F0 over s (s = its largest value over the
    covered texels, so the sRGB texture spans the 8-bit range) and specularColorFactor s / 0.04; F0 = 0
    everywhere: specularFactor 0 (no specular layer). Returns (texture or None, the factors)."""
    f0 = mat.pbr.specular_f0
    s = float(f0[covered].max()) if covered.any() else 0.0
    if s <= 0:
        return None, {"specular_factor": 0.0, "specular_color_factor": 0.0}
    return f0 / s, {"specular_factor": 1.0, "specular_color_factor": s / DIELECTRIC_F0}


def _up_rotation(up_axis: str) -> np.ndarray:
    if up_axis == "z":
        return np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # (x, y, z) -> (x, z, -y)
    if up_axis == "y":
        return np.eye(3)
    raise ConfigError(f"unknown up axis {up_axis!r}", fix=f"use one of {UP_AXES}")


def _unit_normals(mesh) -> np.ndarray:
    n = np.asarray(mesh.vertex_normals(), dtype=np.float64)
    ln = np.linalg.norm(n, axis=1, keepdims=True)
    return np.divide(n, ln, out=np.tile([0.0, 0.0, 1.0], (len(n), 1)), where=ln > 0)


def _copy_maps(m: registry.FittedModel, folder: Path) -> list[str]:
    out = []
    for f in m.map_files():
        data = f.read_bytes()
        outputs.write_atomic_with(folder / f.name, lambda fh, data=data: fh.write(data))
        out.append(f"maps/{f.name}")
    return out


def _info(m: registry.FittedModel, mat: registry.ExportMaterial, cfg: ExportConfig) -> dict:
    h, w = mat.base.shape[:2]
    info = {"kind": mat.name, "vertices": m.mesh.n_vertices, "faces": m.mesh.n_faces, "texture": [w, h],
            "up_axis": cfg.up_axis, "base_colour_clipped_texels": mat.clipped}
    if mat.specular is not None:
        info.update({"specular_scale": mat.specular_scale, "roughness_conversion": cfg.roughness, "mtl_ns": mat.ns})
    if mat.pbr is not None:
        info["gltf_material"] = {**_pbr_specular(mat, m.covered)[1], **mat.pbr.fit}
    if mat.unlit:
        info["radiance_scale"] = cfg.radiance_scale
    info["model_kind"] = m.kind
    info.update(mat.extras)
    return info


def _check_config(cfg: ExportConfig) -> None:
    bad = [f for f in cfg.formats if f not in FORMATS]
    if bad or not cfg.formats:
        raise ConfigError(f"unknown export format(s) {bad or '(none)'}", fix=f"use some of {FORMATS}")
    _up_rotation(cfg.up_axis)
    if cfg.roughness not in ROUGHNESS_CONVERSIONS:
        raise ConfigError(f"unknown roughness conversion {cfg.roughness!r}", fix=f"use one of {ROUGHNESS_CONVERSIONS}")
    if not (math.isfinite(cfg.radiance_scale) and cfg.radiance_scale > 0):
        raise ConfigError(f"radiance_scale must be > 0, got {cfg.radiance_scale}",
                          fix="pass a positive scale")
    if cfg.lfm_view_mean not in LFM_VIEW_MEANS:
        raise ConfigError(f"unknown lfm_view_mean {cfg.lfm_view_mean!r}", fix=f"use one of {LFM_VIEW_MEANS}")
    if not cfg.name or "/" in cfg.name or cfg.name.startswith("."):
        raise ConfigError(f"bad file stem {cfg.name!r}", fix="pass a plain file name without folders")


# ---------------------------------------------------------------------------------------------
# glTF 2.0 binary


def export_gltf(model_dir, out_path, config: ExportConfig | None = None) -> dict:
    """Write a model folder as one glTF 2.0 binary (``.glb``) with embedded PNG textures.

    Lafortune / diffuse models get the core metallic-roughness material fitted to the model (base colour,
    metallic and roughness textures) with ``KHR_materials_specular`` on top (its F0 fitted given them);
    radiance models an unlit base colour (``KHR_materials_unlit``). The module doc gives the
    conversions. With ``config.copy_maps`` the EXR maps are copied into ``maps/`` beside the file.

    Args:
        model_dir: a model folder (``texstream fit`` output).
        out_path: the ``.glb`` to write (atomically; its folder is created).
        config: export options (defaults: ExportConfig()).

    Returns:
        A summary dict (vertices, faces, texture size, conversion factors).

    Raises:
        InputError: missing or invalid model folder (naming the file and the fix).
        ConfigError: bad options.
    """
    cfg = config or ExportConfig()
    _check_config(cfg)
    m = registry.load_model_folder(model_dir)
    return _export_gltf(m, m.export_material(cfg), cfg, Path(out_path))


def _export_gltf(m: registry.FittedModel, mat: registry.ExportMaterial, cfg: ExportConfig, out: Path) -> dict:
    _write_glb(m, mat, cfg, out)
    info = _info(m, mat, cfg)
    info["path"] = str(out)
    if cfg.copy_maps:
        info["maps"] = _copy_maps(m, out.parent / "maps")
    return info


def _write_glb(m: registry.FittedModel, mat: registry.ExportMaterial, cfg: ExportConfig, out: Path) -> None:
    import pygltflib as G

    mesh = m.mesh
    pos = np.ascontiguousarray(mesh.vertices, dtype="<f4")
    nrm = np.ascontiguousarray(_unit_normals(mesh), dtype="<f4")
    uv = np.asarray(mesh.uvs, dtype=np.float64)
    tex = np.ascontiguousarray(np.stack([uv[:, 0], 1.0 - uv[:, 1]], axis=1), dtype="<f4")  # v up -> glTF
    idx = np.ascontiguousarray(mesh.faces, dtype="<u4").reshape(-1)

    blob = bytearray()
    views: list = []

    def view(data: bytes, target: int | None = None) -> int:
        blob.extend(b"\0" * (-len(blob) % 4))
        views.append(G.BufferView(buffer=0, byteOffset=len(blob), byteLength=len(data), target=target))
        blob.extend(data)
        return len(views) - 1

    accessors = [
        G.Accessor(bufferView=view(pos.tobytes(), _ARRAY_BUFFER), componentType=_FLOAT, count=len(pos),
                   type="VEC3", min=pos.min(axis=0).tolist(), max=pos.max(axis=0).tolist()),
        G.Accessor(bufferView=view(nrm.tobytes(), _ARRAY_BUFFER), componentType=_FLOAT, count=len(nrm),
                   type="VEC3"),
        G.Accessor(bufferView=view(tex.tobytes(), _ARRAY_BUFFER), componentType=_FLOAT, count=len(tex),
                   type="VEC2"),
        G.Accessor(bufferView=view(idx.tobytes(), _ELEMENT_ARRAY_BUFFER), componentType=_UINT,
                   count=int(idx.size), type="SCALAR", min=[int(idx.min())], max=[int(idx.max())]),
    ]
    images, textures = [], []

    def texture(name: str, img: np.ndarray) -> int:
        images.append(G.Image(bufferView=view(_png_bytes(img)), mimeType="image/png", name=name))
        textures.append(G.Texture(sampler=0, source=len(images) - 1, name=name))
        return len(textures) - 1

    units = ("base colour, metallic, roughness: the core material fitted to the model; KHR_materials_specular on "
             "top" if mat.pbr is not None else "base colour = albedo (pi * rho_d) or clipped radiance") + \
        "; see docs/export.md"
    extras = {"texstream": {"kind": mat.name, "model_kind": m.kind, "units": units, **mat.extras}}
    pbr_mat = mat.pbr
    pbr = G.PbrMetallicRoughness(baseColorFactor=[1.0, 1.0, 1.0, 1.0], metallicFactor=0.0,
                                 baseColorTexture=G.TextureInfo(index=texture(
                                     "base_color", mat.base if pbr_mat is None else pbr_mat.base_color)))
    if mat.unlit:
        pbr.roughnessFactor = 0.9
        extensions = {"KHR_materials_unlit": {}}
        extras["texstream"]["radiance_scale"] = cfg.radiance_scale
    elif pbr_mat is not None:
        pbr.metallicFactor = pbr.roughnessFactor = 1.0
        pbr.metallicRoughnessTexture = G.TextureInfo(index=texture(
            "metallic_roughness", _roughness_codes(pbr_mat.roughness, pbr_mat.metallic)))
        spec_img, spec = _pbr_specular(mat, m.covered)
        extensions = {"KHR_materials_specular": {"specularFactor": spec["specular_factor"]}}
        if spec_img is not None:
            extensions["KHR_materials_specular"].update({
                "specularColorFactor": [spec["specular_color_factor"]] * 3,
                "specularColorTexture": {"index": texture("specular_color", spec_img)}})
        extras["texstream"].update({"roughness_conversion": cfg.roughness, **pbr_mat.fit})
    elif mat.specular is None:
        pbr.roughnessFactor = 1.0
        extensions = {"KHR_materials_specular": {"specularFactor": 0.0}}  # no specular layer: Lambertian
    else:
        pbr.roughnessFactor = 1.0
        pbr.metallicRoughnessTexture = G.TextureInfo(index=texture("metallic_roughness",
                                                                    _roughness_codes(mat.roughness)))
        spec = {"specularFactor": 1.0, "specularColorFactor": [mat.specular_scale / DIELECTRIC_F0] * 3}
        if mat.specular_scale > 0:
            spec["specularColorTexture"] = {"index": texture("specular_color", mat.specular)}
        extensions = {"KHR_materials_specular": spec}
        extras["texstream"].update({"roughness_conversion": cfg.roughness,
                                    "specular_scale": mat.specular_scale})
    material = G.Material(name=f"texstream_{mat.name}", pbrMetallicRoughness=pbr, extensions=extensions,
                          extras=extras, doubleSided=False)
    if mat.emissive is not None and mat.emissive.max() > 0:
        # the fitted ambient radiance (the room's light): emissive texture / factor in [0, 1], the rest of its
        # peak in KHR_materials_emissive_strength
        peak = float(mat.emissive.max())
        material.emissiveTexture = G.TextureInfo(index=texture("emissive", mat.emissive / peak))
        material.emissiveFactor = [min(peak, 1.0)] * 3
        if peak > 1.0:
            extensions["KHR_materials_emissive_strength"] = {"emissiveStrength": peak}
    up = _up_rotation(cfg.up_axis)
    node = G.Node(mesh=0, name=cfg.name)
    if not np.allclose(up, np.eye(3)):
        node.rotation = [-math.sqrt(0.5), 0.0, 0.0, math.sqrt(0.5)]  # -90 deg about x: +z up -> +y up
    prim = G.Primitive(attributes=G.Attributes(POSITION=0, NORMAL=1, TEXCOORD_0=2), indices=3, material=0,
                       mode=4)
    gltf = G.GLTF2(asset=G.Asset(version="2.0", generator="texstream export"), scene=0,
                   scenes=[G.Scene(nodes=[0])], nodes=[node],
                   meshes=[G.Mesh(name=cfg.name, primitives=[prim])],
                   accessors=accessors, bufferViews=views, buffers=[G.Buffer(byteLength=len(blob))],
                   images=images, textures=textures,
                   samplers=[G.Sampler(magFilter=_LINEAR, minFilter=_LINEAR_MIPMAP_LINEAR, wrapS=_CLAMP,
                                       wrapT=_CLAMP)],
                   materials=[material], extensionsUsed=sorted(extensions))
    gltf.set_binary_blob(bytes(blob))
    data = b"".join(gltf.save_to_bytes())
    outputs.write_atomic_with(out, lambda fh: fh.write(data))


# ---------------------------------------------------------------------------------------------
# OBJ + MTL


def export_obj(model_dir, out_dir, config: ExportConfig | None = None) -> dict:
    """Write a model folder as ``NAME.obj`` + ``NAME.mtl`` + PNG textures into ``out_dir``.

    MTL: ``map_Kd`` = base colour (albedo, sRGB PNG), ``Ks`` / ``map_Ks`` = the lobe albedo (F0, as
    in the glTF: ``Ks`` is its largest value, the texture the normalised map), ``Ns`` = the median
    exponent, ``illum 2``; diffuse models ``Ks 0`` and ``illum 1``; radiance models ``map_Kd`` =
    radiance and ``illum 0``. Vertices and normals are turned so the model's up axis is +y. With
    ``config.copy_maps`` the EXR maps are copied into ``out_dir/maps/``. Every file is written
    atomically (a temporary file, then a rename).

    Returns:
        A summary dict. Raises InputError / ConfigError as :func:`export_gltf`.
    """
    cfg = config or ExportConfig()
    _check_config(cfg)
    m = registry.load_model_folder(model_dir)
    return _export_obj(m, m.export_material(cfg), cfg, Path(out_dir))


def _export_obj(m: registry.FittedModel, mat: registry.ExportMaterial, cfg: ExportConfig, out: Path) -> dict:
    if out.exists() and not out.is_dir():
        raise InputError("output path exists and is not a folder", out, "choose another output folder")
    out.mkdir(parents=True, exist_ok=True)
    stem = cfg.name
    kd = f"{stem}_{mat.label}.png"
    write_image(out / kd, mat.base, bits=8)
    lines = [f"# texstream export: {mat.name} model (conversions: docs/export.md)", "newmtl texstream",
             "Ka 0 0 0", "Kd 1 1 1", f"map_Kd {kd}"]
    if mat.specular is not None:
        ks = f"{stem}_specular.png"
        write_image(out / ks, mat.specular, bits=8)
        s = mat.specular_scale
        lines += [f"Ks {s:.6g} {s:.6g} {s:.6g}", f"map_Ks {ks}", f"Ns {mat.ns:.6g}", "illum 2"]
    else:
        lines += ["Ks 0 0 0", "illum 0" if mat.unlit else "illum 1"]
    lines += ["d 1", ""]
    mtl = "\n".join(lines).encode()
    outputs.write_atomic_with(out / f"{stem}.mtl", lambda fh: fh.write(mtl))

    up = _up_rotation(cfg.up_axis)
    v = np.asarray(m.mesh.vertices, dtype=np.float64) @ up.T
    n = _unit_normals(m.mesh) @ up.T
    f = np.asarray(m.mesh.faces, dtype=np.int64) + 1
    header = (f"# texstream export: {m.mesh.n_vertices} vertices, {m.mesh.n_faces} faces, "
              f"up {cfg.up_axis} -> +y\n")
    parts = [header, f"mtllib {stem}.mtl\n", f"o {stem}\n",
             _rows(v, "v", "%.9g"), _rows(np.asarray(m.mesh.uvs, np.float64), "vt", "%.9g"),
             _rows(n, "vn", "%.7g"), "usemtl texstream\n", _rows(np.repeat(f, 3, axis=1), "f", "%d/%d/%d")]
    obj = "".join(parts).encode()
    outputs.write_atomic_with(out / f"{stem}.obj", lambda fh: fh.write(obj))
    info = _info(m, mat, cfg)
    info["path"] = str(out / f"{stem}.obj")
    if cfg.copy_maps:
        info["maps"] = _copy_maps(m, out / "maps")
    return info


def _rows(a: np.ndarray, prefix: str, fmt: str) -> str:
    if len(a) == 0:
        return ""
    row = prefix + " " + " ".join([fmt] * (a.shape[1] // fmt.count("%"))) + "\n"
    return (row * len(a)) % tuple(a.reshape(-1).tolist())


# ---------------------------------------------------------------------------------------------
# the stage


def export_stage(model_dir, out_dir, config: ExportConfig | None = None) -> StageResult:
    """Export a model folder to ``out_dir`` (written atomically: complete, or untouched on error).

    ``out_dir`` gets ``NAME.glb`` and/or ``NAME.obj`` + ``NAME.mtl`` + ``NAME_*.png``, ``maps/`` (the
    EXR maps), ``export.json`` (what was written and the conversion factors) and
    ``export_config.json`` (the resolved options).
    """
    cfg = config or ExportConfig()
    _check_config(cfg)
    m = registry.load_model_folder(model_dir)  # fail before touching out_dir
    mat = m.export_material(cfg)
    one = dataclasses.replace(cfg, copy_maps=False)
    with atomic_output_dir(out_dir) as tmp:
        written: dict = {}
        if "glb" in cfg.formats:
            with phase("export", f"glTF binary {cfg.name}.glb"):
                written["glb"] = _export_gltf(m, mat, one, tmp / f"{cfg.name}.glb")
        if "obj" in cfg.formats:
            with phase("export", f"OBJ + MTL + PNG textures {cfg.name}.obj"):
                written["obj"] = _export_obj(m, mat, one, tmp)
        maps = _copy_maps(m, tmp / "maps") if cfg.copy_maps else []
        for w in written.values():
            w["path"] = Path(w["path"]).name
        files = {k: w["path"] for k, w in written.items()}
        if mat.environment is not None:  # the estimated light a viewer lights the lit glTF with
            write_image(tmp / "environment.exr", mat.environment, bits=32)
            files["environment"] = "environment.exr"
        summary = {**next(iter(written.values())), "files": files, "maps": maps, "model": str(m.folder.resolve())}
        summary.pop("path", None)
        write_json_atomic(tmp / "export.json", summary)
        save_config(cfg, tmp / "export_config.json")
    return StageResult(Path(out_dir), summary)
