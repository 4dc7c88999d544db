"""The glb's core metallic-roughness material (fit/models/lafortune/gltf_core.py) as a core glTF viewer shades it.

A flat Lafortune sample (capture/synthetic/procedural.py ``flat_sample``, uniform maps) is exported; its glb is read
back with pygltflib and PIL (textures decoded as glTF says: baseColorTexture sRGB, metallicRoughnessTexture linear)
and rendered here by a small numpy implementation of the glTF BRDF for a punctual light, written from the
specification (Lambert + GGX, Smith height-correlated visibility, Schlick's Fresnel with F0 = mix(0.04, baseColor,
metallic); KHR_materials_specular: the dielectric F0 = 0.04 specularColorFactor specularColorTexture) and from no
texstream code. Camera and point light are a flash capture's (the light 0.15 beside the camera, the view near the
normal, where the lobe's highlight falls on the sample); texstream's own ray-traced render of the model folder is
the reference.

CPU only; the fits are of 64 texels over the flash set (milliseconds), the renders 48 x 48.
"""

from __future__ import annotations

import io
import json
import math

import numpy as np
import pygltflib
import pytest
from PIL import Image as PIL_Image

from texstream.capture.capture_json import Frame, Intrinsics, Light
from texstream.capture.imageio import linear_to_srgb
from texstream.capture.synthetic.param_maps import write_param_maps
from texstream.capture.synthetic.procedural import flat_sample
from texstream.fit.models.lafortune import gltf_core
from texstream.fit.stages import export as E
from texstream.geometry.mesh_io import save_mesh
from texstream.render.layout import ModelLayout
from texstream.render.pose import look_at_w2c
from texstream.render.renderer import Renderer


N = 8  # texels a side
SIZE = 48  # pixels a side
EYE, LIGHT, INTENSITY = np.array([0.08, -0.12, 1.1]), np.array([0.2, -0.05, 1.1]), 1.2


def spec_brdf(base, metallic, roughness, light, view, f0_dielectric=0.04):
    """The glTF BRDF for a punctual light (specification, Appendix B, with three.js's and Filament's diffuse
    term: no (1 - F) factor): (..., 3) unit vectors in a frame with the normal +z."""
    h = light + view
    h = h / np.linalg.norm(h, axis=-1, keepdims=True)
    nl, nv, nh, vh = light[..., 2], view[..., 2], h[..., 2], np.sum(view * h, axis=-1)
    a2 = roughness ** 4
    d = a2 / (np.pi * (nh ** 2 * (a2 - 1) + 1) ** 2)
    vis = 0.5 / (nl * np.sqrt(nv ** 2 * (1 - a2) + a2) + nv * np.sqrt(nl ** 2 * (1 - a2) + a2))
    f0 = (1 - metallic) * np.asarray(f0_dielectric) + metallic * np.asarray(base)
    fresnel = f0 + (1 - f0) * ((1 - vh) ** 5)[..., None]
    return (1 - metallic) * np.asarray(base) / np.pi + fresnel * (d * vis)[..., None]


def srgb_decode(codes):
    c = np.asarray(codes, np.float64) / 255
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def model_folder(folder, rho_d, rho_s, n) -> ModelLayout:
    folder.mkdir(parents=True)
    save_mesh(folder / "mesh.obj", flat_sample(1.0, 2))
    lay = ModelLayout("lafortune", 1, lobe_shape="phong")
    grid = lay.pack(np.broadcast_to(rho_d, (N, N, 3)), [{"rho_s": np.broadcast_to(rho_s, (N, N, 3)),
                                                         "n": np.full((N, N), float(n))}]).astype(np.float32)
    files = write_param_maps(folder, grid, lay)
    np.savez(folder / "bake.npz", covered=np.ones((N, N), bool))
    (folder / "model.json").write_text(json.dumps({"kind": "lafortune", "layout": lay.to_json(), "maps": files,
                                                   "mesh": "mesh.obj", "bake": "bake.npz"}))
    return grid, lay


def glb_material(path):
    """The glb's material as a viewer decodes it: base colour (sRGB texture), metallic (B) and roughness (G) of
    the linear texture, the extension's dielectric F0; uniform maps, so one texel stands for all."""
    gl = pygltflib.GLTF2.load(str(path))
    blob = gl.binary_blob()
    img = {}
    for im in gl.images:
        bv = gl.bufferViews[im.bufferView]
        img[im.name] = np.asarray(PIL_Image.open(io.BytesIO(blob[bv.byteOffset:bv.byteOffset + bv.byteLength])))
    mat = gl.materials[0]
    pbr = mat.pbrMetallicRoughness
    ext = mat.extensions["KHR_materials_specular"]
    f0d = 0.04 * np.asarray(ext.get("specularColorFactor", [1.0] * 3)) * ext["specularFactor"]
    if "specular_color" in img:
        f0d = f0d * srgb_decode(img["specular_color"][N // 2, N // 2, :3])
    mr = img["metallic_roughness"][N // 2, N // 2]
    return {"base": srgb_decode(img["base_color"][N // 2, N // 2, :3]), "metallic": mr[2] / 255 * pbr.metallicFactor,
            "roughness": mr[1] / 255 * pbr.roughnessFactor, "f0d": np.minimum(f0d, 1.0), "images": img, "gltf": gl}


def frame() -> Frame:
    r, t = look_at_w2c(EYE, np.zeros(3), up=(0.0, 1.0, 0.0))
    f = 1.1 * SIZE
    return Frame("images/x.exr", r, t, Intrinsics(SIZE, SIZE, f, f, SIZE / 2, SIZE / 2),
                 Light.point(LIGHT, [INTENSITY] * 3))


def spec_render(fr: Frame, base, metallic, roughness, f0d=0.04):
    """The plane z = 0 (normal +z) under the frame's camera and light, shaded by :func:`spec_brdf`."""
    k = fr.intrinsics
    jj, ii = np.mgrid[0:SIZE, 0:SIZE] + 0.5
    d = np.stack([(ii - k.cx) / k.fx, (jj - k.cy) / k.fy, np.ones_like(ii)], -1) @ fr.R  # world directions
    c = fr.center
    p = c + (-c[2] / d[..., 2])[..., None] * d
    view = (c - p) / np.linalg.norm(c - p, axis=-1, keepdims=True)
    to_l = LIGHT - p
    r2 = np.sum(to_l ** 2, -1)
    light = to_l / np.sqrt(r2)[..., None]
    f = spec_brdf(base, metallic, roughness, light, view, f0d)
    return f * (INTENSITY * light[..., 2] / r2)[..., None]


def psnr(a, ref, m):
    """PSNR against the reference's peak (its highlight: 1.1 / 7.0 / 0.4 here), so the three samples compare."""
    return 10 * math.log10(float(ref[m].max()) ** 2 / float(np.mean((a[m] - ref[m]) ** 2)))


# glossy grey lobe on a coloured diffuse; a sharp strong lobe; a broad weak one (albedos pi rho_d <= 0.6, lobe
# albedos 2 pi rho_s / (n + 2) = 0.12 / 0.21 / 0.05)
MATERIALS = {"glossy": ((0.15, 0.08, 0.04), (1.0, 1.0, 1.0), 50.0),
             "sharp": ((0.05, 0.05, 0.06), (6.8, 6.8, 6.8), 200.0),
             "broad": ((0.12, 0.12, 0.10), (0.1, 0.09, 0.08), 10.0)}
# core-only PSNR against texstream's render, relative to the render's peak (its highlight: 1.12 / 6.49 / 0.22 for
# glossy / sharp / broad; mean 0.11): measured 30.3 / 38.8 / 37.3 dB for the fit, 20.2 / 23.8 / 25.2 dB for the
# export before (metallic 0, the lobes only in KHR_materials_specular), 32.3 / 38.8 / 37.8 dB with the extension
# read (CPU, commit of this test). The bounds keep 2 dB below: what is left is GGX's lobe shape against the Phong
# lobe's (a sharper core and heavier tails, docs/export.md), which no choice of the three maps removes, and the
# flash set's directions being a sample (the fit sees the lobe at 5-degree steps, not at these pixels).
CORE_BOUND_DB = {"glossy": 28.0, "sharp": 36.0, "broad": 35.0}


@pytest.mark.parametrize("name", sorted(MATERIALS))
def test_core_material_renders_like_texstream(tmp_path, name):
    rho_d, rho_s, n = MATERIALS[name]
    grid, lay = model_folder(tmp_path / "model", rho_d, rho_s, n)
    E.export_gltf(tmp_path / "model", tmp_path / "m.glb", E.ExportConfig(copy_maps=False))
    got = glb_material(tmp_path / "m.glb")
    fr = frame()
    res = Renderer(flat_sample(1.0, 2), grid, lay).render_frame(fr)
    ref, mask = res.radiance.astype(np.float64), res.mask
    core = spec_render(fr, got["base"], got["metallic"], got["roughness"])
    with_ext = spec_render(fr, got["base"], got["metallic"], got["roughness"], got["f0d"])
    # the export before: base = albedo, metallic 0, roughness from the exponent; the lobes only in the extension
    before = spec_render(fr, np.clip(np.pi * np.asarray(rho_d), 0, 1), 0.0, float(E.roughness_from_exponent(n)))
    p_core, p_ext, p_before = psnr(core, ref, mask), psnr(with_ext, ref, mask), psnr(before, ref, mask)
    assert p_core >= CORE_BOUND_DB[name], (p_core, p_before)
    assert p_core >= p_before + 8.0  # the lobe's energy reaches core viewers (+10 to +15 dB measured)
    # the extension's F0 is least squares given the core's maps, over the flash set (not these pixels): a viewer
    # that reads it is no worse than a core viewer, up to 0.5 dB (the flash set's directions are not these pixels')
    assert p_ext >= p_core - 0.5, (p_ext, p_core)


def test_gltf_colour_spaces(tmp_path):
    """baseColorTexture and specularColorTexture hold sRGB-encoded codes of the linear values (glTF 2.0 section
    3.9.2, KHR_materials_specular), metallicRoughnessTexture linear codes; the material's factors make them the
    fitted values."""
    rho_d, rho_s, n = MATERIALS["glossy"]
    model_folder(tmp_path / "model", rho_d, rho_s, n)
    info = E.export_gltf(tmp_path / "model", tmp_path / "m.glb", E.ExportConfig(copy_maps=False))
    got = glb_material(tmp_path / "m.glb")
    m = E.registry.load_model_folder(tmp_path / "model").export_material(E.ExportConfig())
    pbr = m.pbr
    half = 0.5 / 255 + 1e-6
    codes = got["images"]["base_color"][..., :3] / 255
    assert np.abs(codes - linear_to_srgb(pbr.base_color)).max() <= half
    assert np.abs(codes - pbr.base_color).max() > 0.05  # not stored linear: sRGB lifts these dark values
    mr = got["images"]["metallic_roughness"]
    assert np.abs(mr[..., 2] / 255 - pbr.metallic).max() <= half
    assert np.abs(mr[..., 1] / 255 - pbr.roughness).max() <= half
    s = float(pbr.specular_f0.max())
    assert info["gltf_material"]["specular_color_factor"] == pytest.approx(s / 0.04)
    spec_codes = got["images"]["specular_color"][..., :3] / 255
    assert np.abs(spec_codes - linear_to_srgb(pbr.specular_f0 / s)).max() <= half
    assert got["gltf"].materials[0].pbrMetallicRoughness.metallicFactor == 1.0
    assert pbr.metallic.max() > 0  # the lobe's energy is in the core material
