"""Export of light field mapping models (fit/export.py): the unlit approximation written as glTF /
OBJ base colour, its view-map means, and the EXR maps alongside."""

from __future__ import annotations

import json

import numpy as np
import pytest

from conftest import SCENE_DEVICE
from lfm_scenes import fixed_light_sphere_capture

from texstream.fit.stages import export as E


@pytest.fixture(scope="module")
def lfm_model(tmp_path_factory):
    """A K = 1 LFM fit (20 CG iterations) of the fixed-light sphere."""
    from texstream.fit.optim.fitter import FitConfig
    from texstream.fit.models.lfm.problem import LFMConfig
    from texstream.fit.stages.stage import FitStageConfig, fit_stage

    root = tmp_path_factory.mktemp("lfm_export")
    cap = fixed_light_sphere_capture(root, photos=24, device=SCENE_DEVICE)
    cfg = FitStageConfig(holdout_every=8, renders=0, device=SCENE_DEVICE,
                         fit=FitConfig(model="lfm", lfm=LFMConfig(iterations=20)))
    fit_stage(cap, cap / "ground_truth", root / "model", cfg, progress=False)
    return root / "model"


@pytest.mark.parametrize("mapping", ["disk", "hemioct"])
@pytest.mark.parametrize("lookup", ["bilinear", "nearest"])
def test_view_mean_weights_average_the_renderers_lookups(device, mapping, lookup):
    from texstream.fit.models.lfm.problem import view_directions

    res = 32
    w = E.view_mean_weights(res, mapping, lookup, device)
    assert w.shape == (res * res,) and (w >= 0).all() and w.sum() == pytest.approx(1.0, abs=1e-12)
    d = view_directions(res, mapping)
    # the sampling is symmetric under x -> -x and y -> -y: an odd view map averages to 0 (round-off);
    # nearest lookups send a direction on a texel boundary to the upper texel (floor), which breaks the
    # symmetry by a few of the 12,868 directions (each 7.8e-5 of the weight; measured 3.3e-4)
    tol = 1e-12 if lookup == "bilinear" else 1e-3
    assert abs(w @ d[:, 0]) < tol and abs(w @ d[:, 1]) < tol
    # a map holding cos(theta) at its texel centres: the cosine-weighted mean of cos(theta) is 2/3; the
    # map's texels (and the nearest / bilinear reconstruction between them) leave a discretisation error
    # of about a texel's share of the rim, 1/R (measured 0.23% to 0.47% low at R = 32)
    assert w @ d[:, 2] == pytest.approx(2.0 / 3.0, rel=1.0 / res)


def test_unlit_equals_the_full_model_when_the_view_maps_are_constant(lfm_model, tmp_path):
    """With every view map constant the LFM is view independent, and its unlit export (rendered by the
    radiance renderer from the exported atlas) is the full model (float32 round-off)."""
    import shutil

    from texstream.capture.capture_json import read_capture
    from texstream.fit.models.lfm.model_folder import load_lfm_model

    model = tmp_path / "model"
    shutil.copytree(lfm_model, model)
    z = dict(np.load(model / "lfm.npz"))
    rng = np.random.default_rng(3)
    z["G"] = np.abs(z["G"])  # radiance >= 0 everywhere: the LFM renderer's clamp at 0 never acts
    z["H"] = np.broadcast_to(rng.uniform(0.5, 1.5, (*z["H"].shape[:2], 1, 3)), z["H"].shape).copy()
    np.savez(model / "lfm.npz", **z)
    m = load_lfm_model(model)
    frame = read_capture(lfm_model.parent / "cap").frames[7]
    full, mask = m.renderer(SCENE_DEVICE).render_frame(frame)
    unlit, umask = E.lfm_unlit_renderer(m, "cosine", SCENE_DEVICE)(frame)
    assert mask.sum() > 100 and (mask == umask).all()
    # float32 atlas and renders of values ~0.1 to 1
    np.testing.assert_allclose(unlit[mask], full[mask], rtol=1e-5, atol=1e-6)
    # and "none" drops the view terms: d alone
    d_only, _ = E.lfm_unlit_renderer(m, "none", SCENE_DEVICE)(frame)
    assert np.abs(d_only[mask] - full[mask]).max() > 0.05


def test_lfm_exports_an_unlit_glb_and_obj_with_its_maps(lfm_model, tmp_path):
    from texstream.fit.models.lfm.model_folder import load_lfm_model
    from test_fit_export import assert_srgb_codes, glb_images, trimesh  # the independent readers (test extra)

    out = tmp_path / "export"
    res = E.export_stage(lfm_model, out)
    s = res.summary
    assert s["model_kind"] == "lfm" and s["kind"] == "radiance" and s["lfm_view_mean"] == "cosine"
    names = ("diffuse", "surface_k0_v0", "surface_k0_v1", "surface_k0_v2", "view_k0")
    assert sorted(s["maps"]) == sorted(f"maps/{n}.exr" for n in names)
    assert all((out / f).is_file() for f in s["maps"])
    model = load_lfm_model(lfm_model)
    unlit = E.lfm_atlas(model, E.lfm_unlit_radiance(model, "cosine"))
    gl, images = glb_images(out / "model.glb")
    assert gl.extensionsUsed == ["KHR_materials_unlit"]
    assert gl.materials[0].extras["texstream"]["model_kind"] == "lfm"
    assert_srgb_codes(images["base_color"], unlit)
    glb = trimesh.load(out / "model.glb").to_geometry()
    assert len(glb.faces) == model.mesh.n_faces
    mtl = (out / "model.mtl").read_text().split("\n")
    assert "illum 0" in mtl and "map_Kd model_radiance.png" in mtl
    tm = trimesh.load(out / "model.obj", process=False)
    assert_srgb_codes(np.asarray(tm.visual.material.image.convert("RGB")), unlit)
    # lfm_view_mean "none": the view-independent term alone
    E.export_gltf(lfm_model, tmp_path / "d.glb", E.ExportConfig(lfm_view_mean="none", copy_maps=False))
    _, images = glb_images(tmp_path / "d.glb")
    assert_srgb_codes(images["base_color"], E.lfm_atlas(model, model.params.diffuse))
    assert json.loads((out / "export_config.json").read_text())["lfm_view_mean"] == "cosine"


def test_a_broken_lfm_folder_is_an_input_error(lfm_model, tmp_path):
    import shutil

    from texstream.core.errors import ConfigError, InputError

    model = tmp_path / "model"
    shutil.copytree(lfm_model, model)
    (model / "lfm.npz").unlink()
    with pytest.raises(InputError, match="lfm.npz"):
        E.export_stage(model, tmp_path / "out")
    assert not (tmp_path / "out").exists()
    with pytest.raises(ConfigError, match="lfm_view_mean"):
        E.export_stage(lfm_model, tmp_path / "out", E.ExportConfig(lfm_view_mean="max"))
