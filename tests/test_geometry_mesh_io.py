"""Mesh IO: OBJ seams/polygons/negative indices, PLY/GLB/STL round trips, bad input."""

from __future__ import annotations

import numpy as np
import pytest

from texstream.render.mesh import SurfaceMesh
from texstream.geometry.mesh_io import load_mesh, save_mesh
from texstream.core.errors import InputError

# A unit cube's top as a quad plus a triangle sharing two corners but on another UV island
# (a seam), written with a polygon, relative (negative) indices and normals.
SEAM_OBJ = """# test
v 0 0 0
v 1 0 0
v 1 1 0
v 0 1 0
vt 0 0
vt 0.5 0
vt 0.5 0.5
vt 0 0.5
vn 0 0 1
f 1/1/1 2/2/1 3/3/1 4/4/1
v 1 1 1
vt 0.6 0.6
vt 0.9 0.6
vt 0.9 0.9
f 3/-3/-1 -1/-2/-1 4/-1/-1
"""


def corner_attrs(m: SurfaceMesh) -> tuple[np.ndarray, np.ndarray | None]:
    """Per-corner positions and UVs: what a mesh means, independent of vertex numbering."""
    return m.vertices[m.faces], None if m.uvs is None else m.uvs[m.faces]


def same_partition(a: np.ndarray, b: np.ndarray) -> bool:
    """Two per-corner welded-vertex labellings describe the same welding."""
    pairs = np.unique(np.stack([a.ravel(), b.ravel()], 1), axis=0)
    return len(pairs) == len(np.unique(a)) == len(np.unique(b))


def test_obj_seams_polygons_negative_indices(tmp_path):
    p = tmp_path / "seam.obj"
    p.write_text(SEAM_OBJ)
    m = load_mesh(p)
    assert m.n_faces == 3  # quad fan-triangulated + triangle
    pos, uv = corner_attrs(m)
    np.testing.assert_array_equal(pos[2], [[1, 1, 0], [1, 1, 1], [0, 1, 0]])
    np.testing.assert_array_equal(uv[2], [[0.6, 0.6], [0.9, 0.6], [0.9, 0.9]])
    np.testing.assert_array_equal(uv[0], [[0, 0], [0.5, 0], [0.5, 0.5]])
    # corners 3 and 4 appear with two different vt: split vertices, welded by source_vertex
    assert m.n_vertices == 7
    assert np.array_equal(m.source_vertex[m.faces[2]], [2, 4, 3])
    np.testing.assert_array_equal(m.normals, np.tile([0.0, 0.0, 1.0], (7, 1)))


@pytest.mark.parametrize("ext", ["obj", "ply", "glb"])
def test_round_trip_keeps_corners_and_welding(tmp_path, ext):
    src = tmp_path / "seam.obj"
    src.write_text(SEAM_OBJ)
    m = load_mesh(src)
    out = tmp_path / f"copy.{ext}"
    save_mesh(out, m)
    r = load_mesh(out)
    pa, ua = corner_attrs(m)
    pb, ub = corner_attrs(r)
    # PLY and GLB store float32: 0.6, 0.9 round to ~2.4e-8
    np.testing.assert_allclose(pa, pb, atol=1e-7)
    np.testing.assert_allclose(ua, ub, atol=1e-7)
    assert r.n_vertices == m.n_vertices
    assert same_partition(m.source_vertex[m.faces], r.source_vertex[r.faces])
    np.testing.assert_allclose(r.normals, m.normals, atol=1e-6)  # normals stored as float32 / %.7g


def test_obj_without_uvs_round_trip(tmp_path):
    m = SurfaceMesh(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0.5]], float), np.array([[0, 1, 2]], np.int32))
    save_mesh(tmp_path / "t.obj", m)
    r = load_mesh(tmp_path / "t.obj")
    assert r.uvs is None
    np.testing.assert_allclose(r.vertices[r.faces], m.vertices[m.faces], atol=1e-9)  # %.9g text


def test_stl_ascii(tmp_path):
    p = tmp_path / "t.stl"
    p.write_text("solid t\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 1 0 0\nvertex 0 1 0\n"
                 "endloop\nendfacet\nendsolid t\n")
    m = load_mesh(p)
    assert m.n_faces == 1
    np.testing.assert_allclose(np.sort(m.vertices[m.faces[0]], axis=0),
                               np.sort(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float), axis=0))


def test_glb_uv_orientation_is_flipped(tmp_path):
    """glTF stores v down; texstream uses v up: a saved GLB holds 1 - v."""
    import json
    import struct

    m = SurfaceMesh(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float), np.array([[0, 1, 2]], np.int32),
                    uvs=np.array([[0.0, 0.25], [1.0, 0.25], [0.0, 1.0]]))
    save_mesh(tmp_path / "t.glb", m)
    raw = (tmp_path / "t.glb").read_bytes()
    jlen = struct.unpack_from("<I", raw, 12)[0]
    doc = json.loads(raw[20:20 + jlen])
    acc = doc["accessors"][doc["meshes"][0]["primitives"][0]["attributes"]["TEXCOORD_0"]]
    view = doc["bufferViews"][acc["bufferView"]]
    binary = raw[20 + jlen + 8:]
    uv = np.frombuffer(binary, "<f4", count=6, offset=view["byteOffset"]).reshape(3, 2)
    np.testing.assert_allclose(uv[:, 1], [0.75, 0.75, 0.0])


@pytest.mark.parametrize("text, words", [
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\n", "no faces"),
    ("v 0 0 0\nv nan 0 0\nv 0 1 0\nf 1 2 3\n", "not finite"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n", "out of range"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 x\n", "bad face index"),
])
def test_bad_obj(tmp_path, text, words):
    p = tmp_path / "bad.obj"
    p.write_text(text)
    with pytest.raises(InputError) as e:
        load_mesh(p)
    assert words in str(e.value) and "bad.obj" in str(e.value) and "Fix:" in str(e.value)


def test_missing_and_unsupported(tmp_path):
    with pytest.raises(InputError, match="not found"):
        load_mesh(tmp_path / "nope.obj")
    (tmp_path / "m.fbx").write_text("x")
    with pytest.raises(InputError, match="unsupported"):
        load_mesh(tmp_path / "m.fbx")
    (tmp_path / "bad.ply").write_text("this is not a ply file")
    with pytest.raises(InputError, match="bad.ply"):
        load_mesh(tmp_path / "bad.ply")
    (tmp_path / "bad.glb").write_bytes(b"\0" * 20)
    with pytest.raises(InputError, match="glTF"):
        load_mesh(tmp_path / "bad.glb")


def test_save_is_atomic_and_validates(tmp_path):
    bad = SurfaceMesh(np.zeros((3, 3)), np.array([[0, 1, 5]], np.int32))
    with pytest.raises(InputError, match="out of range"):
        save_mesh(tmp_path / "x.obj", bad)
    assert list(tmp_path.iterdir()) == []  # nothing half-written


@pytest.mark.parametrize("corner", ["{v}", "{v}/{t}", "{v}//{n}", "{v}/{t}/{n}"])
def test_plain_obj_read_by_numpy_as_by_the_general_parser(corner, monkeypatch, tmp_path):
    """Triangles with positive indices in one corner form (what texstream and most exporters write) take the
    numpy path; it must give the general parser's mesh exactly, comments, groups and materials between."""
    import texstream.geometry.mesh_io as mesh_io

    rng = np.random.default_rng(3)
    rows = ["# made by a test", "mtllib a.mtl", "o thing"]
    rows += [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in rng.random((6, 3))]
    rows += [f"vt {u:.4f} {v:.4f}" for u, v in rng.random((5, 2))]
    rows += ["vn 0 0 1", "vn 0 1 0", "g part", "usemtl m", "s off"]
    for k in range(8):
        corners = rng.choice(6, 3, replace=False) + 1
        rows.append("f " + " ".join(corner.format(v=v, t=(v + k) % 5 + 1, n=k % 2 + 1) for v in corners))
    path = tmp_path / "plain.obj"
    path.write_text("\n".join(rows) + "\n")
    assert mesh_io._read_obj_plain(path.read_text()) is not None
    fast = load_mesh(path)
    monkeypatch.setattr(mesh_io, "_read_obj_plain", lambda text: None)
    general = load_mesh(path)
    for name in ("vertices", "faces", "uvs", "normals", "source_vertex"):
        a, b = getattr(fast, name), getattr(general, name)
        assert (a is None) == (b is None) and (a is None or np.array_equal(a, b)), name


@pytest.mark.parametrize("text", [SEAM_OBJ, "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nf 1 2 3 4\n",
                                  "v 0 0 0 1\nv 1 0 0 1\nv 0 1 0 1\nf 1 2 3\n", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\nf 1 2/1 3\n"])
def test_other_obj_forms_go_to_the_general_parser(text):
    """Polygons, negative indices, vertex weights and mixed corner forms are the general parser's."""
    from texstream.geometry.mesh_io import _read_obj_plain

    assert _read_obj_plain(text) is None
