"""Procedural meshes with analytic UVs for synthetic capture sets (numpy only).

- :func:`uv_sphere`: a sphere as a surface of revolution, cylindrical UVs.
- :func:`icosphere`: a subdivided icosahedron (no UVs: for atlas tests).
- :func:`flat_sample`: a subdivided square material sample in the z = 0 plane, UVs = position.
- :func:`ornament`: a Christmas-ornament-like surface of revolution (round body, neck, cap),
  ~3,700 triangles at the defaults, like the seed's ornament (Table 8.1: 3,690 polygons).
- :func:`star`: a puffy five-pointed star (a flattened sphere with a star-shaped outline), 6,240
  triangles at the defaults, like the seed's LFM star (Table 7.1: 6,093 polygons).

Surfaces of revolution (:func:`revolve`) are about the +z axis. UVs: u = azimuth / 2 pi (the seam
column is duplicated, so u runs 0..1 without wrapping), v = arc-length fraction of the profile,
v = 0 at the bottom pole and 1 at the top (v up, capture/conventions.py). The profile stops at a
small radius at each end and is closed by a fan to the pole; each fan triangle has its own pole
vertex at u = segment centre, so no triangle has degenerate UVs. Normals are analytic: the
profile's normal (from central differences, exact for circular arcs sampled uniformly) turned
about the axis.

All meshes are counter-clockwise seen from outside (outward face normals), float64 vertices.
"""

from __future__ import annotations

import numpy as np

from texstream.render.mesh import SurfaceMesh
from texstream.core.errors import ConfigError


def revolve(r: np.ndarray, z: np.ndarray, n_segments: int, normals_rz: np.ndarray | None = None,
            z_poles: tuple[float, float] | None = None) -> SurfaceMesh:
    """Surface of revolution of a profile, closed at both ends by pole fans.

    Args:
        r: (K,) profile radii, all > 0, from the bottom end to the top end.
        z: (K,) profile heights.
        n_segments: number of segments around the axis.
        normals_rz: (K, 2) optional outward profile normals (n_r, n_z); default from central
            differences of the profile.
        z_poles: heights of the bottom and top pole vertices (default: the end rings' heights,
            i.e. flat end discs).

    Returns:
        A :class:`SurfaceMesh` with 2 * n_segments * K triangles, UVs, normals and source_vertex
        (the seam column maps to the first column, pole vertices to one welded pole each).
    """
    r = np.asarray(r, dtype=np.float64)
    z = np.asarray(z, dtype=np.float64)
    k = r.shape[0]
    if k < 2 or np.any(r <= 0) or n_segments < 3:
        raise ConfigError("profile needs >= 2 points with r > 0 and n_segments >= 3")
    z_bot, z_top = (z[0], z[-1]) if z_poles is None else (float(z_poles[0]), float(z_poles[1]))
    # arc length along pole - profile - pole, for v
    pts = np.concatenate([[[0.0, z_bot]], np.stack([r, z], 1), [[0.0, z_top]]])
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    s /= s[-1]
    v_ring = s[1:-1]

    if normals_rz is None:
        ext = np.concatenate([[[-r[0], z[0]]], np.stack([r, z], 1), [[-r[-1], z[-1]]]])
        # mirror the end rings across the axis so the end tangents run across the pole
        tan = ext[2:] - ext[:-2]
        normals_rz = np.stack([tan[:, 1], -tan[:, 0]], 1)
    nrz = np.asarray(normals_rz, dtype=np.float64)
    nrz = nrz / np.linalg.norm(nrz, axis=1, keepdims=True)

    ns = n_segments
    phi = 2.0 * np.pi * np.arange(ns + 1) / ns
    cphi, sphi = np.cos(phi), np.sin(phi)
    cphi[-1], sphi[-1] = 1.0, 0.0  # exact seam duplicate
    ring_v = np.stack([r[:, None] * cphi[None], r[:, None] * sphi[None], np.broadcast_to(z[:, None], (k, ns + 1))], -1)
    ring_n = np.stack([nrz[:, 0:1] * cphi[None], nrz[:, 0:1] * sphi[None], np.broadcast_to(nrz[:, 1:2], (k, ns + 1))], -1)
    ring_uv = np.stack([np.broadcast_to(np.arange(ns + 1)[None] / ns, (k, ns + 1)),
                        np.broadcast_to(v_ring[:, None], (k, ns + 1))], -1)
    n_ring = k * (ns + 1)
    verts = [ring_v.reshape(-1, 3)]
    norms = [ring_n.reshape(-1, 3)]
    uvs = [ring_uv.reshape(-1, 2)]
    col = np.arange(ns + 1) % ns
    src = [(np.arange(k)[:, None] * ns + col[None]).reshape(-1)]
    n_weld_ring = k * ns
    # pole vertices: one per segment (u at segment centre), welded to one source vertex
    uc = (np.arange(ns) + 0.5) / ns
    for zp, vp, nz, widx in ((z_bot, 0.0, -1.0, n_weld_ring), (z_top, 1.0, 1.0, n_weld_ring + 1)):
        verts.append(np.tile([0.0, 0.0, zp], (ns, 1)))
        norms.append(np.tile([0.0, 0.0, nz], (ns, 1)))
        uvs.append(np.stack([uc, np.full(ns, vp)], 1))
        src.append(np.full(ns, widx))
    bot0 = n_ring
    top0 = n_ring + ns

    def vid(ring, j):
        return ring * (ns + 1) + j

    kk, jj = np.meshgrid(np.arange(k - 1), np.arange(ns), indexing="ij")
    a, b = vid(kk, jj), vid(kk, jj + 1)
    c, d = vid(kk + 1, jj + 1), vid(kk + 1, jj)
    quads = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    j = np.arange(ns)
    fan_bot = np.stack([bot0 + j, vid(0, j + 1), vid(0, j)], 1)
    fan_top = np.stack([top0 + j, vid(k - 1, j), vid(k - 1, j + 1)], 1)
    faces = np.concatenate([fan_bot, quads, fan_top]).astype(np.int32)
    return SurfaceMesh(vertices=np.concatenate(verts), faces=faces, normals=np.concatenate(norms),
                       uvs=np.concatenate(uvs), source_vertex=np.concatenate(src).astype(np.int32))


def uv_sphere(radius: float = 1.0, n_segments: int = 64, n_rings: int = 32, center=(0.0, 0.0, 0.0)) -> SurfaceMesh:
    """A sphere: ``n_rings`` latitude rings between the poles, exact normals (p - center) / radius."""
    if n_rings < 2:
        raise ConfigError("uv_sphere needs n_rings >= 2")
    theta = np.pi * (np.arange(n_rings) + 1) / (n_rings + 1)  # polar angle from the top, excluding poles
    theta = theta[::-1]  # bottom to top
    r, z = radius * np.sin(theta), radius * np.cos(theta)
    m = revolve(r, z, n_segments, normals_rz=np.stack([np.sin(theta), np.cos(theta)], 1),
                z_poles=(-radius, radius))
    m.vertices += np.asarray(center, dtype=np.float64)
    return m


def icosphere(radius: float = 1.0, subdivisions: int = 3) -> SurfaceMesh:
    """A subdivided icosahedron (welded, no UVs, exact normals)."""
    t = (1.0 + 5 ** 0.5) / 2.0
    v = np.array([[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t], [0, -1, -t],
                  [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]], dtype=np.float64)
    f = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4],
                  [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8],
                  [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]], dtype=np.int64)
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    for _ in range(subdivisions):
        edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
        uniq, inv = np.unique(edges, axis=0, return_inverse=True)
        mid = v[uniq].mean(axis=1)
        mid /= np.linalg.norm(mid, axis=1, keepdims=True)
        m = inv.reshape(3, -1).T + len(v)  # midpoints of edges (01, 12, 20) per face
        v = np.concatenate([v, mid])
        a, b, c = f[:, 0], f[:, 1], f[:, 2]
        m01, m12, m20 = m[:, 0], m[:, 1], m[:, 2]
        f = np.concatenate([np.stack([a, m01, m20], 1), np.stack([b, m12, m01], 1),
                            np.stack([c, m20, m12], 1), np.stack([m01, m12, m20], 1)])
    return SurfaceMesh(vertices=v * radius, faces=f.astype(np.int32), normals=v.copy())


def flat_sample(size: float = 1.0, n: int = 16) -> SurfaceMesh:
    """A flat square material sample in the z = 0 plane, centred at the origin, facing +z.

    ``n`` x ``n`` quads, two triangles each; UV = (x / size + 1/2, y / size + 1/2), so the
    texture's top row (v = 1) is at y = +size / 2.
    """
    if n < 1:
        raise ConfigError("flat_sample needs n >= 1")
    g = np.linspace(0.0, 1.0, n + 1)
    uu, vv = np.meshgrid(g, g, indexing="xy")  # (n+1, n+1), row = v index
    verts = np.stack([(uu - 0.5) * size, (vv - 0.5) * size, np.zeros_like(uu)], -1).reshape(-1, 3)
    uvs = np.stack([uu, vv], -1).reshape(-1, 2)
    ii, jj = np.meshgrid(np.arange(n), np.arange(n), indexing="xy")
    a = jj * (n + 1) + ii
    b, c, d = a + 1, a + n + 2, a + n + 1
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    return SurfaceMesh(vertices=verts, faces=faces.astype(np.int32), normals=np.tile([0.0, 0.0, 1.0], (len(verts), 1)),
                       uvs=uvs)


def ornament_profile(n_body: int = 20, n_neck: int = 4, n_cap: int = 5, body_radius: float = 1.0,
                     neck_radius: float = 0.25, neck_height: float = 0.24, cap_radius: float = 0.06):
    """Profile (r, z) of the ornament, bottom to top: a spherical body (centre at the origin), a
    cylindrical neck of ``neck_radius`` rising ``neck_height`` above where it meets the body, and a
    rounded cap (a quarter arc) ending at ``cap_radius`` from the axis before the top fan.

    Returns:
        r (K,), z (K,) and the (bottom, top) pole heights.
    """
    th_bot = np.pi - np.arcsin(cap_radius / body_radius)  # polar angle of the bottom ring
    th_top = np.arcsin(neck_radius / body_radius)  # where the body meets the neck
    th = np.linspace(th_bot, th_top, n_body)
    r_body, z_body = body_radius * np.sin(th), body_radius * np.cos(th)
    z0 = z_body[-1]
    zn = np.linspace(z0, z0 + neck_height, n_neck + 1)[1:]
    r_neck = np.full(n_neck, neck_radius)
    rc = neck_radius - cap_radius  # cap: quarter ellipse from the neck top toward the axis
    a = np.linspace(0.0, np.pi / 2, n_cap + 1)[1:]
    r_cap = cap_radius + rc * np.cos(a)
    z_cap = zn[-1] + 0.5 * rc * np.sin(a)
    return np.concatenate([r_body, r_neck, r_cap]), np.concatenate([z_body, zn, z_cap]), (-body_radius, z_cap[-1])


def ornament(n_segments: int = 64, n_body: int = 20, n_neck: int = 4, n_cap: int = 5, **profile_kw) -> SurfaceMesh:
    """The ornament: 2 * n_segments * (n_body + n_neck + n_cap) triangles (3,712 at the defaults).

    Body of radius 1 centred at the origin, neck and cap on +z (height ~1.29 at the top).
    """
    r, z, poles = ornament_profile(n_body, n_neck, n_cap, **profile_kw)
    return revolve(r, z, n_segments, z_poles=poles)


def star(n_points: int = 5, depth: float = 0.45, thickness: float = 0.5, n_segments: int = 80,
         n_rings: int = 39) -> SurfaceMesh:
    """A puffy star ornament: a sphere flattened to ``thickness`` along z whose radius in the xy plane
    follows 1 + depth cos(n_points phi) (points at phi = 2 pi k / n_points), so its surface has
    concave valleys between the points (self-occlusion, cast shadows, normals turning quickly).
    2 * n_segments * n_rings triangles: 6,240 at the defaults, the size of the dissertation's
    star (Table 7.1: 6,093 polygons). UVs as :func:`uv_sphere`; normals area-weighted over the welded
    vertices (the seam column and each pole fan share them)."""
    if n_points < 2 or not 0.0 <= depth < 1.0 or thickness <= 0.0:
        raise ConfigError("star needs n_points >= 2, 0 <= depth < 1 and thickness > 0")
    m = uv_sphere(1.0, n_segments, n_rings)
    v = m.vertices.copy()
    phi = np.arctan2(v[:, 1], v[:, 0])
    f = 1.0 + depth * np.cos(n_points * phi)
    v[:, 0] *= f
    v[:, 1] *= f
    v[:, 2] *= thickness
    return SurfaceMesh(vertices=v, faces=m.faces, normals=None, uvs=m.uvs,
                       source_vertex=m.source_vertex).with_normals()


PROCEDURAL = {"uv_sphere": uv_sphere, "icosphere": icosphere, "flat_sample": flat_sample, "ornament": ornament,
              "star": star}


def make(name: str, **params) -> SurfaceMesh:
    """A procedural mesh by name (keys of ``PROCEDURAL``) with keyword parameters."""
    if name not in PROCEDURAL:
        raise ConfigError(f"unknown procedural mesh {name!r}", fix=f"use one of {sorted(PROCEDURAL)}")
    try:
        return PROCEDURAL[name](**params)
    except TypeError as e:
        raise ConfigError(f"bad parameters for procedural mesh {name!r} ({e})") from None
