"""Texel bake: analytic plane, frames on a sphere atlas, unique deterministic ownership across
devices, padding fill, save/load, bad input."""

from __future__ import annotations

import numpy as np
import pytest

from texstream.capture.conventions import texel_center_uv
from texstream.geometry.atlas import AtlasConfig, build_atlas
from texstream.geometry.bake import TexelBake, bake_texels, claim_texels, padding_sources
from texstream.render.mesh import SurfaceMesh
from texstream.core.errors import InputError

from test_geometry_atlas import icosphere


def uv_plane(n: int = 5, sx: float = 2.0, sy: float = 1.0) -> SurfaceMesh:
    """Plane z = 0 over [0, sx] x [0, sy], UV (x / sx, y / sy), n x n grid vertices, CCW from +z."""
    u, v = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n))
    uv = np.stack([u.ravel(), v.ravel()], 1)
    verts = np.stack([sx * uv[:, 0], sy * uv[:, 1], np.zeros(n * n)], 1)
    a = (np.arange(n - 1)[None, :] + n * np.arange(n - 1)[:, None]).ravel()
    f = np.concatenate([np.stack([a, a + 1, a + n + 1], 1), np.stack([a, a + n + 1, a + n], 1)])
    return SurfaceMesh(verts, f.astype(np.int32), uvs=uv)


def test_plane_positions_are_the_analytic_map(device):
    w, h = 40, 24
    b = bake_texels(uv_plane(), w, h, device=device)
    assert b.covered.all()  # [0,1]^2 UVs: every texel centre is on the plane
    x, y = np.meshgrid(np.arange(w), np.arange(h))
    u, v = texel_center_uv(x, y, w, h)
    # float32 positions of values in [0, 2]: 2.4e-7 ulp, a few ulps of interpolation
    np.testing.assert_allclose(b.position[..., 0], 2 * u, atol=1e-6)
    np.testing.assert_allclose(b.position[..., 1], v, atol=1e-6)
    np.testing.assert_allclose(b.position[..., 2], 0, atol=1e-7)
    # frame: normal +z, tangent = dp/du direction +x, bitangent = n x t = +y (float32 rounding)
    np.testing.assert_allclose(b.normal, np.broadcast_to([0, 0, 1], b.normal.shape), atol=1e-6)
    np.testing.assert_allclose(b.tangent, np.broadcast_to([1, 0, 0], b.normal.shape), atol=1e-6)
    np.testing.assert_allclose(b.bitangent, np.broadcast_to([0, 1, 0], b.normal.shape), atol=1e-6)
    assert b.n_covered == w * h and len(b.faces_without_texels) == 0


@pytest.fixture(scope="module")
def sphere():
    out, info = build_atlas(icosphere(2), AtlasConfig(resolution=96, padding=2))
    return out, info


def test_sphere_frames_lie_on_their_faces(device, sphere):
    mesh, info = sphere
    b = bake_texels(mesh, info.width, info.height, device=device)
    c = b.covered
    f = b.face[c]
    bary = b.bary[c].astype(np.float64)
    # barycentrics: a point of the closed triangle (float32 rounding of values <= 1)
    assert bary.min() >= 0 and bary.max() <= 1
    np.testing.assert_allclose(bary.sum(1), 1, atol=1e-6)
    p = mesh.vertices[mesh.faces[f]]  # (N, 3, 3)
    pos = b.position[c].astype(np.float64)
    # float32 rounding of unit-size values
    np.testing.assert_allclose(np.einsum("ni,nij->nj", bary, p), pos, atol=1e-6)
    n_face = mesh.face_normals()[f]
    # distance of the texel's point to its face's plane: float32 positions on a unit sphere
    assert np.abs(np.einsum("ij,ij->i", pos - p[:, 0], n_face)).max() < 1e-6
    n, t, bt = (a[c].astype(np.float64) for a in (b.normal, b.tangent, b.bitangent))
    # unit, orthogonal frames (float32 normalisation: ~1e-7 per component)
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1, atol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(t, axis=1), 1, atol=1e-5)
    assert np.abs(np.einsum("ij,ij->i", n, t)).max() < 1e-5
    np.testing.assert_allclose(np.cross(n, t), bt, atol=1e-5)
    # interpolated vertex normals of a sphere point outwards, close to the position direction
    assert np.einsum("ij,ij->i", n, pos / np.linalg.norm(pos, axis=1, keepdims=True)).min() > 0.95
    assert (b.face[~c] == -1).all() and (b.bary[~c] == 0).all()


def test_ownership_is_unique_and_the_same_on_every_device(device, sphere):
    mesh, info = sphere
    ref = claim_texels(mesh, info.width, info.height, device="cpu")
    got = bake_texels(mesh, info.width, info.height, device=device)
    np.testing.assert_array_equal(got.face, ref)  # atomic_min: deterministic lowest-id owner
    again = claim_texels(mesh, info.width, info.height, device=device)
    np.testing.assert_array_equal(again, ref)


def test_orphan_sliver_gets_a_texel(device):
    # a big triangle and a sliver whose UV triangle contains no texel centre
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 2, 0], [2.1, 2, 0], [2, 2.001, 0]], float)
    uv = np.array([[0.0, 0.0], [0.5, 0.0], [0.0, 0.5], [0.8, 0.8], [0.82, 0.8], [0.8, 0.8002]])
    mesh = SurfaceMesh(v, np.array([[0, 1, 2], [3, 4, 5]], np.int32), uvs=uv)
    plain = bake_texels(mesh, 16, 16, device=device, claim_orphans=False)
    assert plain.faces_without_texels.tolist() == [1]
    b = bake_texels(mesh, 16, 16, device=device)
    assert len(b.faces_without_texels) == 0
    k = b.face == 1
    assert k.sum() == 1
    # its point is clamped onto the sliver: inside the face's 3D bounding box (float32 slack)
    p = b.position[k][0]
    assert np.all(p >= v[3:].min(0) - 1e-6) and np.all(p <= v[3:].max(0) + 1e-6)


def test_padding_sources_and_fill(sphere):
    mesh, info = sphere
    b = bake_texels(mesh, info.width, info.height, padding=2)
    src = b.fill_source
    h, w = src.shape
    idx = np.arange(h * w).reshape(h, w)
    np.testing.assert_array_equal(src[b.covered], idx[b.covered])  # covered: itself
    pad = (~b.covered) & (src >= 0)
    assert pad.any()
    sy, sx = np.divmod(src[pad], w)
    assert b.covered.reshape(-1)[src[pad]].all()  # padding copies a covered texel
    yy, xx = np.nonzero(pad)
    assert np.maximum(np.abs(sy - yy), np.abs(sx - xx)).max() <= 2  # within `padding` (chessboard)
    # texels beyond the padding: no covered texel within 2 (chessboard) -> -1
    far = src < 0
    cov = np.pad(b.covered, 2)
    near = np.zeros_like(b.covered)
    for dy in range(5):
        for dx in range(5):
            near |= cov[dy:dy + h, dx:dx + w]
    np.testing.assert_array_equal(far, ~near)
    vals = np.random.default_rng(0).normal(size=(h, w, 4)).astype(np.float32)
    filled = b.fill_padding(vals)
    assert filled.shape == vals.shape
    np.testing.assert_array_equal(filled.reshape(-1, 4)[idx[pad]], vals.reshape(-1, 4)[src[pad]])
    np.testing.assert_array_equal(filled[b.covered | far], vals[b.covered | far])
    np.testing.assert_array_equal(b.fill_padding(vals.reshape(h * w, 4)), filled.reshape(h * w, 4))


def test_padding_sources_small_case():
    cov = np.zeros((5, 5), bool)
    cov[2, 2] = True
    src = padding_sources(cov, 1)
    assert (src[1:4, 1:4] == 12).all() and (src[0] == -1).all() and (src[:, 4] == -1).all()


def test_save_load_round_trip(tmp_path, sphere):
    mesh, info = sphere
    b = bake_texels(mesh, info.width, info.height)
    b.save(tmp_path / "bake.npz")
    r = TexelBake.load(tmp_path / "bake.npz")
    assert (r.width, r.height, r.padding) == (b.width, b.height, b.padding)
    for k in TexelBake._ARRAYS:
        np.testing.assert_array_equal(getattr(r, k), getattr(b, k))
    assert [p.name for p in tmp_path.iterdir()] == ["bake.npz"]  # no temporary left behind
    img = r.normal_preview()
    assert img.shape == (b.height, b.width, 3) and img.min() >= 0 and img.max() <= 1


def test_bad_bake_input(tmp_path):
    m = uv_plane()
    with pytest.raises(InputError, match="no texture coordinates"):
        bake_texels(SurfaceMesh(m.vertices, m.faces), 8, 8)
    with pytest.raises(InputError, match="not found"):
        TexelBake.load(tmp_path / "missing.npz")
    (tmp_path / "junk.npz").write_bytes(b"junk")
    with pytest.raises(InputError, match="junk.npz"):
        TexelBake.load(tmp_path / "junk.npz")
