"""Atlas seams: edge pairs, per-sample stencils, and no crack after averaging.

The crack is measured the way the renderer textures a point: a Warp kernel calls the shared
``texel_coords`` / ``bilinear_taps`` funcs at the UV of the same 3D point on both sides of a seam.
"""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from texstream.capture.synthetic.procedural import icosphere, uv_sphere
from texstream.render.shading import bilinear_taps, texel_coords
from texstream.geometry.atlas import AtlasConfig, atlas_stage, build_atlas
from texstream.geometry.bake import bake_texels
from texstream.geometry.seams import SEAMS_FILE, Seams, average_across_seams, find_seams, seam_edges, seam_gaps
from texstream.core.errors import InputError


@wp.kernel(enable_backward=False)
def _lookup(grid: wp.array2d(dtype=wp.float32), uv: wp.array(dtype=wp.vec2), width: int, height: int,
            out: wp.array(dtype=wp.float32)):
    i = wp.tid()
    x, y = texel_coords(uv[i], width, height)
    x0, y0, fx, fy = bilinear_taps(x, y, width, height)
    out[i] = (1.0 - fy) * ((1.0 - fx) * grid[y0, x0] + fx * grid[y0, x0 + 1]) + \
        fy * ((1.0 - fx) * grid[y0 + 1, x0] + fx * grid[y0 + 1, x0 + 1])


def render_lookup(grid2d: np.ndarray, uv: np.ndarray, device: str) -> np.ndarray:
    h, w = grid2d.shape
    out = wp.zeros(len(uv), dtype=wp.float32, device=device)
    wp.launch(_lookup, dim=len(uv), inputs=[wp.array(np.ascontiguousarray(grid2d, np.float32), dtype=wp.float32,
                                                      device=device),
                                             wp.array(uv.astype(np.float32), dtype=wp.vec2, device=device), w, h],
              outputs=[out], device=device)
    return out.numpy()


def random_seam_points(mesh, n: int, seed: int = 1):
    """UVs on both sides and 3D positions of n random points on seam edges."""
    rng = np.random.default_rng(seed)
    _, va, vb = seam_edges(mesh)
    e = rng.integers(0, len(va), n)
    t = rng.random(n)[:, None]

    def lerp(arr, v):
        return (1 - t) * arr[v[e, 0]] + t * arr[v[e, 1]]

    return lerp(mesh.uvs, va), lerp(mesh.uvs, vb), lerp(mesh.vertices, va), lerp(mesh.vertices, vb)


@pytest.fixture(scope="module")
def atlased():
    mesh, info = build_atlas(icosphere(1.0, 3), AtlasConfig(resolution=128, padding=2))
    bake = bake_texels(mesh, info.width, info.height, padding=2)
    return mesh, bake, find_seams(mesh, info.width, info.height, bake.fill_source)


def test_seam_edges_are_the_split_edges(atlased):
    mesh, _, seams = atlased
    faces, va, vb = seam_edges(mesh)
    assert len(faces) > 0 and seams.n_edges == len(faces)
    # the two copies of a seam edge: same welded vertices, same 3D points, different UVs
    np.testing.assert_array_equal(mesh.source_vertex[va], mesh.source_vertex[vb])
    np.testing.assert_array_equal(mesh.vertices[va], mesh.vertices[vb])
    assert np.all(np.any(mesh.uvs[va] != mesh.uvs[vb], axis=(1, 2)))
    # every welded edge appears at most once, and the faces differ
    key = np.sort(mesh.source_vertex[va], axis=1)
    assert len(np.unique(key, axis=0)) == len(key) and np.all(faces[:, 0] != faces[:, 1])
    # each face of a pair holds its edge's vertices
    for side, v in ((0, va), (1, vb)):
        f = mesh.faces[faces[:, side]]
        assert np.all((f == v[:, :1]).any(axis=1) & (f == v[:, 1:]).any(axis=1))
    # stencils are bilinear weights (rows sum to 1) and sample positions lie on the unit sphere's chords
    np.testing.assert_allclose(seams.w_a.sum(axis=1), 1, atol=1e-12)
    np.testing.assert_allclose(seams.w_b.sum(axis=1), 1, atol=1e-12)
    assert np.all(np.linalg.norm(seams.position, axis=1) <= 1 + 1e-12)


def test_averaging_removes_the_crack(device, atlased):
    mesh, bake, seams = atlased
    rng = np.random.default_rng(0)
    grid = bake.fill_padding(rng.random((bake.height, bake.width)).astype(np.float32))
    uva, uvb, pa, pb = random_seam_points(mesh, 4000)
    np.testing.assert_array_equal(pa, pb)  # the same 3D points
    before = np.abs(render_lookup(grid, uva, device) - render_lookup(grid, uvb, device))
    assert before.max() > 0.3  # random texels: the two sides disagree
    out = average_across_seams(grid, seams)
    assert out.shape == grid.shape and out.dtype == grid.dtype
    after = np.abs(render_lookup(out, uva, device) - render_lookup(out, uvb, device))
    # points not used as constraint samples; residual from the eps regularisation (measured 2e-4),
    # bound: a quarter of an 8-bit code value on values in [0, 1]
    assert after.max() < 1e-3, after.max()
    # only texels some seam lookup reads change (padding refill aside: the input was already filled)
    changed = np.flatnonzero((out != grid).reshape(-1))
    assert np.isin(changed, seams.texels()).all()
    assert np.abs(seam_gaps(out, seams)).max() < 1e-3


def test_smooth_map_changes_little(atlased):
    """A map that is a smooth function of position (here the position itself) needs only small
    changes: the gutter (padding texels) absorbs most of the seam mismatch."""
    _, bake, seams = atlased
    grid = bake.fill_padding(bake.position.copy())
    gap0 = np.abs(seam_gaps(grid, seams)).max()
    out = average_across_seams(grid, seams)
    assert np.abs(seam_gaps(out, seams)).max() < 1e-3  # as above
    change = np.abs(out - grid).max(axis=2)[bake.covered]
    # measured: max 1.3x the largest gap before (chart corners), 90% of the changed fitted texels
    # by less than 0.37x; bounds 2x and 0.5x
    assert change.max() < 2 * gap0 and np.percentile(change[change > 0], 90) < 0.5 * gap0


def test_averaging_extreme_values_stays_in_bounds(atlased):
    """Per-texel fits put neighbours at opposite ends of a parameter's range (a lobe exponent of 1
    beside one of 10,000, an albedo of 0 beside 10); the unbounded least-squares solution moves cheap
    gutter texels far outside the range (what gave real-photo models exponents of -5,000), so the
    bounded averaging must keep every texel inside [lower, upper] and still close most gaps."""
    _, bake, seams = atlased
    rng = np.random.default_rng(3)
    lo, hi = np.array([0.0, 1.0]), np.array([10.0, 1.0e4])
    # each covered texel at one of its channel's bounds: the most extreme disagreement across seams
    grid = np.where(rng.random((bake.height, bake.width, 2)) < 0.5, lo, hi).astype(np.float32)
    grid = bake.fill_padding(grid)
    free = average_across_seams(grid, seams)
    assert (free < lo).any() or (free > hi).any()  # the case is real: unbounded, texels leave the range
    out = average_across_seams(grid, seams, lower=lo, upper=hi)
    assert np.all(out >= lo) and np.all(out <= hi)
    gap0 = np.abs(seam_gaps(grid, seams)).max(axis=0)
    gap = np.abs(seam_gaps(out, seams))
    # bounds cost some exactness where a seam needs an out-of-range gutter to close; measured here:
    # the median seam sample closes to under 1e-3 of the range, none ends wider than it started
    assert np.all(np.median(gap, axis=0) < 1e-3 * (hi - lo)) and np.all(gap.max(axis=0) <= gap0 + 1e-6)


def test_uv_sphere_seam_pairs_texels_one_to_one(device):
    """The procedural UV sphere's seams: longitude 0 = 1 (the atlas's left and right edges, texel rows
    line up so samples tie texel pairs) and the split pole vertices (one UV per pole triangle)."""
    m = uv_sphere(1.0, n_segments=16, n_rings=8)
    w, h = 32, 18
    bake = bake_texels(m, w, h, padding=1)
    seams = find_seams(m, w, h, bake.fill_source)
    assert seams.n_edges > 0
    # a sample is on the longitude seam (u = 0 on one side, u = 1 on the other) or on a pole edge
    u = np.sort(np.stack([seams.uv_a[:, 0], seams.uv_b[:, 0]], axis=1), axis=1)
    lon = (u[:, 0] == 0) & (u[:, 1] == 1)
    pole_v = np.minimum(seams.uv_a[:, 1], 1 - seams.uv_a[:, 1])
    assert lon.sum() > 0 and np.all(lon | (pole_v < 1.5 / 9))  # 9 latitude bands: the polar ones
    pairs = seams.pairs()
    lon_pairs = pairs[(pairs[:, 0] % w == 0) & (pairs[:, 1] % w == w - 1)]
    assert len(lon_pairs) >= h - 4  # one per texel row, rows at the poles aside
    grid = np.random.default_rng(2).random((h, w, 2)).astype(np.float32)
    out = average_across_seams(bake.fill_padding(grid), seams)
    assert np.abs(seam_gaps(out, seams)).max() < 1e-3
    uva, uvb, _, _ = random_seam_points(m, 500)
    for c in range(2):
        d = render_lookup(out[..., c], uva, device) - render_lookup(out[..., c], uvb, device)
        assert np.abs(d).max() < 1e-3  # as above: a quarter of an 8-bit code value


def test_no_seams_is_a_no_op():
    from test_geometry_bake import uv_plane

    m = uv_plane()
    bake = bake_texels(m, 16, 8)
    seams = find_seams(m, 16, 8, bake.fill_source)
    assert seams.n_samples == 0
    g = np.random.default_rng(0).random((8, 16, 3))
    np.testing.assert_array_equal(average_across_seams(g, seams), g)


def test_atlas_stage_writes_seams(tmp_path, atlased):
    from texstream.geometry.mesh_io import save_mesh

    save_mesh(tmp_path / "ico.ply", icosphere(1.0, 2))
    res = atlas_stage(tmp_path / "ico.ply", tmp_path / "atlas", AtlasConfig(resolution=64))
    s = Seams.load(tmp_path / "atlas" / SEAMS_FILE)
    assert s.width == res.summary["width"] and s.n_samples > 0 and res.summary["seam_edges"] == s.n_edges
    with pytest.raises(InputError, match="atlas"):
        Seams.load(tmp_path / "missing.npz")


def test_a_seam_system_is_factorised_once_for_every_map_of_an_atlas(atlased, monkeypatch):
    """The seam solve keeps its factorisations by system (constraint matrix, eps) and inverse costs
    (geometry/seams.py ``_factor_cache``): a second map on the same atlas, and a channel whose active set holds
    the same texels as another's, reuse them; the results are those of fresh factorisations to the bit (the same
    matrix factorised the same way)."""
    from texstream.geometry import seams as seams_module

    _, bake, seams = atlased
    rng = np.random.default_rng(5)
    lo, hi = np.array([0.0, 0.0]), np.array([1.0, 1.0])
    grid = bake.fill_padding(np.where(rng.random((bake.height, bake.width, 2)) < 0.5, lo, hi).astype(np.float32))
    made = []
    factor = seams_module._seam_factor
    monkeypatch.setattr(seams_module, "_seam_factor", lambda *a: made.append(1) or factor(*a))
    monkeypatch.setattr(seams_module, "_FACTORS", {})
    first = average_across_seams(grid, seams, lower=lo, upper=hi)
    n_first = len(made)
    again = average_across_seams(grid, seams, lower=lo, upper=hi)
    assert n_first >= 2 and len(made) == n_first  # the base system and an active set; nothing new the second time
    monkeypatch.setattr(seams_module, "_FACTORS", {})  # fresh factorisations: the same bits
    fresh = average_across_seams(grid, seams, lower=lo, upper=hi)
    assert np.array_equal(first, again) and np.array_equal(first, fresh)


def test_the_bounded_channels_on_threads_give_one_threads_bits(atlased, monkeypatch):
    """Each channel's active-set rounds are its own, so solving the channels on threads (geometry/seams.py: SuperLU
    releases the GIL while it factorises; with several cores one thread a channel) gives the maps of one thread to
    the bit."""
    from texstream.geometry import seams as seams_module

    used = []
    in_order = seams_module.in_order
    monkeypatch.setattr(seams_module, "in_order", lambda work, items, threads: (used.append(threads),
                                                                                 in_order(work, items, threads))[1])

    _, bake, seams = atlased
    rng = np.random.default_rng(7)
    lo, hi = np.array([0.0, 1.0, 0.0]), np.array([10.0, 1.0e4, 1.0])
    grid = bake.fill_padding(np.where(rng.random((bake.height, bake.width, 3)) < 0.5, lo, hi).astype(np.float32))
    out = {}
    for threads in (1, 2):
        monkeypatch.setattr(seams_module, "threads_for", lambda asked, device, t=threads: t)
        monkeypatch.setattr(seams_module, "_FACTORS", {})
        out[threads] = average_across_seams(grid, seams, lower=lo, upper=hi)
    assert np.array_equal(out[1], out[2]) and used == [1, 3]  # 2 cores: the 3 channels on a thread each
