"""Shading functions shared by the synthetic renderer and the fit (one model, no disagreement).

All functions are generic over float32/float64 (Warp overloads them per argument type).
Conventions (light direction, BRDF units, UV orientation) are in
:mod:`texstream.capture.conventions`.

The Lafortune lobe of the seed (Eq. 2.12, ch. 8) is
    lobe(u, v) = max(Cx ux vx + Cy uy vy + Cz uz vz, 0) ^ n
with u the unit direction to the light and v the unit direction to the viewer, both in the local
tangent frame (x = tangent, y = bitangent, z = normal). The isotropic form has Cx = Cy = Cxy.
A texel's outgoing radiance is (rho_d + sum_j rho_s,j lobe_j) * E * cos(theta_i).
"""

from __future__ import annotations

from typing import Any

import warp as wp

LIGHT_POINT = wp.constant(0)
LIGHT_DIRECTIONAL = wp.constant(1)
LIGHT_NONE = wp.constant(2)
"""No light (a photo under fixed, unknown lighting, capture.json frames without ``light``): only the
radiance model (render/layout.py) fits or renders it, its model term being the radiance itself."""

# Shadow-ray offset relative to the mesh's bounding-box diagonal (the renderer's, and the fit's
# traced taps): large enough to clear float32 round-off of the hit position (~1e-7 x the scene
# size) with margin, small enough that contact shadows are not lost (a 1e-4 gap is sub-texel for
# any texture under ~5000 texels across).
SHADOW_EPS_REL = 1.0e-4


@wp.func
def incident_light(kind: int, pos_or_dir: wp.vec3, intensity: wp.vec3, p: wp.vec3):
    """Unit direction from ``p`` to the light, irradiance on a surface facing it (no cosine),
    and the distance to the light (a large number for directional lights)."""
    if kind == LIGHT_POINT:
        d = pos_or_dir - p
        r2 = wp.dot(d, d)
        r = wp.sqrt(r2)
        return d / r, intensity / r2, r
    return -wp.normalize(pos_or_dir), intensity, float(1.0e30)


@wp.func
def to_local(d: Any, t: Any, b: Any, n: Any):
    """Components of direction ``d`` in the frame (t, b, n)."""
    return type(d)(wp.dot(d, t), wp.dot(d, b), wp.dot(d, n))


@wp.func
def lafortune_base(c: Any, u: Any, v: Any):
    """The lobe's base s = Cx ux vx + Cy uy vy + Cz uz vz (not clamped)."""
    return c[0] * u[0] * v[0] + c[1] * u[1] * v[1] + c[2] * u[2] * v[2]


@wp.func
def lafortune_lobe(c: Any, n: Any, u: Any, v: Any):
    """max(s, 0)^n, evaluated as exp(n log s) so exponents up to 1e4 underflow to 0, never NaN."""
    s = lafortune_base(c, u, v)
    if s <= type(n)(0.0):
        return type(n)(0.0)
    # capped at e^30 like the fit's model (fit/kernels/lafortune_grad.py) so they agree everywhere
    return wp.exp(wp.min(n * wp.log(s), type(n)(30.0)))


@wp.func
def texel_coords(uv: wp.vec2, width: int, height: int):
    """Continuous texel coordinates (centres at integers) of a UV (v up, row 0 at the top)."""
    return uv[0] * float(width) - 0.5, (1.0 - uv[1]) * float(height) - 0.5


@wp.func
def bilinear_taps(x: float, y: float, width: int, height: int):
    """Clamped integer corners and weights of a bilinear lookup at continuous coords (x, y)."""
    xc = wp.clamp(x, 0.0, float(width - 1))
    yc = wp.clamp(y, 0.0, float(height - 1))
    x0 = wp.min(int(wp.floor(xc)), width - 2)
    y0 = wp.min(int(wp.floor(yc)), height - 2)
    x0 = wp.max(x0, 0)
    y0 = wp.max(y0, 0)
    fx = xc - float(x0)
    fy = yc - float(y0)
    return x0, y0, fx, fy


@wp.func
def surface_frame(points: wp.array(dtype=wp.vec3), indices: wp.array(dtype=wp.int32),
                  normals: wp.array(dtype=wp.vec3), uvs: wp.array(dtype=wp.vec2),
                  face: int, b0: float, b1: float):
    """Position, UV, shading normal, tangent and bitangent at barycentrics (b0, b1, 1-b0-b1).

    The barycentric convention is Warp's ``mesh_query_ray`` one (p = b0 p0 + b1 p1 + b2 p2).
    The normal interpolates vertex normals; the tangent is dp/du of the face's UV mapping
    made orthogonal to the normal (bitangent = n x t), with an arbitrary perpendicular
    when the face's UVs are degenerate. The renderer and the texel bake both call this.
    """
    i0 = indices[face * 3 + 0]
    i1 = indices[face * 3 + 1]
    i2 = indices[face * 3 + 2]
    b2 = 1.0 - b0 - b1
    p0 = points[i0]
    p1 = points[i1]
    p2 = points[i2]
    pos = b0 * p0 + b1 * p1 + b2 * p2
    uv = b0 * uvs[i0] + b1 * uvs[i1] + b2 * uvs[i2]
    n = wp.normalize(b0 * normals[i0] + b1 * normals[i1] + b2 * normals[i2])
    e1 = p1 - p0
    e2 = p2 - p0
    d1 = uvs[i1] - uvs[i0]
    d2 = uvs[i2] - uvs[i0]
    det = d1[0] * d2[1] - d1[1] * d2[0]
    t = wp.vec3(0.0)
    if wp.abs(det) > 1.0e-20:
        t = (e1 * d2[1] - e2 * d1[1]) / det
    t = t - n * wp.dot(n, t)
    if wp.length(t) < 1.0e-12:
        # degenerate UVs: any tangent perpendicular to n
        a = wp.vec3(1.0, 0.0, 0.0)
        if wp.abs(n[0]) > 0.9:
            a = wp.vec3(0.0, 1.0, 0.0)
        t = a - n * wp.dot(n, a)
    t = wp.normalize(t)
    b = wp.cross(n, t)
    return pos, uv, n, t, b


@wp.func
def lafortune_brdf(params: wp.array2d(dtype=Any), row: int, n_lobes: int, aniso: int, u: Any, v: Any, one: Any):
    """BRDF (RGB, 1/sr) of texel ``row`` for local light direction ``u`` and view direction ``v``.

    Column layout as in :class:`texstream.render.layout.ModelLayout`: rho_d RGB, then per lobe
    rho_s RGB, C (c_xy, c_z or c_x, c_y, c_z) and n. ``one`` is the scalar 1 of the compute
    type (float32 or float64): parameters stored in any float type are cast to it.
    """
    out = type(u)(type(one)(params[row, 0]), type(one)(params[row, 1]), type(one)(params[row, 2]))
    stride = 6 + aniso
    for j in range(n_lobes):
        o = 3 + j * stride
        c = type(u)(type(one)(params[row, o + 3]), type(one)(params[row, o + 3]), type(one)(params[row, o + 4]))
        if aniso != 0:
            c = type(u)(type(one)(params[row, o + 3]), type(one)(params[row, o + 4]), type(one)(params[row, o + 5]))
        n = type(one)(params[row, o + stride - 1])
        lobe = lafortune_lobe(c, n, u, v)
        out = out + lobe * type(u)(type(one)(params[row, o]), type(one)(params[row, o + 1]), type(one)(params[row, o + 2]))
    return out


@wp.func
def view_radiance(params: wp.array2d(dtype=Any), row: int, v: Any, one: Any):
    """Radiance (RGB) of texel ``row`` of the view-dependent radiance model for local view ``v``:
    L_c + sum_k a_k,c phi_k(v), phi = (v_x, v_y, v_x^2, v_x v_y, v_y^2) (render/layout.py)."""
    phi = wp.vector(v[0], v[1], v[0] * v[0], v[0] * v[1], v[1] * v[1])
    out = type(v)(type(one)(params[row, 0]), type(one)(params[row, 1]), type(one)(params[row, 2]))
    for k in range(5):
        o = 3 + 3 * k
        out = out + phi[k] * type(v)(type(one)(params[row, o]), type(one)(params[row, o + 1]),
                                     type(one)(params[row, o + 2]))
    return out
