"""Synthetic captures under an environment light (capture/synthetic/environments.py, env_capture.py).

Ground truth is closed form: a constant environment gives albedo x radiance on a convex surface, an SH
band-limited one render/sh.py's diffuse radiance, a wall beside a floor the form factor of an infinite strip.
The tolerances are the quadrature error of the lat-long integration grid (documented per test)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import SCENE_DEVICE
from texstream.capture.capture_json import read_capture
from texstream.capture.imageio import read_image
from texstream.capture.synthetic import env_capture, environments, procedural
from texstream.capture.synthetic.synth import SynthConfig, render_scene, synthesize
from texstream.core.errors import ConfigError, InputError
from texstream.geometry.bake import bake_texels
from texstream.render import sh
from texstream.render.mesh import SurfaceMesh

TINY = {"scale": 0.02, "progress": False, "preview": False, "device": SCENE_DEVICE}


@pytest.fixture(scope="module")
def sphere():
    mesh = procedural.make("uv_sphere", radius=1.0, n_segments=32, n_rings=16)
    return mesh, bake_texels(mesh, 32, 16, device=SCENE_DEVICE, padding=1)


def test_builtin_environments_are_deterministic_finite_and_distinct():
    maps = {n: environments.make_environment(n, 16) for n in environments.environment_names()}
    assert len(maps) >= 3
    for name, env in maps.items():
        assert env.shape == (16, 32, 3) and env.dtype == np.float32
        assert np.all(np.isfinite(env)) and env.min() > 0, name  # radiance, every direction lit a little
        np.testing.assert_array_equal(env, environments.make_environment(name, 16))  # closed forms: same bits
    coeffs = [sh.project_latlong(e) for e in maps.values()]
    for i in range(len(coeffs)):
        for j in range(i):
            assert np.abs(coeffs[i] - coeffs[j]).max() > 0.1  # distinct lightings, not one map recoloured


def test_downsampling_keeps_the_integral_and_sh_truncation_is_a_few_percent():
    env = environments.make_environment("sky", 64)
    coarse = environments.downsample_latlong(env, 16, 32)
    total = [(e * sh.latlong_directions(*e.shape[:2])[1][..., None]).sum((0, 1)) for e in (env, coarse)]
    np.testing.assert_allclose(total[1], total[0], rtol=1e-6)  # solid-angle-weighted: exact up to float32 storage
    err = environments.irradiance_sh_error(env, normal_rows=16)
    assert 0 < err["rms_relative"] < 0.06  # measured 2.8%: the sun is soft on purpose (module doc)
    with pytest.raises(ConfigError, match="multiples"):
        environments.downsample_latlong(env, 24, 48)


def test_environment_file_round_trip_and_bad_files(tmp_path):
    env = environments.make_environment("studio", 16)
    environments.write_environment(tmp_path / "studio.exr", env)
    back, name = environments.load_environment(str(tmp_path / "studio.exr"))
    np.testing.assert_array_equal(back, env)  # float32 EXR: lossless
    assert name == "studio"
    environments.write_environment(tmp_path / "square.exr", env[:, :16])
    with pytest.raises(InputError, match="2:1"):
        environments.read_environment(tmp_path / "square.exr")
    with pytest.raises(ConfigError, match="unknown environment"):
        environments.make_environment("moon")


def test_convex_sphere_under_a_constant_environment_gives_albedo_times_radiance(sphere, device):
    """Irradiance pi c on every texel: no self-occlusion on a convex surface. 1%: the midpoint quadrature of the
    clamped cosine's kink on a 16 x 32 grid (measured 0.3%) and the facets' own horizon (directions above the
    shading normal's horizon but below the facet's are blocked)."""
    mesh, bake = sphere
    irr, transfer = env_capture.texel_environment(mesh, bake, np.full((16, 32, 3), 0.7, np.float32), device)
    np.testing.assert_allclose(irr[bake.covered], math.pi * 0.7, rtol=1e-2)
    assert not irr[~bake.covered].any() and not transfer[~bake.covered].any()


def test_sphere_under_a_band_limited_environment_matches_sh_diffuse_radiance(sphere, device):
    """An SH-9 light integrated over the grid equals render/sh.py's closed form albedo * T(n) . L with the
    unoccluded transfer; and the kernel's occluded transfer equals that T(n) (convex: nothing occludes).
    Tolerances: the grid's quadrature (measured 0.4% of the mean and 2e-3 absolute on the transfer)."""
    mesh, bake = sphere
    rng = np.random.default_rng(1)
    coeffs = rng.normal(scale=0.15, size=(9, 3))
    coeffs[0] = 1.0  # a positive light everywhere (min radiance 0.06)
    irr, transfer = env_capture.texel_environment(mesh, bake, sh.latlong_from_sh(coeffs, 16, 32), device)
    n = bake.normal[bake.covered].astype(np.float64)
    albedo = np.array([0.8, 0.5, 0.2])
    expected = sh.diffuse_radiance(np.broadcast_to(albedo, n.shape), sh.unoccluded_transfer(n), coeffs)
    got = albedo / math.pi * irr[bake.covered]  # rho_d * irradiance
    assert np.abs(got - expected).max() < 1e-2 * expected.mean()
    np.testing.assert_allclose(transfer[bake.covered], sh.unoccluded_transfer(n), atol=5e-3)


def _floor_and_wall(height: float = 2.0, half_length: float = 10.0) -> SurfaceMesh:
    """A floor (z = 0, x in [0, 2]) and a wall (x = 0, z in [0, height]) meeting in a long corner; unwelded, so
    each keeps its flat normal."""
    y = half_length
    v = np.array([[0, -y, 0], [2, -y, 0], [2, y, 0], [0, y, 0],
                  [0, -y, 0], [0, y, 0], [0, y, height], [0, -y, height]], float)
    uv = np.array([[0, 0], [0.5, 0], [0.5, 1], [0, 1], [0.5, 0], [0.5, 1], [1, 1], [1, 0]], float)
    return SurfaceMesh(vertices=v, faces=np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]]), uvs=uv).with_normals()


def test_occlusion_darkens_a_concavity_by_the_walls_form_factor(device):
    """Floor texels at distance a from a wall of height h lose the form factor F = (1 - a / sqrt(a^2 + h^2)) / 2
    of an infinitely long strip (half the sky at the corner). Checked where the 20-long wall is long compared
    to the distances (|y| < 5); 0.02: the wall's edge cuts the 32 x 64 grid's 5.6-degree pixels (measured 0.009)."""
    mesh = _floor_and_wall()
    bake = bake_texels(mesh, 32, 32, device=SCENE_DEVICE, padding=1)
    irr, _ = env_capture.texel_environment(mesh, bake, np.ones((32, 64, 3), np.float32), device)
    floor = bake.covered & (bake.normal[..., 2] > 0.5) & (np.abs(bake.position[..., 1]) < 5)
    a = bake.position[floor][:, 0].astype(np.float64)
    form_factor = 0.5 * (1 - a / np.sqrt(a * a + 4.0))
    np.testing.assert_allclose(irr[floor][:, 0] / math.pi, 1 - form_factor, atol=0.02)
    assert irr[floor][:, 0].min() < 0.55 * math.pi < 0.8 * math.pi < irr[floor][:, 0].max()  # corner: half the sky


def test_synth_env_writes_an_unlit_capture_with_its_ground_truth(tmp_path):
    """End to end on the sphere scene under a constant environment file: no lights in capture.json, the
    ground truth's radiance is albedo x c (1%: as the convex test) and the photos show it."""
    c = 0.6
    environments.write_environment(tmp_path / "grey.exr", np.full((64, 128, 3), c, np.float32))
    out = tmp_path / "sphere_grey"
    synthesize("sphere", out, SynthConfig(env=str(tmp_path / "grey.exr"), env_grid=16, **TINY))
    cap = read_capture(out)
    assert cap.frames and all(f.light is None for f in cap.frames)
    gt = env_capture.load_env_ground_truth(out)
    assert gt["manifest"]["name"] == "grey" and gt["manifest"]["integration_grid"] == [16, 32]
    covered = np.load(out / "ground_truth" / "bake.npz")["covered"]
    np.testing.assert_allclose(gt["radiance"][covered], gt["albedo"][covered] * c, rtol=1e-2)
    np.testing.assert_allclose(gt["coeffs"][0], c * math.sqrt(4 * math.pi), rtol=1e-5)  # only Y_00
    assert np.abs(gt["coeffs"][1:]).max() < 2e-3  # the theta midpoint rule's error on Y_20 at 64 rows (5e-4)
    photo = read_image(cap.image_path(cap.frames[0]), channels=3)
    lit = photo[photo.sum(-1) > 0]
    lo, hi = gt["albedo"][covered].min(0) * c, gt["albedo"][covered].max(0) * c
    assert np.all(lit >= lo * 0.98) and np.all(lit <= hi * 1.02)  # bilinear blends of the texels' radiance


def test_every_environment_sees_the_same_cameras():
    """Captures under other environments are the relighting references: same frames, other light."""
    a = render_scene("sphere", SynthConfig(env="sky", env_grid=8, **TINY))
    b = render_scene("sphere", SynthConfig(env="studio", env_grid=8, **TINY))
    assert len(a.frames) == len(b.frames) > 0
    for fa, fb in zip(a.frames, b.frames):
        np.testing.assert_array_equal(fa.R, fb.R)
        assert fa.light is None and fb.light is None
    assert a.layout.kind == "diffuse" and a.params.shape[-1] == 3
    assert a.environment.name == "sky" and b.environment.coeffs.shape == (9, 3)
    assert np.abs(a.images[0] - b.images[0]).max() > 0.05
    with pytest.raises(ConfigError, match="room light"):
        render_scene("sphere_room", SynthConfig(env="sky", env_grid=8, **TINY))
