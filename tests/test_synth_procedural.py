"""Procedural meshes: orientation, analytic UVs without degenerate triangles, seams, sizes."""

from __future__ import annotations

import numpy as np
import pytest

from texstream.capture.synthetic import procedural
from texstream.core.errors import ConfigError


def _uv_areas(m):
    uv = m.uvs[m.faces]
    d1, d2 = uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]
    return 0.5 * (d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0])


@pytest.mark.parametrize("name", ["uv_sphere", "ornament", "icosphere"])
def test_closed_meshes_point_outwards(name):
    m = procedural.make(name)
    v = m.vertices[m.faces]
    # signed volume > 0 <=> counter-clockwise seen from outside
    vol = np.einsum("ij,ij->i", v[:, 0], np.cross(v[:, 1], v[:, 2])).sum() / 6.0
    assert vol > 0
    fn = m.face_normals()
    # vertex normals agree with the faces they belong to
    assert np.all(np.einsum("ij,ij->i", m.normals[m.faces].mean(1), fn) > 0.5)
    np.testing.assert_allclose(np.linalg.norm(m.normals, axis=1), 1.0, atol=1e-12)


@pytest.mark.parametrize("name", ["uv_sphere", "ornament", "flat_sample"])
def test_uvs_are_in_range_and_not_degenerate(name):
    m = procedural.make(name)
    assert m.uvs.min() >= 0.0 and m.uvs.max() <= 1.0
    a = _uv_areas(m)
    # every triangle (pole fans included) has positive UV area with the same orientation as in 3D
    assert np.all(a > 0)


def test_ornament_size_matches_the_seed():
    m = procedural.ornament()
    assert 3600 <= m.n_faces <= 3800  # seed Table 8.1: 3,690 polygons
    lo, hi = m.bbox()
    assert hi[2] > 1.2 and lo[2] == pytest.approx(-1.0)


def test_sphere_vertices_on_sphere_and_seam_duplicated():
    m = procedural.uv_sphere(2.0, n_segments=16, n_rings=8, center=(1.0, 0.0, 0.0))
    np.testing.assert_allclose(np.linalg.norm(m.vertices - [1.0, 0.0, 0.0], axis=1), 2.0, atol=1e-12)
    # seam: u = 0 and u = 1 columns share positions and the welded source vertex
    u0 = np.flatnonzero(m.uvs[:, 0] == 0.0)
    u1 = np.flatnonzero(m.uvs[:, 0] == 1.0)
    assert len(u0) == len(u1) == 8
    np.testing.assert_array_equal(m.vertices[u0], m.vertices[u1])
    np.testing.assert_array_equal(m.source_vertex[u0], m.source_vertex[u1])


def test_flat_sample_uv_is_position():
    m = procedural.flat_sample(size=2.0, n=3)
    np.testing.assert_allclose(m.uvs, m.vertices[:, :2] / 2.0 + 0.5, atol=1e-12)


def test_unknown_procedural_name():
    with pytest.raises(ConfigError):
        procedural.make("teapot")
    with pytest.raises(ConfigError):
        procedural.make("uv_sphere", nonsense=3)
