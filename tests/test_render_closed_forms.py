"""The Warp renderer against closed forms: Lambert, point-light falloff, cast shadows, a Lafortune
lobe and the texel-grid lookup convention. Every expected value is recomputed in float64 from the
pixel's ray, so the tolerances only have to absorb the renderer's float32 arithmetic."""

from __future__ import annotations

import numpy as np
import pytest

from texstream.capture.synthetic import procedural
from texstream.capture.capture_json import Light
from texstream.capture.conventions import look_at_w2c, uv_to_texel
from texstream.render.layout import ModelLayout
from texstream.render.renderer import Renderer
from texstream.render.mesh import SurfaceMesh

# float32 renderer vs float64 reference: positions, normals and cosines carry ~1e-7 relative
# round-off; 1e-4 relative (the bar) leaves two orders of magnitude of margin.
RTOL32 = 1e-4

LAMBERT = ModelLayout("diffuse", 0)
LAF = ModelLayout("lafortune", 1)


def _const_grid(layout: ModelLayout, row: np.ndarray, h: int = 4, w: int = 4) -> np.ndarray:
    return np.broadcast_to(np.asarray(row, dtype=np.float64), (h, w, layout.n_params)).copy()


def _pixel_rays(r, t, fx, fy, cx, cy, w, h):
    """float64 ray origin (3,) and unit directions (H, W, 3) through the pixel centres."""
    jj, ii = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    d_cam = np.stack([(ii + 0.5 - cx) / fx, (jj + 0.5 - cy) / fy, np.ones_like(ii, dtype=np.float64)], -1)
    d = d_cam @ r  # R^T d_cam for row vectors
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    return -r.T @ t, d


def _hit_plane_z0(origin, d):
    s = -origin[2] / d[..., 2]
    return origin + s[..., None] * d


def test_lambertian_sphere_directional(device):
    # Finely tessellated sphere, constant albedo. The reference cosine uses the *interpolated shading
    # normal* at the hit (recomputed in float64 from the face id and the pixel ray): that is what the
    # renderer defines, so the 1e-4 bar tests the renderer's arithmetic, not the tessellation.
    # A second, looser check against the analytic sphere normal shows it is a sphere.
    mesh = procedural.uv_sphere(1.0, n_segments=96, n_rings=48)
    rho, e = 0.7 / np.pi, np.array([2.0, 1.5, 1.0])
    rend = Renderer(mesh, _const_grid(LAMBERT, [rho, rho, rho]), LAMBERT, device)
    light_dir = np.array([-0.4, 0.3, -1.0])
    light = Light.directional(light_dir, e)
    r, t = look_at_w2c([0.5, -3.5, 1.2], [0, 0, 0])
    w = h = 48
    fx = fy = 60.0
    res = rend.render(r, t, fx, fy, w / 2, h / 2, w, h, light)
    origin, d = _pixel_rays(r, t, fx, fy, w / 2, h / 2, w, h)
    m = res.mask
    assert 0.2 < m.mean() < 0.9

    f = mesh.faces[res.face[m]]
    p0, p1, p2 = (mesh.vertices[f[:, k]] for k in range(3))
    dd = d[m]
    # ray / triangle plane intersection and barycentrics in float64
    ng = np.cross(p1 - p0, p2 - p0)
    s = np.einsum("ij,ij->i", p0 - origin, ng) / np.einsum("ij,ij->i", dd, ng)
    x = origin + s[:, None] * dd
    area = np.einsum("ij,ij->i", ng, ng)
    b0 = np.einsum("ij,ij->i", np.cross(p1 - x, p2 - x), ng) / area
    b1 = np.einsum("ij,ij->i", np.cross(p2 - x, p0 - x), ng) / area
    b2 = 1 - b0 - b1
    n = b0[:, None] * mesh.normals[f[:, 0]] + b1[:, None] * mesh.normals[f[:, 1]] + b2[:, None] * mesh.normals[f[:, 2]]
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    l = -light_dir / np.linalg.norm(light_dir)
    cos = n @ l
    # depth is camera z of the hit
    np.testing.assert_allclose(res.depth[m], (x @ r.T + t)[:, 2], rtol=RTOL32)
    lit = cos > 0.2  # away from the terminator, where the shadow ray may graze neighbouring faces
    expected = rho * cos[lit, None] * e[None]
    got = res.radiance[m][lit]
    assert lit.sum() > 200
    np.testing.assert_allclose(got, expected, rtol=RTOL32)
    # analytic normal at the hit: the 96x48 tessellation bends normals by ~(2 pi / 96)^2 / 8 rad,
    # up to ~3e-3 relative in cos(theta) at cos > 0.2
    cos_true = (x / np.linalg.norm(x, axis=1, keepdims=True)) @ l
    np.testing.assert_allclose(got[:, 0], rho * e[0] * cos_true[lit], rtol=5e-3)
    # back-facing light gives exact zeros
    assert np.all(res.radiance[m][cos <= 0.0] == 0.0)
    assert np.all(res.radiance[~m] == 0.0) and np.all(res.face[~m] == -1) and np.all(res.depth[~m] == 0.0)


def test_point_light_falloff_on_plane(device):
    # plane z = 0 (exact +z normals), point light: L = rho * I * cos / r^2
    mesh = procedural.flat_sample(size=4.0, n=4)
    rho = np.array([0.3, 0.2, 0.1])
    inten = np.array([5.0, 6.0, 7.0])
    lpos = np.array([0.3, -0.2, 1.5])
    rend = Renderer(mesh, _const_grid(LAMBERT, rho), LAMBERT, device)
    r, t = look_at_w2c([0.0, -2.0, 3.0], [0, 0, 0])
    w, h, fx = 40, 32, 30.0
    res = rend.render(r, t, fx, fx, w / 2, h / 2, w, h, Light.point(lpos, inten))
    origin, d = _pixel_rays(r, t, fx, fx, w / 2, h / 2, w, h)
    x = _hit_plane_z0(origin, d)
    m = res.mask
    assert m.mean() > 0.5
    dl = lpos - x[m]
    r2 = np.einsum("ij,ij->i", dl, dl)
    cos = dl[:, 2] / np.sqrt(r2)
    expected = rho[None] * inten[None] * (cos / r2)[:, None]
    np.testing.assert_allclose(res.radiance[m], expected, rtol=RTOL32)


def _merge(*meshes: SurfaceMesh) -> SurfaceMesh:
    off = np.cumsum([0] + [m.n_vertices for m in meshes[:-1]])
    return SurfaceMesh(vertices=np.concatenate([m.vertices for m in meshes]),
                       faces=np.concatenate([m.faces + o for m, o in zip(meshes, off)]).astype(np.int32),
                       normals=np.concatenate([m.normals for m in meshes]),
                       uvs=np.concatenate([m.uvs for m in meshes]))


def test_cast_shadow(device):
    # ground plane z = 0 and a square occluder of half-size a at height hh under a slanted directional
    # light: the shadow is the occluder's footprint shifted by hh * (dx / -dz) along x
    plane = procedural.flat_sample(size=4.0, n=8)
    a, hh = 0.3, 0.5
    occ = procedural.flat_sample(size=2 * a, n=2)
    occ.vertices = occ.vertices + [0.0, 0.0, hh]
    mesh = _merge(plane, occ)
    rho, e = 0.25, np.array([1.0, 1.0, 1.0])
    rend = Renderer(mesh, _const_grid(LAMBERT, [rho] * 3), LAMBERT, device)
    ldir = np.array([0.6, 0.0, -1.0])
    r, t = look_at_w2c([-0.5, -2.5, 3.5], [0.3, 0.0, 0.0])
    w = h = 64
    fx = 60.0
    res = rend.render(r, t, fx, fx, w / 2, h / 2, w, h, Light.directional(ldir, e))
    origin, d = _pixel_rays(r, t, fx, fx, w / 2, h / 2, w, h)
    x = _hit_plane_z0(origin, d)
    on_plane = res.mask & (res.face >= 0) & (res.face < plane.n_faces)
    shift = hh * ldir[0] / -ldir[2]
    dx, dy = np.abs(x[..., 0] - shift), np.abs(x[..., 1])
    margin = 0.03  # keep clear of the shadow edge, where pixel centres straddle it
    inside = on_plane & (dx < a - margin) & (dy < a - margin)
    outside = on_plane & ((dx > a + margin) | (dy > a + margin))
    assert inside.sum() > 20 and outside.sum() > 200
    assert np.all(res.radiance[inside] == 0.0)
    cos = (-ldir / np.linalg.norm(ldir))[2]
    np.testing.assert_allclose(res.radiance[outside], rho * cos * np.ones((outside.sum(), 3)), rtol=RTOL32)
    # with shadows off the same pixels are lit
    flat = Renderer(mesh, _const_grid(LAMBERT, [rho] * 3), LAMBERT, device, shadows=False)
    res2 = flat.render(r, t, fx, fx, w / 2, h / 2, w, h, Light.directional(ldir, e))
    np.testing.assert_allclose(res2.radiance[inside], rho * cos, rtol=RTOL32)


def test_lafortune_lobe_peak(device):
    # flat sample, light mirrored into the camera at the origin, which sits at a pixel centre:
    # there the lobe base s = dot(mirror(u), v) = 1 and the BRDF is rho_d + rho_s * 1^n
    mesh = procedural.flat_sample(size=2.0, n=2)
    rho_d, rho_s, n_exp = np.array([0.05, 0.1, 0.15]), np.array([2.0, 1.5, 1.0]), 40.0
    row = LAF.pack(rho_d, [{"rho_s": rho_s, "c": (-1.0, 1.0), "n": n_exp}])
    rend = Renderer(mesh, _const_grid(LAF, row), LAF, device)
    cam = np.array([0.0, -1.5, 2.0])
    ldir = np.array([0.0, -1.5, -2.0]) / 2.5  # from (0, 1.5, 2): the camera's mirror image
    r, t = look_at_w2c(cam, [0, 0, 0])
    w = h = 33
    fx, cx = 40.0, 16.5  # the origin projects to the centre of pixel (16, 16)
    e = np.array([1.0, 1.0, 1.0])
    res = rend.render(r, t, fx, fx, cx, cx, w, h, Light.directional(ldir, e))
    u = -ldir
    cos_i = u[2]
    peak = res.radiance[16, 16]
    np.testing.assert_allclose(peak, (rho_d + rho_s) * cos_i, rtol=RTOL32)
    assert np.all(res.radiance[res.mask].sum(-1) <= peak.sum() * (1 + 1e-6))
    # every pixel: (rho_d + rho_s * max(s, 0)^n) * cos_i with s = -(ux vx + uy vy) + uz vz
    origin, d = _pixel_rays(r, t, fx, fx, cx, cx, w, h)
    x = _hit_plane_z0(origin, d)
    v = origin - x
    v /= np.linalg.norm(v, axis=-1, keepdims=True)
    s = -(u[0] * v[..., 0] + u[1] * v[..., 1]) + u[2] * v[..., 2]
    # lobe^n amplifies the float32 error of s by n: 40 * ~1e-7 is still far below 1e-4
    expected = (rho_d + rho_s * np.maximum(s, 0.0)[..., None] ** n_exp) * cos_i
    np.testing.assert_allclose(res.radiance[res.mask], expected[res.mask], rtol=RTOL32)


def test_texel_grid_lookup_convention(device):
    # distinct diffuse values per texel; the rendered value is the bilinear blend of the texel grid at
    # the hit's UV with row 0 at the top of the texture (v up), as capture/conventions.py says
    mesh = procedural.flat_sample(size=2.0, n=3)
    tw, th = 7, 5
    rng = np.random.default_rng(3)
    grid = rng.uniform(0.1, 0.9, size=(th, tw, 3))
    rend = Renderer(mesh, grid, LAMBERT, device)
    r, t = look_at_w2c([0.2, -0.3, 3.0], [0, 0, 0])
    w, h, fx = 37, 29, 40.0
    res = rend.render(r, t, fx, fx, w / 2, h / 2, w, h, Light.directional([0, 0, -1], [1, 1, 1]))
    origin, d = _pixel_rays(r, t, fx, fx, w / 2, h / 2, w, h)
    x = _hit_plane_z0(origin, d)[res.mask]
    uv = x[:, :2] / 2.0 + 0.5
    tx, ty = uv_to_texel(uv[:, 0], uv[:, 1], tw, th)
    tx, ty = np.clip(tx, 0, tw - 1), np.clip(ty, 0, th - 1)
    x0 = np.minimum(np.floor(tx).astype(int), tw - 2)
    y0 = np.minimum(np.floor(ty).astype(int), th - 2)
    fxx, fyy = (tx - x0)[:, None], (ty - y0)[:, None]
    expected = ((1 - fxx) * (1 - fyy) * grid[y0, x0] + fxx * (1 - fyy) * grid[y0, x0 + 1]
                + (1 - fxx) * fyy * grid[y0 + 1, x0] + fxx * fyy * grid[y0 + 1, x0 + 1])
    # texel coordinates are uv * size in float32: ~1e-6 absolute, times the grid's slope (< 1)
    np.testing.assert_allclose(res.radiance[res.mask], expected, rtol=RTOL32, atol=2e-6)


def test_bad_inputs():
    mesh = procedural.flat_sample(size=1.0, n=1)
    from texstream.core.errors import ConfigError, InputError
    with pytest.raises(ConfigError):
        Renderer(mesh, np.zeros((4, 4, 5)), LAMBERT)
    with pytest.raises(InputError):
        Renderer(SurfaceMesh(mesh.vertices, mesh.faces), np.zeros((4, 4, 3)), LAMBERT)
    bad = np.zeros((4, 4, 3))
    bad[0, 0, 0] = np.nan
    with pytest.raises(InputError):
        Renderer(mesh, bad, LAMBERT)


def test_anisotropic_layout_and_device_params(device):
    # the general lobe with c_x = c_y = -1 is the isotropic lobe; a Warp array already on the device
    # gives the same image as the numpy grid; render_frame renders a capture Frame's view
    import warp as wp

    from texstream.capture.capture_json import Frame, Intrinsics

    mesh = procedural.uv_sphere(1.0, n_segments=32, n_rings=16)
    aniso = ModelLayout("lafortune", 1, anisotropic=True)
    rho_d, lobe = [0.1, 0.2, 0.3], {"rho_s": [1.0, 0.8, 0.6], "n": 25.0}
    iso_grid = _const_grid(LAF, LAF.pack(rho_d, [{**lobe, "c": (-1.0, 0.9)}]))
    an_grid = _const_grid(aniso, aniso.pack(rho_d, [{**lobe, "c": (-1.0, -1.0, 0.9)}]))
    r, t = look_at_w2c([0.0, -3.0, 1.0], [0, 0, 0])
    light = Light.point([1.0, -3.0, 2.0], [9.0, 9.0, 9.0])
    frame = Frame("x.exr", r, t, Intrinsics(32, 32, 40.0, 40.0, 16.0, 16.0), light=light)
    a = Renderer(mesh, iso_grid, LAF, device).render_frame(frame)
    b = Renderer(mesh, an_grid, aniso, device).render_frame(frame)
    # identical arithmetic except c_x, c_y read as separate columns: float32 equality up to rounding
    np.testing.assert_allclose(b.radiance, a.radiance, rtol=1e-6, atol=1e-7)
    dev_params = wp.array(iso_grid.reshape(-1, LAF.n_params).astype(np.float32), dtype=wp.float32, device=device)
    c = Renderer(mesh, dev_params, LAF, device, tex_size=(4, 4)).render_frame(frame)
    np.testing.assert_array_equal(c.radiance, a.radiance)
    assert a.radiance.max() > 0.1
