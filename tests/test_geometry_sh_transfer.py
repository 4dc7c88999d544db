"""Per-texel SH transfer with visibility (geometry/sh_transfer.py) against render/sh.py's closed form.

On a convex mesh nothing occludes, so the Monte Carlo transfer must equal ``sh.unoccluded_transfer`` up to the
sampling error; inside a concavity (the floor of a box open at the top) the walls hide part of the sky, so the
constant term (the texel's ambient visibility) is smaller, by the solid-angle share the walls take.
"""

from __future__ import annotations

import numpy as np

from texstream.capture.synthetic.procedural import icosphere
from texstream.geometry.sh_transfer import sh_transfer
from texstream.render import sh
from texstream.render.mesh import SurfaceMesh


def test_convex_mesh_gives_the_unoccluded_transfer():
    mesh = icosphere(1.0, 3)
    fn = mesh.face_normals()
    rng = np.random.default_rng(0)
    faces = rng.integers(0, mesh.n_faces, 200)
    bary = rng.dirichlet(np.ones(3), 200)
    pos = np.einsum("nk,nkd->nd", bary, mesh.vertices[mesh.faces[faces]])
    nrm = pos / np.linalg.norm(pos, axis=1, keepdims=True)  # the sphere's true normal (shading normal)
    t = sh_transfer(mesh.vertices, mesh.faces, pos, nrm, fn[faces], samples=256)
    want = sh.unoccluded_transfer(nrm)
    # 16 x 16 stratified cosine samples: the error of a smooth integrand's strata mean is ~1e-3 of the basis'
    # range (0.28-1.09); 0.01 is several times the largest seen, and far below an occluded texel's loss (> 0.05).
    # The shading normal differs from the flat face's by < 8 deg on this icosphere: rays within ~8 deg of the
    # tangent plane leave between face and sphere and see nothing: a cos^2 (< 2%) share of the lobe, no hit
    np.testing.assert_allclose(t, want, atol=0.01)
    # a constant sky of radiance 1 gives radiance 1 to an unoccluded white texel (the convention's check)
    lit = sh.diffuse_radiance(np.ones((200, 1)), t, sh.project_latlong(np.ones((16, 32, 1))))
    np.testing.assert_allclose(lit, 1.0, atol=0.01)


def _open_box(depth: float) -> SurfaceMesh:
    """A unit square floor at z = 0 with four walls up to z = depth (no lid), normals inwards: a concavity."""
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0],
                  [0, 0, depth], [1, 0, depth], [1, 1, depth], [0, 1, depth]], float)
    f = [[0, 1, 2], [0, 2, 3]]
    for a, b in ((0, 1), (1, 2), (2, 3), (3, 0)):
        f += [[a, b + 4, b], [a, a + 4, b + 4]]
    return SurfaceMesh(vertices=v, faces=np.array(f, np.int32))


def test_concavity_has_a_smaller_transfer():
    box = _open_box(1.0)
    pos = np.array([[0.5, 0.5, 0.0], [0.1, 0.5, 0.0]])
    nrm = np.array([[0.0, 0.0, 1.0]] * 2)
    t = sh_transfer(box.vertices, box.faces, pos, nrm, samples=1024)
    free = sh.unoccluded_transfer(nrm)
    # the floor's centre sees the sky through a 1 x 1 opening one unit up: the cosine-weighted share of the
    # hemisphere inside it is the view factor of a point to a coaxial square, four corner rectangles of sides
    # A = B = 0.5 at distance 1: (2 / pi) * 2 * A / sqrt(1 + A^2) * atan(B / sqrt(1 + A^2))
    a = 0.5 / np.sqrt(1.25)
    view_factor = (2.0 / np.pi) * 2.0 * a * np.arctan(a)
    np.testing.assert_allclose(t[0, 0] / free[0, 0], view_factor, atol=0.01)  # 32 x 32 strata: error < 0.005
    # nearer a wall it sees less of the opening than the centre does
    assert t[1, 0] < t[0, 0]
    assert np.all(t[:, 0] < free[:, 0] - 0.05)
    # the sky it sees is straight up: the z (k=2) term keeps more of its share than the constant term does
    assert t[0, 2] / free[0, 2] > t[0, 0] / free[0, 0]
