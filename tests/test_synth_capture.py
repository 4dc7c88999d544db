"""Synthetic capture sets: scenes, scaling, cameras and lights, photo effects, the written folder."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from conftest import need_data

from texstream.capture.synthetic import synth
from texstream.capture.capture_json import read_capture
from texstream.capture.conventions import project
from texstream.capture.synthetic.synth import SynthConfig, render_scene, synthesize
from texstream.core.errors import ConfigError, InputError

TINY = dict(scale=0.02, progress=False, preview=False)


def test_builtin_scenes_load():
    assert {"sphere", "flat_sample", "bunny", "ornament"} <= set(synth.builtin_scenes())
    for name in synth.builtin_scenes():
        sc = synth.load_scene(name)
        assert sc["name"] == name


def test_full_ornament_matches_the_seed_sizes():
    sc = synth.resolve_scene("ornament", SynthConfig())
    assert sc["cameras"]["count"] == 1760
    assert sc["cameras"]["width"] == sc["cameras"]["height"] == 430
    mesh, (w, h), _ = synth.build_mesh(sc)
    assert 3600 <= mesh.n_faces <= 3800
    from texstream.geometry.bake import bake_texels

    bake = bake_texels(mesh, w, h)
    assert 90_000 <= bake.n_covered <= 100_000  # seed: ~96,000 texels


def test_scale_shrinks_photos_images_and_texels():
    full = synth.resolve_scene("sphere", SynthConfig())
    small = synth.resolve_scene("sphere", SynthConfig(scale=0.25))
    assert small["cameras"]["count"] == round(full["cameras"]["count"] * 0.25)
    assert small["cameras"]["width"] == round(full["cameras"]["width"] * 0.5)
    assert synth._scaled_texture(full, 0.25)["width"] == round(full["texture"]["width"] * 0.5)
    with pytest.raises(ConfigError):
        synth.resolve_scene("sphere", SynthConfig(scale=0.0))


@pytest.mark.parametrize("layout", ["fibonacci", "ring"])
def test_cameras_look_at_the_target(layout):
    cams = {"layout": layout, "count": 10, "distance": 3.0, "target": [0.1, 0.2, 0.3], "rings": [10.0, 40.0],
            "min_elevation_deg": -20, "max_elevation_deg": 60}
    poses = synth.camera_poses(cams, 10)
    assert len(poses) == 10
    for r, t in poses:
        uv, z = project(np.array([[0.1, 0.2, 0.3]]), r, t, 100.0, 100.0, 50.0, 40.0)
        np.testing.assert_allclose(uv[0], [50.0, 40.0], atol=1e-9)  # pure float64 geometry
        assert z[0] == pytest.approx(3.0)


def test_light_modes():
    r, t = synth.camera_poses({"count": 1, "distance": 4.0}, 1)[0]
    center = -r.T @ t
    cam = synth.frame_light({"type": "point", "mode": "camera", "offset": [1.0, 0.0, 0.0], "intensity": 2.0},
                            r, t, 0, 10, np.zeros(3))
    # offset along the camera's x axis (row 0 of R), one unit from the camera centre
    np.testing.assert_allclose(cam.position, center + r[0], atol=1e-12)
    np.testing.assert_allclose(cam.intensity, [2.0, 2.0, 2.0])
    spun = synth.frame_light({"type": "point", "mode": "camera", "offset": [1.0, 0.0, 0.0], "spin_turns": 1.0},
                             r, t, 1, 4, np.zeros(3))
    np.testing.assert_allclose(spun.position, center + r[1], atol=1e-12)  # a quarter turn: x -> y
    orb = synth.frame_light({"type": "point", "mode": "orbit", "radius": 2.0, "height": 1.0, "turns": 1.0},
                            r, t, 2, 4, np.zeros(3))
    np.testing.assert_allclose(orb.position, [-2.0, 0.0, 1.0], atol=1e-12)
    d = synth.frame_light({"type": "directional", "mode": "camera", "direction": [0, 0, 1]}, r, t, 0, 1, np.zeros(3))
    np.testing.assert_allclose(d.direction, r[2], atol=1e-12)  # travels along the optical axis


def test_develop_noise_clipping_and_quantisation():
    rad = np.full((64, 64, 3), 0.25, dtype=np.float32)
    rng = np.random.default_rng(0)
    out = synth.develop(rad, 2.0, {"noise_sigma": 0.05, "bits": 32, "saturation": None}, rng)
    # 12288 samples: the sample mean is within 4 sigma / sqrt(n) ~ 2e-3 of 0.5, the std within 3%
    assert abs(out.mean() - 0.5) < 2e-3 and abs(out.std() - 0.05) < 0.05 * 0.03
    clip = synth.develop(rad, 8.0, {"noise_sigma": 0.0, "bits": 32, "saturation": 1.5}, rng)
    assert np.all(clip == 1.5)
    q16 = synth.develop(rad * 1.0001, 1.0, {"noise_sigma": 0.0, "bits": 16}, rng)
    np.testing.assert_array_equal(q16 * 65535, np.round(q16 * 65535))
    q8 = synth.develop(np.linspace(0, 1.2, 300, dtype=np.float32).reshape(10, 10, 3), 1.0, {"noise_sigma": 0.0, "bits": 8}, rng)
    from texstream.capture.imageio import linear_to_srgb

    codes = linear_to_srgb(q8.astype(np.float64)) * 255
    np.testing.assert_allclose(codes, np.round(codes), atol=1e-6)  # exactly 8-bit sRGB codes
    assert q8.max() == 1.0


def test_render_scene_in_memory(device):
    cfg = SynthConfig(device=device, save_clean=True, **TINY)
    res = render_scene("ornament", cfg)
    mesh, bake, params, frames, images = res
    assert len(frames) == len(images) == len(res.clean) == round(1760 * 0.02)
    assert params.shape == (bake.height, bake.width, res.layout.n_params) and np.all(np.isfinite(params))
    # three materials, each on some texels; gold has a lobe, white none
    assert set(np.unique(res.material_id[bake.covered])) == {0, 1, 2}
    white = res.material_names.index("white")
    assert np.all(params[res.material_id == white][:, 3:6] == 0.0)
    assert all(m.any() for m in res.masks)
    # noise-free float photos equal the clean renders
    np.testing.assert_array_equal(images[0], res.clean[0])


def test_synth_command_writes_a_readable_capture(tmp_path):
    from texstream.capture.imageio import read_image, read_mask
    from texstream.pipelines.cli import main

    out = tmp_path / "sphere"
    rc = main(["synth", "sphere", "-o", str(out), "--scale", "0.05", "--bits", "8", "--noise", "0.01",
               "--no-progress", "--save-clean", "--exposure", "0.8"])
    assert rc == 0
    cap = read_capture(out)
    n = round(120 * 0.05)
    assert len(cap.frames) == n and cap.has_lights
    f0 = cap.frames[0]
    assert f0.exposure == pytest.approx(0.8) and f0.saturation == 1.0
    img = read_image(cap.image_path(f0))
    mask = read_mask(cap.mask_path(f0))
    assert img.shape[:2] == mask.shape == (f0.intrinsics.height, f0.intrinsics.width)
    # the in-memory API gives exactly what was written (same seed, 8-bit codes decode exactly)
    mem = render_scene("sphere", SynthConfig(scale=0.05, bits=8, noise=0.01, exposure=0.8, progress=False))
    np.testing.assert_array_equal(img, mem.images[0])
    np.testing.assert_array_equal(mask > 0, mem.masks[0])
    # ground truth reads back
    gmesh, params, layout, bake, man = synth.load_ground_truth(out)
    np.testing.assert_array_equal(params, mem.params)
    assert gmesh.n_faces == mem.mesh.n_faces and gmesh.uvs is not None
    assert man["counts"]["photos"] == n and layout.n_lobes == 1
    assert len(list((out / "ground_truth" / "clean").glob("*.exr"))) == n
    assert json.loads((out / "synth_config.json").read_text())["noise"] == 0.01
    assert (out / "previews" / "rho_d.png").is_file()


def test_bad_scene_errors_and_no_half_written_output(tmp_path, monkeypatch):
    bad = tmp_path / "bad.json"
    sc = synth.load_scene("sphere")
    sc["assignment"] = {"rule": "uniform", "material": "nope"}
    bad.write_text(json.dumps(sc))
    with pytest.raises(ConfigError, match="nope"):
        synth.load_scene(bad)
    with pytest.raises(InputError):
        synth.load_scene(tmp_path / "missing.json")
    out = tmp_path / "out"

    def boom(*a, **k):
        raise InputError("simulated failure mid-render")

    monkeypatch.setattr(synth, "develop", boom)
    with pytest.raises(InputError):
        synthesize("sphere", out, SynthConfig(**TINY))
    assert not out.exists()
    assert not [p for p in Path(tmp_path).iterdir() if p.name.startswith(".out")]


def test_bunny_scene(data_dir, tmp_path, capsys):
    """`texstream synth bunny --scale 0.02` (once: 'could not pack the 36 charts into 36x36 texels')."""
    from texstream.capture.imageio import read_mask
    from texstream.pipelines.cli import main

    need_data(data_dir, "stanford_bunny")
    out = tmp_path / "bunny"
    rc = main(["synth", "bunny", "-o", str(out), "--scale", "0.02", "--photos", "2", "--image-size", "48",
               "--no-progress", "--no-preview"])
    assert rc == 0, capsys.readouterr().err
    mesh, params, layout, bake, man = synth.load_ground_truth(out)
    # 256 x sqrt(0.02) = 36 texels is raised to the 64-texel floor; xatlas packs into at most that
    assert 0.9 * synth.MIN_ATLAS_RESOLUTION <= max(bake.width, bake.height) <= synth.MIN_ATLAS_RESOLUTION
    assert mesh.n_faces <= 5200 and bake.n_covered > 1000
    assert len(read_capture(out).frames) == 2
    masks = [read_mask(p) for p in sorted((out / "masks").iterdir())]
    assert len(masks) == 2 and all(m.any() for m in masks)  # the bunny is in view in both photos


def test_scaled_atlas_resolution_floor_and_pack_failure_message(monkeypatch):
    atlas_scene = {"texture": {"resolution": 256, "padding": 2}}
    assert synth._scaled_texture(atlas_scene, 0.02)["resolution"] == synth.MIN_ATLAS_RESOLUTION  # not 36
    assert synth._scaled_texture(atlas_scene, 0.25)["resolution"] == 128  # above the floor: x sqrt(s)
    assert synth._scaled_texture({"texture": {"resolution": 32}}, 0.02)["resolution"] == 32  # never raised
    assert synth._scaled_texture({"texture": {"width": 128, "height": 64}}, 0.02)["width"] == 18  # UV meshes: x sqrt(s)
    # a pack failure names an option synth has (the atlas' own message says --resolution)
    from texstream.geometry import atlas

    def no_room(mesh, cfg, *a, **k):
        raise ConfigError(f"could not pack the 9 charts into {cfg.resolution}x{cfg.resolution} texels",
                          fix="raise --resolution")

    monkeypatch.setattr(atlas, "build_atlas", no_room)
    sc = synth.load_scene("sphere")
    sc["texture"] = {"resolution": 256, "padding": 2}
    with pytest.raises(ConfigError) as e:
        synth.build_mesh(sc, 0.02)
    line = e.value.one_line()
    assert "64x64" in line and "--scale" in line and "--resolution" not in line and "\n" not in line


def test_azimuth_offset_gives_distinct_held_out_views():
    a = synth.resolve_scene("sphere", SynthConfig(scale=0.05))
    b = synth.resolve_scene("sphere", SynthConfig(scale=0.05, azimuth_offset=7.0))
    pa = synth.camera_poses(a["cameras"], 4)
    pb = synth.camera_poses(b["cameras"], 4)
    ca, cb = (np.array([-r.T @ t for r, t in p]) for p in (pa, pb))
    # same elevations and distances, azimuths turned by 7 degrees
    np.testing.assert_allclose(ca[:, 2], cb[:, 2], atol=1e-12)
    ang = np.degrees(np.arctan2(cb[:, 1], cb[:, 0]) - np.arctan2(ca[:, 1], ca[:, 0]))
    np.testing.assert_allclose((ang + 180) % 360 - 180, 7.0, atol=1e-9)
