"""An atlas folder is read and its texels set up once per process while its files stay the same: the model
choice's candidates and the fit after them (four set-ups of one atlas in a `texstream run` of real photos) get
the very arrays of the first, read-only so no caller can change another's; a changed file is read again. The
texels' derivatives computed on covered texels alone equal those of the whole grid (to the bit)."""

import os

import numpy as np
import pytest

from texstream.capture.synthetic.procedural import uv_sphere
from texstream.fit.common.inputs import load_geometry
from texstream.fit.common.setup import texels_of
from texstream.fit.stream.texels import surface_derivatives, texel_coordinate_gradients
from texstream.geometry.bake import bake_texels
from texstream.geometry.mesh_io import save_mesh


@pytest.fixture()
def atlas_folder(tmp_path):
    mesh = uv_sphere(1.0, 24, 12).with_normals()
    save_mesh(tmp_path / "mesh.obj", mesh)
    bake_texels(mesh, 48, 24).save(tmp_path / "bake.npz")
    return tmp_path


def test_atlas_read_once_while_unchanged(atlas_folder):
    mesh, bake = load_geometry(atlas_folder, 0, "cpu")
    again = load_geometry(atlas_folder, 0, "cpu")
    assert again[0] is mesh and again[1] is bake
    with pytest.raises(ValueError):
        bake.face[0, 0] = 3  # read-only: a caller's change would reach every later fit
    with pytest.raises(ValueError):
        mesh.vertices[0, 0] = 0.0
    texels = texels_of(mesh, bake, mesh.vertex_normals())
    assert texels_of(mesh, bake, mesh.vertex_normals()) is texels
    with pytest.raises(ValueError):
        texels.position[0, 0] = 0.0
    # a new bake (another size, a later modification time) is read again
    stat = os.stat(atlas_folder / "bake.npz")
    bake_texels(mesh, 32, 16).save(atlas_folder / "bake.npz")
    os.utime(atlas_folder / "bake.npz", ns=(stat.st_atime_ns, stat.st_mtime_ns + 10**9))
    mesh2, bake2 = load_geometry(atlas_folder, 0, "cpu")
    assert bake2 is not bake and bake2.width == 32
    assert texels_of(mesh2, bake2, mesh2.vertex_normals()) is not texels


def test_writable_geometry_is_not_reused():
    """A mesh built in memory may change between set-ups (refine moves vertices): its texels are built anew."""
    mesh = uv_sphere(1.0, 16, 8).with_normals()
    bake = bake_texels(mesh, 32, 16)
    first = texels_of(mesh, bake, mesh.vertex_normals())
    assert texels_of(mesh, bake, mesh.vertex_normals()) is not first


def test_derivatives_on_covered_texels_match_the_grid_rule(atlas_folder):
    """Texels on no face get zeros, as the whole-grid computation gave them (face -1 -> bary 0 -> zeros)."""
    mesh, bake = load_geometry(atlas_folder, 0, "cpu")
    fn, jac = surface_derivatives(mesh.vertices, mesh.faces, mesh.vertex_normals(), bake.face, bake.bary)
    grad = texel_coordinate_gradients(mesh.vertices, mesh.faces, mesh.uvs, bake.face, bake.width, bake.height)
    off = bake.face < 0
    assert off.any() and (~off).any()
    assert not fn[off].any() and not jac[off].any() and not grad[off].any()
    assert fn.dtype == jac.dtype == grad.dtype == np.float32
    # the covered texels' face normals are unit and their texel-coordinate gradients non-zero
    np.testing.assert_allclose(np.linalg.norm(fn[~off], axis=-1), 1.0, atol=1e-5)  # float32 normalisation
    assert np.all(np.abs(grad[~off]).sum(axis=(-1, -2)) > 0)
