"""Ray-traced rendering of a textured Lafortune (or diffuse) mesh: one module-level Warp kernel.

Per pixel: a primary ray through the pixel centre (capture convention, centre of pixel (i, j) at
(i + 0.5, j + 0.5)), the closest hit on a ``wp.Mesh`` (BVH), the surface frame at the hit
(:func:`surface_frame`, the same one the texel bake uses), a shadow ray toward the light, and
the radiance

    L = f_r(u, v) * E * cos(theta_i)

with f_r the Lafortune BRDF of :func:`lafortune_brdf` (shared with the fit) looked up bilinearly
in the texel grid: the BRDF is evaluated at the four texels around the hit's continuous texel
coordinates and the four values are blended with the bilinear weights. At a texel centre this is
exactly the BRDF the fit models at that texel. E comes from :func:`incident_light`; L is zero
where the light is behind the shading normal or the shadow ray is blocked.

A layout with an ambient radiance A (render/layout.py ``ModelLayout.ambient``) adds A, looked up bilinearly the
same way, to every pixel on the object, lit by the flash or not (the room lights the shadows too).

The radiance model (fit/models) renders with a ``LIGHT_NONE`` light: L is the texels' radiance
columns looked up the same way (no light, cosine or shadow ray).

Everything is float32 (the renderer makes ground truth at photo precision, not fit precision).
"""

from __future__ import annotations

import warp as wp

from texstream.render.camera import ImageInfo
from texstream.render.shading import (LIGHT_NONE, bilinear_taps, incident_light, lafortune_brdf, surface_frame, texel_coords,
                                      to_local, view_radiance)


@wp.func
def shade_texel_grid(params: wp.array2d(dtype=wp.float32), tex_w: int, tex_h: int, n_lobes: int, aniso: int,
                     uv: wp.vec2, u_local: wp.vec3, v_local: wp.vec3):
    """Bilinear blend of the BRDF (RGB, 1/sr) of the four texels around ``uv``."""
    x, y = texel_coords(uv, tex_w, tex_h)
    x0, y0, fx, fy = bilinear_taps(x, y, tex_w, tex_h)
    one = wp.float32(1.0)
    r00 = y0 * tex_w + x0
    f00 = lafortune_brdf(params, r00, n_lobes, aniso, u_local, v_local, one)
    f10 = lafortune_brdf(params, r00 + 1, n_lobes, aniso, u_local, v_local, one)
    f01 = lafortune_brdf(params, r00 + tex_w, n_lobes, aniso, u_local, v_local, one)
    f11 = lafortune_brdf(params, r00 + tex_w + 1, n_lobes, aniso, u_local, v_local, one)
    return ((1.0 - fx) * (1.0 - fy)) * f00 + (fx * (1.0 - fy)) * f10 + ((1.0 - fx) * fy) * f01 + (fx * fy) * f11


@wp.func
def shade_view_texel_grid(params: wp.array2d(dtype=wp.float32), tex_w: int, tex_h: int, uv: wp.vec2,
                          v_local: wp.vec3):
    """Bilinear blend of the view-dependent radiance of the four texels around ``uv``, seen along the
    local view direction ``v_local``; negative values (a polynomial past its photos) clamp to 0."""
    x, y = texel_coords(uv, tex_w, tex_h)
    x0, y0, fx, fy = bilinear_taps(x, y, tex_w, tex_h)
    one = wp.float32(1.0)
    r00 = y0 * tex_w + x0
    f00 = view_radiance(params, r00, v_local, one)
    f10 = view_radiance(params, r00 + 1, v_local, one)
    f01 = view_radiance(params, r00 + tex_w, v_local, one)
    f11 = view_radiance(params, r00 + tex_w + 1, v_local, one)
    out = ((1.0 - fx) * (1.0 - fy)) * f00 + (fx * (1.0 - fy)) * f10 + ((1.0 - fx) * fy) * f01 + (fx * fy) * f11
    return wp.max(out, wp.vec3(0.0))


@wp.func
def ambient_texel_grid(params: wp.array2d(dtype=wp.float32), tex_w: int, tex_h: int, uv: wp.vec2, col: int):
    """Bilinear blend of the ambient radiance (columns ``col``..``col + 2``) of the four texels around ``uv``."""
    x, y = texel_coords(uv, tex_w, tex_h)
    x0, y0, fx, fy = bilinear_taps(x, y, tex_w, tex_h)
    out = wp.vec3(0.0)
    for corner in range(4):
        cx = corner % 2
        cy = corner // 2
        b = (fx * float(cx) + (1.0 - fx) * float(1 - cx)) * (fy * float(cy) + (1.0 - fy) * float(1 - cy))
        row = (y0 + cy) * tex_w + x0 + cx
        out = out + b * wp.vec3(params[row, col], params[row, col + 1], params[row, col + 2])
    return out


@wp.kernel(enable_backward=False)
def render_kernel(mesh_id: wp.uint64,
                  points: wp.array(dtype=wp.vec3), indices: wp.array(dtype=wp.int32),
                  normals: wp.array(dtype=wp.vec3), uvs: wp.array(dtype=wp.vec2),
                  params: wp.array2d(dtype=wp.float32), tex_w: int, tex_h: int, n_lobes: int, aniso: int,
                  view_terms: int, ambient_col: int, cam: ImageInfo, shadow_eps: float, shadows: int,
                  radiance: wp.array2d(dtype=wp.vec3), mask: wp.array2d(dtype=wp.uint8),
                  depth: wp.array2d(dtype=wp.float32), face_id: wp.array2d(dtype=wp.int32)):
    """Render one image; launch with dim = (height, width).

    Outputs per pixel (row j, column i): linear radiance (RGB, no exposure), mask (1 on the
    object), depth (camera z of the hit, i.e. the OpenCV Z coordinate, 0 off the object) and the
    hit face (-1 off the object).

    ``cam`` is the view's camera and light (``light_kind``, ``light_vec``: position of a point light or
    travel direction of a directional one, ``light_intensity``; ``LIGHT_NONE`` for the radiance model,
    whose parameters are the radiance). Shadow rays start at the hit moved by ``shadow_eps`` (world units) along the geometric face
    normal, on the light's side of the face, so a ray cannot re-hit its own triangle (acne);
    the renderer sets it to 1e-4 x the mesh's bounding-box diagonal. They end ``shadow_eps``
    short of a point light. ``ambient_col`` >= 0: the layout's ambient columns, added everywhere on the object.
    """
    j, i = wp.tid()
    # primary ray: camera-space direction through the pixel centre, then to world
    d_cam = wp.vec3((float(i) + 0.5 - cam.cx) / cam.fx, (float(j) + 0.5 - cam.cy) / cam.fy, 1.0)
    rt = wp.transpose(cam.rot)
    origin = -(rt @ cam.trans)
    inv_len = 1.0 / wp.length(d_cam)
    d = wp.normalize(rt @ d_cam)

    radiance[j, i] = wp.vec3(0.0)
    mask[j, i] = wp.uint8(0)
    depth[j, i] = 0.0
    face_id[j, i] = -1

    hit = wp.mesh_query_ray(mesh_id, origin, d, 1.0e30)
    if not hit.result:
        return
    mask[j, i] = wp.uint8(1)
    depth[j, i] = hit.t * inv_len  # distance along the unit ray times cos to the optical axis = Z
    face_id[j, i] = hit.face

    pos, uv, n, tg, bt = surface_frame(points, indices, normals, uvs, hit.face, hit.u, hit.v)
    if cam.light_kind == LIGHT_NONE:
        # radiance model: n_lobes = 0, so the blended "BRDF" is the texels' radiance L itself
        if view_terms > 0:
            radiance[j, i] = shade_view_texel_grid(params, tex_w, tex_h, uv, to_local(-d, tg, bt, n))
        else:
            radiance[j, i] = shade_texel_grid(params, tex_w, tex_h, n_lobes, aniso, uv, n, n)
        return
    ambient = wp.vec3(0.0)
    if ambient_col >= 0:
        ambient = ambient_texel_grid(params, tex_w, tex_h, uv, ambient_col)
        radiance[j, i] = ambient
    l, e, dist = incident_light(cam.light_kind, cam.light_vec, cam.light_intensity, pos)
    cos_i = wp.dot(n, l)
    if cos_i <= 0.0:
        return  # light behind the shading normal

    if shadows != 0:
        ng = hit.normal
        if wp.dot(ng, l) < 0.0:
            ng = -ng
        start = pos + shadow_eps * ng
        if wp.mesh_query_ray_anyhit(mesh_id, start, l, dist - shadow_eps):
            return  # cast shadow

    u_local = to_local(l, tg, bt, n)
    v_local = to_local(-d, tg, bt, n)
    f = shade_texel_grid(params, tex_w, tex_h, n_lobes, aniso, uv, u_local, v_local)
    radiance[j, i] = ambient + wp.cw_mul(f, e) * cos_i
