"""The resolved flash scene samples its object as issue 39 asks, the first does not (capture/synthetic/
flash_sampling.py, figures from the scenes alone: no rendering, about 3 s)."""

from texstream.capture.synthetic.flash_capture import FlashCaptureConfig
from texstream.capture.synthetic.flash_sampling import scene_sampling


def test_resolved_flash_scene_meets_the_issues_sampling_and_the_first_does_not():
    size = FlashCaptureConfig().image_size
    first = scene_sampling("flash_sphere", 24, size)
    resolved = scene_sampling("flash_sphere_resolved", 72, size)
    # the issue's "4x the pixels the atlas needs": 4 pixels a fitted texel in the median facing photo (the first's
    # photos give its atlas 1.26; the resolved scene's fit atlas has a quarter of the truth's texels: 5.0)
    assert resolved["pixels_a_fit_texel_median_facing_photo"] >= 4.0 > 2.0 > first["pixels_a_fit_texel_median_facing_photo"]
    # the same texture, finer than either fit atlas (a real object's; SIFT registers on it): the benchmarks score the
    # albedo against the truth averaged over each fitted texel
    assert resolved["fit_texels_a_noise_cell"] < 2.0 and first["fit_texels_a_noise_cell"] < 2.0
    # the exponent-40 highlight shown twice: none of the first's texels, about half of the resolved scene's that
    # show it at all (cameras along a ring within the lobe's 9.7-degree reach; between the rings none)
    assert first["highlight_shown_twice_of_shown"] == 0.0
    assert resolved["highlight_shown_twice_of_shown"] > 0.4
    assert resolved["texels_highlight_shown"] > first["texels_highlight_shown"]


def test_fit_geometry_bakes_the_truths_mesh_at_the_fit_atlas(tmp_path):
    import json

    from texstream.capture.synthetic.flash_capture import fit_geometry
    from texstream.capture.synthetic.procedural import uv_sphere
    from texstream.geometry.bake import TexelBake
    from texstream.geometry.mesh_io import save_mesh

    gt = tmp_path / "capture" / "ground_truth"
    gt.mkdir(parents=True)
    save_mesh(gt / "mesh.obj", uv_sphere(1.0, 24, 12))
    (gt / "flash.json").write_text(json.dumps({"fit_atlas": [32, 16]}))
    geometry = fit_geometry(tmp_path / "capture", tmp_path / "fit_geometry")
    bake = TexelBake.load(geometry / "bake.npz")
    # the fit's atlas at the size asked, on the truth's mesh (copied beside it), most of the UV square on the surface
    assert (bake.width, bake.height) == (32, 16) and (geometry / "mesh.obj").is_file()
    assert bake.covered.mean() > 0.8
    (gt / "flash.json").write_text(json.dumps({"fit_atlas": None}))  # the first scene: the truth's own atlas
    assert fit_geometry(tmp_path / "capture", tmp_path / "unused") == gt
