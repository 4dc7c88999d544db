"""fit/export.py: glTF 2.0 binary and OBJ + MTL from a model folder, read back by independent readers.

Each test builds a tiny model folder (a 2 x 2-quad flat sample with UVs, 8 x 8 parameter maps in
four quadrants of known values, model.json with the layout, a bake.npz ``covered`` mask) through the
project's own writers (geometry.mesh_io.save_mesh, capture.synthetic.param_maps.write_param_maps); no fit, no Warp
kernels, CPU only.

Texture tolerance: the exporter sRGB-encodes float32 values and rounds them to the nearest 8-bit
code, so a decoded code sits within half a code (0.5 / 255, plus float32 rounding of the encode) of
the exact sRGB value of the known linear albedo; the tests check exactly that bound.
"""

from __future__ import annotations

import io
import json
import math
import types

import numpy as np
import PIL.Image as PIL_Image
import pygltflib
import pytest
import trimesh

from texstream.capture.imageio import linear_to_srgb
from texstream.capture.synthetic.procedural import flat_sample
from texstream.capture.synthetic.param_maps import write_param_maps
from texstream.core.config import load_config
from texstream.core.errors import ConfigError, InputError
from texstream.fit.stages import export as E
from texstream.render.layout import MODEL_KINDS, ModelLayout
from texstream.render.mesh import SurfaceMesh
from texstream.geometry.mesh_io import load_mesh, save_mesh

H = W = 8
HALF_CODE = 0.5 / 255 + 1e-6  # nearest-code rounding (+ float32 encode)
Z_UP_TO_Y_UP = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])
# quadrants (row block, column block): top-left, top-right, bottom-left, bottom-right of the image
RHO_D = {(0, 0): (0.05, 0.10, 0.20), (0, 1): (0.30, 0.20, 0.10), (1, 0): (0.0, 0.01, 0.30),
         (1, 1): (0.35, 0.35, 0.35)}
RHO_S = {(0, 0): (0.5, 0.5, 0.5), (0, 1): (3.0, 3.0, 3.0), (1, 0): (20.0, 20.0, 20.0),
         (1, 1): (0.3, 0.15, 0.06)}
EXPONENT = {(0, 0): 10.0, (0, 1): 100.0, (1, 0): 1000.0, (1, 1): 1.0}
UNCOVERED = (3, 3)  # off the surface: a wild value there must not set the specular scale


def quadrant_map(table: dict, channels: int) -> np.ndarray:
    out = np.zeros((H, W, channels))
    for (by, bx), v in table.items():
        out[by * H // 2:(by + 1) * H // 2, bx * W // 2:(bx + 1) * W // 2] = v
    return out


def make_model(folder, kind: str = "lafortune", n_lobes: int = 1, mesh: SurfaceMesh | None = None):
    """A model folder as ``texstream fit`` writes it (the files export reads); returns the grid, the
    covered mask and the mesh as read back from mesh.obj (vertex order as the exporter sees it)."""
    folder.mkdir(parents=True, exist_ok=True)
    save_mesh(folder / "mesh.obj", mesh or flat_sample(1.0, 2))
    lay = ModelLayout(kind, n_lobes)
    rho_s = quadrant_map(RHO_S, 3)
    n = quadrant_map(EXPONENT, 1)[..., 0]
    rho_s[UNCOVERED] = 1000.0
    grid = lay.pack(quadrant_map(RHO_D, 3), [{"rho_s": rho_s, "n": n}] * n_lobes).astype(np.float32)
    files = write_param_maps(folder, grid, lay)
    covered = np.ones((H, W), bool)
    covered[UNCOVERED] = False
    np.savez(folder / "bake.npz", covered=covered)
    (folder / "model.json").write_text(json.dumps({"kind": kind, "layout": lay.to_json(), "maps": files,
                                                   "mesh": "mesh.obj", "bake": "bake.npz"}))
    return grid.astype(np.float64), covered, load_mesh(folder / "mesh.obj")


def expected_f0(grid, covered, n_lobes=1):
    lay = ModelLayout("lafortune", n_lobes)
    offsets = [lay.lobe_offset(j) for j in range(n_lobes)]
    f0 = sum(E.lobe_albedo(grid[..., o:o + 3], grid[..., o + 5]) for o in offsets)
    f0 = np.clip(f0, 0, 1)
    return f0, float(f0[covered].max())


def glb_images(path) -> tuple[object, dict]:
    """pygltflib's document and its embedded images decoded by PIL, by image name."""
    gl = pygltflib.GLTF2.load(str(path))
    blob = gl.binary_blob()
    images = {}
    for im in gl.images:
        bv = gl.bufferViews[im.bufferView]
        png = blob[bv.byteOffset:bv.byteOffset + bv.byteLength]
        images[im.name] = np.asarray(PIL_Image.open(io.BytesIO(png)))
    return gl, images


def assert_srgb_codes(codes: np.ndarray, linear: np.ndarray) -> None:
    err = np.abs(codes.astype(np.float64) / 255 - linear_to_srgb(np.clip(linear, 0, 1)))
    assert err.max() <= HALF_CODE, err.max()


# --------------------------------------------------------------------------- conversions


def test_lobe_conversion_table_reproduces_the_documented_errors():
    """The numbers in the module doc (and docs/export.md) come from this function."""
    rows = {int(r["n"]): r for r in E.lobe_conversion_table((1, 10, 100, 1000, 10000))}
    documented = {1: (0.424, -0.27, 0.44, 0.76, 0.93), 10: (0.235, -0.11, 0.094, 0.93, 0.75),
                  100: (0.0836, -0.076, 0.061, 0.99, 0.70), 1000: (0.0268, -0.076, 0.058, 1.00, 0.70),
                  10000: (0.0085, -0.067, 0.058, 1.00, 0.69)}
    for n, (alpha, width, shape, albedo, peak) in documented.items():
        r = rows[n]
        assert r["alpha"] == pytest.approx(alpha, rel=0.01)
        assert r["roughness"] == pytest.approx(math.sqrt(r["alpha"]))
        assert r["fwhm_error"] == pytest.approx(width, abs=0.006)
        assert r["max_shape_diff"] == pytest.approx(shape, abs=0.006)
        assert r["ggx_albedo"] == pytest.approx(albedo, abs=0.006)
        assert r["peak_ratio"] == pytest.approx(peak, abs=0.006)
    # the textbook chain (Blinn-Phong 4n, Walter et al.) is ~2.7x further from the Lafortune lobe's shape
    blinn = {int(r["n"]): r for r in E.lobe_conversion_table((10, 100, 1000), "blinn4")}
    for n in (10, 100, 1000):
        assert rows[n]["max_shape_diff"] < blinn[n]["max_shape_diff"]
        assert abs(rows[n]["fwhm_error"]) < abs(blinn[n]["fwhm_error"])
    assert blinn[1000]["fwhm_error"] == pytest.approx(-0.23, abs=0.006)


def test_lobe_albedo_and_ggx_normalisation_agree_with_quadrature():
    """lobe_albedo is the hemispherical integral of the lobe (light along the normal); the GGX lobe
    used for the error table conserves energy for small alpha (its albedo with F0 = 1 tends to 1)."""
    th = np.linspace(0, np.pi / 2, 200001)
    for n in (1.0, 10.0, 300.0):
        y = np.cos(th) ** n * np.cos(th) * np.sin(th)
        quad = 2 * np.pi * np.sum(0.5 * (y[1:] + y[:-1]) * np.diff(th))
        assert E.lobe_albedo(np.ones(3), n)[0] == pytest.approx(quad, rel=1e-6)
    g = E.ggx_lobe_inplane(0.01, 0.0, th[:-1])
    albedo = 2 * np.pi * np.sum(g * np.cos(th[:-1]) * np.sin(th[:-1]) * np.diff(th))
    assert albedo == pytest.approx(1.0, abs=2e-3)
    assert np.all(np.diff(E.roughness_from_exponent(np.array([1, 10, 100, 1e4]))) < 0)
    with pytest.raises(ConfigError):
        E.ggx_alpha_from_exponent(10.0, "beckmann?")


# --------------------------------------------------------------------------- glTF


def test_glb_reads_back_with_pygltflib_and_trimesh(tmp_path):
    grid, covered, mesh = make_model(tmp_path / "model")
    info = E.export_gltf(tmp_path / "model", tmp_path / "out" / "model.glb")
    assert (info["vertices"], info["faces"]) == (9, 8)
    _, scale = expected_f0(grid, covered)
    assert 0 < scale < 1  # the uncovered texel (F0 clipped to 1) is left out
    assert info["specular_scale"] == pytest.approx(scale, rel=1e-6)
    assert info["base_colour_clipped_texels"] == 16  # the bottom-right quadrant: pi * 0.35 > 1

    gl, images = glb_images(tmp_path / "out" / "model.glb")
    assert gl.extensionsUsed == ["KHR_materials_specular"]
    mat = gl.materials[0]
    # the core material fitted to the model (tests/test_gltf_core_material.py renders it): metallic and roughness
    # in the texture (B, G; linear), the factors 1; KHR_materials_specular's F0 on top
    pbr = E.registry.load_model_folder(tmp_path / "model").export_material(E.ExportConfig()).pbr
    assert mat.pbrMetallicRoughness.metallicFactor == 1.0
    assert mat.pbrMetallicRoughness.roughnessFactor == 1.0
    spec = mat.extensions["KHR_materials_specular"]
    s = float(pbr.specular_f0[covered].max())
    assert spec["specularFactor"] == 1.0
    assert spec["specularColorFactor"] == pytest.approx([s / 0.04] * 3)
    assert info["gltf_material"]["directions"].startswith("flash set")
    assert gl.nodes[0].rotation == pytest.approx([-math.sqrt(0.5), 0, 0, math.sqrt(0.5)])
    assert_srgb_codes(images["base_color"], pbr.base_color)
    assert_srgb_codes(images["specular_color"], pbr.specular_f0 / s)
    assert np.abs(images["metallic_roughness"][..., 1] / 255 - pbr.roughness).max() <= HALF_CODE
    assert np.abs(images["metallic_roughness"][..., 2] / 255 - pbr.metallic).max() <= HALF_CODE
    # sharper lobes, smoother surfaces
    rough = {n: images["metallic_roughness"][by * 4 + 1, bx * 4 + 1, 1] for (by, bx), n in EXPONENT.items()}
    assert rough[10.0] > rough[100.0] > rough[1000.0]

    scene = trimesh.load(tmp_path / "out" / "model.glb")
    tm = scene.to_geometry()  # node transform applied
    assert tm.vertices.shape == (9, 3) and tm.faces.shape == (8, 3)
    np.testing.assert_allclose(tm.vertices, mesh.vertices @ Z_UP_TO_Y_UP.T, atol=1e-6)
    assert np.allclose(tm.vertex_normals, [0, 1, 0], atol=1e-6)  # +z (the sample's normal) is now up
    np.testing.assert_allclose(tm.visual.uv, mesh.uvs, atol=1e-6)  # trimesh flips glTF's v back to v up
    mat_t = tm.visual.material
    assert mat_t.metallicFactor == 1.0
    np.testing.assert_array_equal(np.asarray(mat_t.baseColorTexture.convert("RGB")), images["base_color"])
    # orientation: the vertex at UV (0, 1) (top-left of the image, v up) shows the top-left quadrant, etc.
    corners = np.array([[0.0, 1.0], [1.0, 1.0], [0.0, 0.0], [1.0, 0.0]])
    got = trimesh.visual.color.uv_to_color(corners, mat_t.baseColorTexture)[:, :3]
    for c, q in zip(got, [(0, 0), (0, 1), (1, 0), (1, 1)]):
        assert_srgb_codes(c, pbr.base_color[q[0] * 4 + 1, q[1] * 4 + 1])
    maps = sorted(p.name for p in (tmp_path / "out" / "maps").iterdir())
    assert maps == ["lobe0_rho_s.exr", "lobe0_shape.exr", "rho_d.exr"]


def test_glb_of_two_lobes_sums_albedos_and_takes_the_dominant_width(tmp_path):
    _, covered, _ = make_model(tmp_path / "model", n_lobes=2)
    lay = ModelLayout("lafortune", 2)
    lobes = [{"rho_s": quadrant_map(RHO_S, 3), "n": quadrant_map(EXPONENT, 1)[..., 0]},
             {"rho_s": np.full((H, W, 3), 0.17), "n": np.full((H, W), 5.0)}]
    grid = lay.pack(quadrant_map(RHO_D, 3), lobes)
    write_param_maps(tmp_path / "model", grid.astype(np.float32), lay)
    E.export_obj(tmp_path / "model", tmp_path / "obj", E.ExportConfig(copy_maps=False))
    f0, scale = expected_f0(grid, covered, 2)
    assert_srgb_codes(np.asarray(PIL_Image.open(tmp_path / "obj" / "model_specular.png").convert("RGB")), f0 / scale)
    m = E.registry.load_model_folder(tmp_path / "model").export_material(E.ExportConfig())
    a0 = E.lobe_albedo(grid[..., 3:6], grid[..., 8]).mean(-1)
    a1 = E.lobe_albedo(grid[..., 9:12], grid[..., 14]).mean(-1)
    assert (a1 > a0).any() and (a0 > a1).any()  # each lobe dominates somewhere
    n_dominant = np.where(a1 > a0, grid[..., 14], grid[..., 8])
    assert np.abs(m.roughness - E.roughness_from_exponent(n_dominant)).max() < 1e-12  # OBJ's Ns and the table
    # glTF: the core material fitted to both lobes together (its error below the export before's)
    fit = m.pbr.fit
    assert fit["relative_rms_core"] < fit["relative_rms_before_core"]
    assert not (tmp_path / "maps").exists()


def test_diffuse_only_model_gets_the_core_material_closest_to_lambert(tmp_path):
    """A core viewer always adds a GGX layer of F0 >= 0.04; the fit darkens the base colour for it (by at most 0.04,
    that layer's reflectance along the normal) and keeps metallic near 0. OBJ keeps the albedo."""
    grid, covered, _ = make_model(tmp_path / "model", kind="diffuse", n_lobes=0)
    E.export_gltf(tmp_path / "model", tmp_path / "d.glb")
    gl, images = glb_images(tmp_path / "d.glb")
    assert gl.extensionsUsed == ["KHR_materials_specular"]
    pbr = E.registry.load_model_folder(tmp_path / "model").export_material(E.ExportConfig()).pbr
    assert_srgb_codes(images["base_color"], pbr.base_color)
    albedo = np.clip(np.pi * grid[..., 0:3], 0, 1)
    lit = covered[..., None] & (albedo > 0.05) & (albedo < 0.95)
    assert np.all(np.abs(pbr.base_color - albedo)[lit] <= 0.04)
    assert np.median(pbr.metallic[covered]) <= 0.05
    assert pbr.fit["relative_rms_core"] <= pbr.fit["relative_rms_before_core"]
    E.export_obj(tmp_path / "model", tmp_path / "obj", E.ExportConfig(copy_maps=False))
    mtl = (tmp_path / "obj" / "model.mtl").read_text().split("\n")
    assert "Ks 0 0 0" in mtl and "illum 1" in mtl


def radiance_model(folder, monkeypatch):
    """A radiance model folder; while fit/models.py does not know the kind yet (another change), the
    loader is stubbed with the layout that change adds (3 columns: radiance.L.r/g/b)."""
    mesh = flat_sample(1.0, 2)
    radiance = quadrant_map({(0, 0): (0.2, 0.4, 0.8), (0, 1): (1.5, 0.5, 0.0), (1, 0): (0.01, 0.02, 0.03),
                             (1, 1): (0.9, 0.9, 0.9)}, 3)
    folder.mkdir(parents=True)
    save_mesh(folder / "mesh.obj", mesh)
    if "radiance" in MODEL_KINDS:
        lay = ModelLayout("radiance", 0)
        files = write_param_maps(folder, radiance.astype(np.float32), lay)
        layout_json = lay.to_json()
    else:
        files = {"radiance": "radiance.exr"}
        layout_json = {"kind": "radiance", "n_lobes": 0, "anisotropic": False}
        stub = types.SimpleNamespace(kind="radiance", n_lobes=0, n_params=3)
        from texstream.fit.stages import stage

        def load_model(d):
            man = json.loads((d / "model.json").read_text())
            return mesh.with_normals(), radiance.astype(np.float32), stub, man

        monkeypatch.setattr(stage, "load_model", load_model)
    (folder / "model.json").write_text(json.dumps({"kind": "radiance", "layout": layout_json, "maps": files}))
    return radiance


def test_radiance_model_exports_an_unlit_material(tmp_path, monkeypatch):
    radiance = radiance_model(tmp_path / "model", monkeypatch)
    cfg = E.ExportConfig(radiance_scale=0.5, copy_maps=False)
    info = E.export_gltf(tmp_path / "model", tmp_path / "r.glb", cfg)
    assert info["kind"] == "radiance" and info["base_colour_clipped_texels"] == 0
    gl, images = glb_images(tmp_path / "r.glb")
    assert gl.extensionsUsed == ["KHR_materials_unlit"]
    mat = gl.materials[0]
    assert mat.extensions == {"KHR_materials_unlit": {}}  # no KHR_materials_specular: the spec forbids both
    assert mat.pbrMetallicRoughness.metallicFactor == 0.0
    assert_srgb_codes(images["base_color"], 0.5 * radiance)
    E.export_gltf(tmp_path / "model", tmp_path / "r1.glb", E.ExportConfig(copy_maps=False))
    _, images = glb_images(tmp_path / "r1.glb")
    assert_srgb_codes(images["base_color"], np.clip(radiance, 0, 1))  # 1.5 clips to white

    E.export_obj(tmp_path / "model", tmp_path / "obj", cfg)
    mtl = (tmp_path / "obj" / "model.mtl").read_text().split("\n")
    assert "illum 0" in mtl and "map_Kd model_radiance.png" in mtl
    tm = trimesh.load(tmp_path / "obj" / "model.obj", process=False)
    assert_srgb_codes(np.asarray(tm.visual.material.image.convert("RGB")), 0.5 * radiance)


# --------------------------------------------------------------------------- OBJ


def test_obj_and_mtl_read_back_with_trimesh(tmp_path):
    grid, covered, mesh = make_model(tmp_path / "model")
    info = E.export_obj(tmp_path / "model", tmp_path / "obj")
    out = tmp_path / "obj"
    assert sorted(p.name for p in out.iterdir()) == ["maps", "model.mtl", "model.obj", "model_basecolor.png",
                                                     "model_specular.png"]
    tm = trimesh.load(out / "model.obj", process=False)
    assert tm.vertices.shape == (9, 3) and tm.faces.shape == (8, 3)
    np.testing.assert_allclose(tm.vertices, mesh.vertices @ Z_UP_TO_Y_UP.T, atol=1e-7)
    np.testing.assert_allclose(tm.visual.uv, mesh.uvs, atol=1e-7)  # OBJ keeps v up
    mat = tm.visual.material
    assert_srgb_codes(np.asarray(mat.image.convert("RGB")), np.pi * grid[..., 0:3])  # map_Kd resolved
    f0, scale = expected_f0(grid, covered)
    mtl = dict(line.split(" ", 1) for line in (out / "model.mtl").read_text().splitlines()
               if line and not line.startswith("#"))
    assert [float(x) for x in mtl["Ks"].split()] == pytest.approx([scale] * 3, rel=1e-5)
    assert float(mtl["Ns"]) == info["mtl_ns"] == pytest.approx(np.median(grid[..., 8][covered]))  # 100 here
    assert mtl["illum"] == "2" and mtl["map_Ks"] == "model_specular.png"
    assert_srgb_codes(np.asarray(PIL_Image.open(out / "model_specular.png").convert("RGB")), f0 / scale)


def test_up_axis_y_keeps_coordinates(tmp_path):
    _, _, mesh = make_model(tmp_path / "model")
    cfg = E.ExportConfig(up_axis="y", copy_maps=False)
    E.export_obj(tmp_path / "model", tmp_path / "obj", cfg)
    E.export_gltf(tmp_path / "model", tmp_path / "m.glb", cfg)
    obj = trimesh.load(tmp_path / "obj" / "model.obj", process=False)
    np.testing.assert_allclose(obj.vertices, mesh.vertices, atol=1e-7)
    assert pygltflib.GLTF2.load(str(tmp_path / "m.glb")).nodes[0].rotation is None
    glb = trimesh.load(tmp_path / "m.glb").to_geometry()
    np.testing.assert_allclose(glb.vertices, mesh.vertices, atol=1e-6)


# --------------------------------------------------------------------------- the stage and bad input


def test_export_stage_writes_the_folder_with_its_config(tmp_path):
    make_model(tmp_path / "model")
    cfg = E.ExportConfig(formats=("glb", "obj"), roughness="blinn4")
    res = E.export_stage(tmp_path / "model", tmp_path / "export", cfg)
    out = tmp_path / "export"
    assert res.output == out
    assert sorted(p.name for p in out.iterdir()) == ["export.json", "export_config.json", "maps", "model.glb",
                                                     "model.mtl", "model.obj", "model_basecolor.png",
                                                     "model_specular.png"]
    assert load_config(E.ExportConfig, out / "export_config.json") == cfg
    summary = json.loads((out / "export.json").read_text())
    assert summary["files"] == {"glb": "model.glb", "obj": "model.obj"}
    assert summary["roughness_conversion"] == "blinn4"
    assert summary["maps"] == ["maps/rho_d.exr", "maps/lobe0_rho_s.exr", "maps/lobe0_shape.exr"]
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary folder left
    # glb only, overwriting: the folder is replaced as a whole
    E.export_stage(tmp_path / "model", out, E.ExportConfig(formats=("glb",), copy_maps=False))
    assert sorted(p.name for p in out.iterdir()) == ["export.json", "export_config.json", "model.glb"]


def _no_uvs(folder):
    m = flat_sample(1.0, 2)
    save_mesh(folder / "mesh.obj", SurfaceMesh(m.vertices, m.faces))


@pytest.mark.parametrize("damage, names", [
    (lambda d: None, "no_folder"),
    (lambda d: (d / "model.json").unlink(), "model.json"),
    (lambda d: (d / "model.json").write_text("{not json"), "model.json"),
    (lambda d: (d / "model.json").write_text('{"maps": {}}'), "model.json"),
    (lambda d: (d / "model.json").write_text('{"layout": {"kind": "phong", "n_lobes": 1}}'), "model.json"),
    (lambda d: (d / "model.json").write_text('{"layout": {"kind": "lafortune"}}'), "model.json"),
    (lambda d: (d / "lobe0_shape.exr").unlink(), "lobe0_shape.exr"),
    (lambda d: (d / "mesh.obj").unlink(), "mesh.obj"),
    (_no_uvs, "mesh.obj"),
])
def test_bad_model_folder_is_an_input_error_naming_the_file(tmp_path, damage, names):
    d = tmp_path / "model"
    if names != "no_folder":
        make_model(d)
        damage(d)
    with pytest.raises(InputError) as err:
        E.export_stage(d, tmp_path / "export")
    msg = str(err.value)
    assert (str(d) if names == "no_folder" else names) in msg and "Fix:" in msg
    assert not (tmp_path / "export").exists()


def test_bad_options_are_config_errors(tmp_path):
    make_model(tmp_path / "model")
    for cfg in (E.ExportConfig(formats=("fbx",)), E.ExportConfig(formats=()), E.ExportConfig(up_axis="x"),
                E.ExportConfig(radiance_scale=0.0), E.ExportConfig(name="../x")):
        with pytest.raises(ConfigError):
            E.export_stage(tmp_path / "model", tmp_path / "export", cfg)
    assert not (tmp_path / "export").exists()
