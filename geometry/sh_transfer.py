"""Per-texel diffuse transfer vectors with self-occlusion: T[k] = (1 / pi) * integral V(w) max(0, n.w) Y_k(w) dw.

The convention (basis, order, constants) is render/sh.py's; a Lambertian texel of albedo a under an order-2 SH
light L (9, 3) sends a * (T @ L). Unoccluded, T is ``sh.unoccluded_transfer(n)``; here V(w), the environment's
visibility from the texel, comes from rays cast against the mesh, so a concavity's texels get a smaller
transfer instead of a darker albedo.

Monte Carlo with cosine-weighted directions (Malley: uniform on the unit disk, lifted to the hemisphere):
the cosine and the 1 / pi cancel against the sampling density, so T[k] is the mean of V Y_k over the
samples. The unit square is stratified (``side`` x ``side`` cells, one jittered sample in each, the jitter a
hash of texel and cell, deterministic): the error of the unoccluded part falls about as 1 / side^2 rather
than 1 / side. Rays start ``SHADOW_EPS_REL`` x the mesh's bounding-box diagonal off the surface along the
face normal, as the renderer's shadow rays do (render/shading.py).
"""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from texstream.render.sh import SH_COUNT, sh9_basis_component
from texstream.render.shading import SHADOW_EPS_REL


@wp.func
def _hash01(a: int, b: int, salt: int):
    """A float in [0, 1) from two integers (a 32-bit integer hash; deterministic on every device)."""
    h = wp.uint32(a) * wp.uint32(747796405) + wp.uint32(b) * wp.uint32(2891336453) + wp.uint32(salt) * wp.uint32(
        277803737)
    h = h ^ (h >> wp.uint32(16))
    h = h * wp.uint32(2246822519)
    h = h ^ (h >> wp.uint32(13))
    h = h * wp.uint32(3266489917)
    h = h ^ (h >> wp.uint32(16))
    return float(h >> wp.uint32(8)) / 16777216.0


@wp.func
def _tangent_frame(n: wp.vec3):
    """Two unit vectors completing ``n`` to an orthonormal frame (Frisvad / Duff et al.)."""
    s = 1.0
    if n[2] < 0.0:
        s = -1.0
    a = -1.0 / (s + n[2])
    b = n[0] * n[1] * a
    t = wp.vec3(1.0 + s * n[0] * n[0] * a, s * b, -s * n[0])
    u = wp.vec3(b, s + n[1] * n[1] * a, -n[1])
    return t, u


@wp.kernel
def _transfer_kernel(mesh: wp.uint64, positions: wp.array(dtype=wp.vec3), normals: wp.array(dtype=wp.vec3),
                     face_normals: wp.array(dtype=wp.vec3), side: int, eps: float, max_t: float, occlusion: int,
                     transfer: wp.array2d(dtype=float)):
    i = wp.tid()
    n = wp.normalize(normals[i])
    t, u = _tangent_frame(n)
    start = positions[i] + eps * face_normals[i]
    acc = wp.vector(dtype=float, length=9)
    for cell in range(side * side):
        cx = cell % side
        cy = cell // side
        su = (float(cx) + _hash01(i, cell, 1)) / float(side)
        sv = (float(cy) + _hash01(i, cell, 2)) / float(side)
        r = wp.sqrt(su)
        phi = 2.0 * wp.pi * sv
        x = r * wp.cos(phi)
        y = r * wp.sin(phi)
        z = wp.sqrt(wp.max(0.0, 1.0 - su))
        d = x * t + y * u + z * n
        visible = 1.0
        if occlusion != 0:
            if wp.mesh_query_ray_anyhit(mesh, start, d, max_t):
                visible = 0.0
        if visible > 0.0:
            for k in range(9):
                acc[k] = acc[k] + sh9_basis_component(d, k, 1.0)
    inv = 1.0 / float(side * side)
    for k in range(9):
        transfer[i, k] = acc[k] * inv


def sh_transfer(vertices: np.ndarray, faces: np.ndarray, positions: np.ndarray, normals: np.ndarray,
                face_normals: np.ndarray | None = None, samples: int = 256, occlusion: bool = True,
                device: str = "cpu") -> np.ndarray:
    """(N, 9) float64 transfer vectors of surface points ``positions`` (N, 3) with shading ``normals`` (N, 3).

    Args:
        vertices, faces: the mesh that occludes (world units; faces (F, 3)).
        face_normals: (N, 3) the geometric normal of each point's face, along which rays start off the surface
            (None: the shading normals).
        samples: directions per point, rounded up to a square (stratified side x side).
        occlusion: False gives the unoccluded transfer by the same sampling (for tests and comparisons).
    """
    positions = np.asarray(positions, np.float32)
    if len(positions) == 0:
        return np.zeros((0, SH_COUNT))
    side = max(1, math.ceil(math.sqrt(samples)))
    verts = np.asarray(vertices, np.float32)
    diag = float(np.linalg.norm(verts.max(axis=0) - verts.min(axis=0))) if len(verts) else 1.0
    points = wp.array(verts, dtype=wp.vec3, device=device)
    indices = wp.array(np.asarray(faces, np.int32).reshape(-1), dtype=wp.int32, device=device)
    mesh = wp.Mesh(points=points, indices=indices)
    fn = normals if face_normals is None else face_normals
    out = wp.zeros((len(positions), SH_COUNT), dtype=float, device=device)
    wp.launch(_transfer_kernel, dim=len(positions), device=device,
              inputs=[mesh.id, wp.array(positions, dtype=wp.vec3, device=device),
                      wp.array(np.asarray(normals, np.float32), dtype=wp.vec3, device=device),
                      wp.array(np.asarray(fn, np.float32), dtype=wp.vec3, device=device), side,
                      float(SHADOW_EPS_REL * max(diag, 1e-12)), float(4.0 * max(diag, 1e-12)), int(occlusion)],
              outputs=[out])
    return out.numpy().astype(np.float64)
