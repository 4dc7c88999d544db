"""The image-streaming distribution step (seed ch. 4-5, 8): one (texel, photo) sample as the passes see it.

A pass's thread takes a texel and loops over a group of photos, projecting the texel, testing
visibility against the photo's depth map and the light's shadow map, sampling the photo
(:func:`observe`: the nearest pixel with the model evaluated at the surface point it sees, or the
seed's bilinear filter), rejecting grazing / masked / clipped / out-of-frame / occluded samples; the
accumulation of the objective, gradient and curvature over the samples is
:mod:`texstream.fit.kernels.accumulate`'s, the initial guess from the samples this module's
(:func:`initial_guess_kernel_for`).

The functions read a photo's constants as ``infos[k].field`` where they use them, because a local copy
of the whole ``ImageInfo`` (about 50 words) is loaded at once and stays live through the sample
(registers decide the speed, benchmarks/results/h100_kernels).
"""

from __future__ import annotations

import functools
from typing import Any

import warp as wp

from texstream.fit.kernels.overloads import IMAGE_PIXEL, declare
from texstream.render.camera import ImageInfo
from texstream.render.shading import bilinear_taps, incident_light, lafortune_brdf, surface_frame, texel_coords, to_local
from texstream.render.visibility import depth_consistent

# no kernel here is differentiated (the fit writes its own derivatives): skipping Warp's adjoint
# code generation roughly halves compile time
wp.set_module_options({"enable_backward": False})




@wp.struct
class TexelFrames:
    """The texels' surface location space (compact texel index), one struct so kernels take it whole.

    ``face_nrm`` (unit normal of the texel's face) and ``dn_dp`` (derivative of the shading normal
    along the face, divided by the interpolated normal's length, so that
    ``normalize(nrm + dn_dp @ dp)`` is the renderer's shading normal at ``pos + dp``) serve the
    point sampling of :func:`observe`; zero ``dn_dp`` and ``face_nrm = nrm`` describe a flat texel.
    """

    pos: wp.array(dtype=wp.vec3)
    nrm: wp.array(dtype=wp.vec3)
    tan: wp.array(dtype=wp.vec3)
    bit: wp.array(dtype=wp.vec3)
    face_nrm: wp.array(dtype=wp.vec3)
    dn_dp: wp.array(dtype=wp.mat33)
    # the renderer's texture lookup (``StreamConfig.model_lookup`` "bilinear", :func:`texel_blend`);
    # one-element placeholders otherwise
    centre_xy: wp.array(dtype=wp.vec2)
    """continuous texel coordinates of the texel's surface point (its grid position)"""
    dx_dp: wp.array(dtype=wp.vec3)
    """gradient of the texel x coordinate along the texel's face (0 off the face's plane)"""
    dy_dp: wp.array(dtype=wp.vec3)
    """gradient of the texel y coordinate along the texel's face"""
    grid_source: wp.array(dtype=wp.int32)
    """per atlas texel (y * width + x), the row of ``lookup_params`` the renderer reads there: the
    compact texel it is or whose value its padding copies, else the defaults row (the last)"""
    lookup_params: wp.array2d(dtype=wp.float32)
    """(N + 1, P) the parameters the neighbours are held at (:meth:`StreamProblem.refresh_lookup`),
    float32 as the renderer reads them; row N holds the layout's defaults"""
    grid_width: int
    grid_height: int
    n_lobes: int
    anisotropic: int
    # the mesh the filtered taps are traced to (``StreamConfig.tap_geometry`` "mesh", :func:`traced_tap`);
    # 0 and one-element placeholders otherwise
    mesh: wp.uint64
    mesh_points: wp.array(dtype=wp.vec3)
    mesh_indices: wp.array(dtype=wp.int32)
    mesh_normals: wp.array(dtype=wp.vec3)
    mesh_uvs: wp.array(dtype=wp.vec2)
    shadow_eps: float
    """the renderer's shadow-ray offset (1e-4 of the mesh's bounding-box diagonal, render/renderer.py)"""
    shadow_rays: int
    """1: traced taps cast shadow rays (``StreamConfig.shadow_map_size`` > 0, also for photos whose
    light sits inside the object's bounds and so has no shadow map); 0: cast shadows ignored"""


@wp.struct
class SampleOptions:
    """Rejection thresholds and what to accumulate (see FitConfig for the meaning)."""

    cos_light_min: float
    cos_view_min: float
    depth_tol: float
    shadow_tol: float
    reflectance_space: int
    sampling: int
    """SAMPLING_BILINEAR (0), SAMPLING_POINT (1) or SAMPLING_FILTERED (2): how a texel samples a
    photo (see :func:`observe`)."""
    robust_scale: float
    """the robust loss's scale k in residual units (photo values in radiance space), read by the
    passes compiled with a robust loss (:func:`accumulate_kernel` ``robust``); ignored otherwise"""




@wp.func
def unmasked(depth: wp.array3d(dtype=wp.float32), k: int, xs: float, ys: float):
    """Mask-only visibility (``ImageInfo.depth_is_mask``): the pixel nearest (xs, ys) is not masked.

    Nearest, not all four taps: single-view texels sit on pixel centres, where float rounding may
    pick a neighbour as the first bilinear tap with a weight of ~1e-6."""
    return depth[k, int(ys + 0.5), int(xs + 0.5)] > 0.0


@wp.func
def lit(shadow: wp.array3d(dtype=wp.float32), k: int, infos: wp.array(dtype=ImageInfo), p: wp.vec3, tol: float):
    """Point ``p`` is lit when no shadow-map tap around its projection is closer to the light."""
    if infos[k].has_shadow == 0:
        return True
    pl = infos[k].sh_rot @ p + infos[k].sh_trans
    if pl[2] <= 0.0:
        return False
    sx = 0.0
    sy = 0.0
    if infos[k].sh_ortho != 0:
        sx = infos[k].sh_fx * pl[0] + infos[k].sh_cx - 0.5
        sy = infos[k].sh_fy * pl[1] + infos[k].sh_cy - 0.5
    else:
        sx = infos[k].sh_fx * pl[0] / pl[2] + infos[k].sh_cx - 0.5
        sy = infos[k].sh_fy * pl[1] / pl[2] + infos[k].sh_cy - 0.5
    if sx < 0.0 or sy < 0.0 or sx >= float(infos[k].sh_size - 1) or sy >= float(infos[k].sh_size - 1):
        return True  # outside the map: nothing of the object lies between
    x0 = int(sx)
    y0 = int(sy)
    ok = True
    for dy in range(2):
        for dx in range(2):
            if shadow[k, y0 + dy, x0 + dx] < pl[2] * (1.0 - tol):
                ok = False
    return ok


@wp.func
def depth_tap_ok(depth: wp.array3d(dtype=wp.float32), k: int, x: int, y: int, z: float, tol: float, slack: float):
    """One depth-map tap sees this surface (masked or empty pixels hold 0 and fail)."""
    return wp.abs(depth[k, y, x] - z) <= tol * z + slack


SAMPLING_BILINEAR = wp.constant(0)
SAMPLING_POINT = wp.constant(1)
SAMPLING_FILTERED = wp.constant(2)


@wp.func
def ray_surface(ray: wp.vec3, cam: wp.vec3, p: wp.vec3, face_nrm: wp.vec3, plane: float, nrm: wp.vec3,
                dn_dp: wp.mat33):
    """Where the ray ``cam + t ray`` meets a texel's face plane (through ``p``, normal ``face_nrm``,
    ``plane`` = (p - cam) . face_nrm): (point, shading normal). The normal is the interpolated
    vertex normal there (``nrm + dn_dp (q - p)``, normalised), as the renderer's
    :func:`surface_frame` gives it; a ray nearly parallel to the plane keeps the texel's."""
    den = wp.dot(ray, face_nrm)
    if wp.abs(den) <= 1.0e-3 * wp.length(ray):
        return p, nrm
    q = cam + ray * (plane / den)
    return q, wp.normalize(nrm + dn_dp @ (q - p))


@wp.func
def texel_blend(tex: TexelFrames, i: int, x: float, y: float, u: wp.vec3, v: wp.vec3):
    """The renderer's texture lookup at continuous texel coordinates (x, y) (``StreamConfig.model_lookup``
    "bilinear"): the BRDF there is the bilinear blend of the four atlas texels around (x, y)
    (render/kernels.py ``shade_texel_grid``). Returns (w_own, b): the weight of texel i's own
    BRDF (it may sit at several corners through padding copies) and the blend of the other corners'
    BRDFs at local directions (u, v), read from ``tex.lookup_params`` (held fixed)."""
    x0, y0, fx, fy = bilinear_taps(x, y, tex.grid_width, tex.grid_height)
    own = float(0.0)
    other = wp.vec3(0.0)
    one = float(1.0)
    for corner in range(4):
        cx = corner % 2
        cy = corner // 2
        b = (fx * float(cx) + (1.0 - fx) * float(1 - cx)) * (fy * float(cy) + (1.0 - fy) * float(1 - cy))
        row = tex.grid_source[(y0 + cy) * tex.grid_width + x0 + cx]
        if row == i:
            own = own + b
        elif b > 0.0:
            other = other + b * lafortune_brdf(tex.lookup_params, row, tex.n_lobes, tex.anisotropic, u, v, one)
    return own, other


@wp.func
def texel_blend_ambient(tex: TexelFrames, i: int, x: float, y: float, col: int, room: bool):
    """The ambient radiance (columns ``col``..``col + 2`` of ``tex.lookup_params``; ``room``: the room light's
    radiance rho_d S, those columns times rho_d) that the renderer's lookup at continuous texel coordinates (x, y)
    blends in from the corners other than texel i (held fixed), as :func:`texel_blend` does for the BRDF; texel
    i's own weight there is :func:`texel_blend`'s."""
    x0, y0, fx, fy = bilinear_taps(x, y, tex.grid_width, tex.grid_height)
    other = wp.vec3(0.0)
    for corner in range(4):
        cx = corner % 2
        cy = corner // 2
        b = (fx * float(cx) + (1.0 - fx) * float(1 - cx)) * (fy * float(cy) + (1.0 - fy) * float(1 - cy))
        row = tex.grid_source[(y0 + cy) * tex.grid_width + x0 + cx]
        if row != i and b > 0.0:
            amb = wp.vec3(tex.lookup_params[row, col], tex.lookup_params[row, col + 1], tex.lookup_params[row, col + 2])
            if room:
                amb = wp.cw_mul(amb, wp.vec3(tex.lookup_params[row, 0], tex.lookup_params[row, 1],
                                             tex.lookup_params[row, 2]))
            other = other + b * amb
    return other


@wp.func
def plane_texel_coords(tex: TexelFrames, i: int, q: wp.vec3):
    """Texel coordinates of point ``q`` on texel i's face plane (``tap_geometry`` "plane"): the face's
    UV map extended linearly (``dx_dp``, ``dy_dp``), exact while q stays on the texel's face and a
    first-order guess beyond it (where ``tap_geometry`` "mesh" traces the tap instead)."""
    d = q - tex.pos[i]
    xy = tex.centre_xy[i]
    return xy[0] + wp.dot(tex.dx_dp[i], d), xy[1] + wp.dot(tex.dy_dp[i], d)


@wp.func
def traced_tap(tex: TexelFrames, cam: wp.vec3, ray: wp.vec3, light_kind: int, light_vec: wp.vec3, shadows: int):
    """What a filtered tap's pixel ray sees (``StreamConfig.tap_geometry`` "mesh"), exactly as the
    renderer (render/kernels.py) sees it: the closest hit on the mesh, the surface frame there
    (:func:`surface_frame`: interpolated normal, the face's UV tangent) and, with ``shadows``
    (``TexelFrames.shadow_rays``), a shadow ray toward the light from the same offset start.

    Returns (a, light direction, point, normal, tangent, bitangent, texel x, texel y) with
    a = cos(theta_i) * falloff (the light's 1/r^2; 1 for directional lights), 0 where the ray
    misses, the light is behind the normal or the shadow ray is blocked: the pixel the renderer
    leaves dark."""
    zero3 = wp.vec3(0.0)
    hit = wp.mesh_query_ray(tex.mesh, cam, wp.normalize(ray), 1.0e30)
    if not hit.result:
        return float(0.0), zero3, cam, zero3, zero3, zero3, float(0.0), float(0.0)
    p, uv, nrm, tg, bt = surface_frame(tex.mesh_points, tex.mesh_indices, tex.mesh_normals, tex.mesh_uvs,
                                       hit.face, hit.u, hit.v)
    wi, falloff, dist = incident_light(light_kind, light_vec, wp.vec3(1.0), p)
    x, y = texel_coords(uv, tex.grid_width, tex.grid_height)
    cos_i = wp.dot(wi, nrm)
    a = float(0.0)
    if cos_i > 0.0:
        a = cos_i * falloff[0]
        if shadows != 0:
            ng = hit.normal
            if wp.dot(ng, wi) < 0.0:
                ng = -ng
            if wp.mesh_query_ray_anyhit(tex.mesh, p + tex.shadow_eps * ng, wi, dist - tex.shadow_eps):
                a = float(0.0)
    return a, wi, p, nrm, tg, bt, x, y


@wp.func
def traced_texel(tex: TexelFrames, cam: wp.vec3, ray: wp.vec3):
    """The radiance model's :func:`traced_tap`: whether the tap's pixel ray hits the mesh (1 or 0)
    and the texel coordinates there; no light, so no cosine and no shadow ray."""
    hit = wp.mesh_query_ray(tex.mesh, cam, wp.normalize(ray), 1.0e30)
    if not hit.result:
        return float(0.0), float(0.0), float(0.0)
    p, uv, nrm, tg, bt = surface_frame(tex.mesh_points, tex.mesh_indices, tex.mesh_normals, tex.mesh_uvs,
                                       hit.face, hit.u, hit.v)
    x, y = texel_coords(uv, tex.grid_width, tex.grid_height)
    return float(1.0), x, y


@wp.func
def tangent_frame(nrm: wp.vec3, tex: TexelFrames, i: int):
    """(tangent, bitangent) about the shading normal ``nrm``: the texel's tangent made orthogonal."""
    tan = wp.normalize(tex.tan[i] - nrm * wp.dot(nrm, tex.tan[i]))
    return tan, wp.cross(nrm, tan)


@wp.func
def pixel_point(infos: wp.array(dtype=ImageInfo), k: int, tex: TexelFrames, i: int, x: int, y: int):
    """Where pixel (x, y)'s centre ray meets texel i (:func:`ray_surface`), with the tangent frame
    there: (point, normal, tangent, bitangent)."""
    p = tex.pos[i]
    ray = wp.transpose(infos[k].rot) @ wp.vec3((float(x) + 0.5 - infos[k].cx) / infos[k].fx, (float(y) + 0.5 - infos[k].cy) / infos[k].fy, 1.0)
    ng = tex.face_nrm[i]
    q, nrm = ray_surface(ray, infos[k].center, p, ng, wp.dot(p - infos[k].center, ng), tex.nrm[i], tex.dn_dp[i])
    tan, bit = tangent_frame(nrm, tex, i)
    return q, nrm, tan, bit


@functools.cache
def observe_func(radiance: bool = False):
    """:func:`observe` specialised to the model's light handling when it compiles: reflectance
    models (``radiance`` False) take each photo's light (the cosine and shadow tests, weight
    exposure * E * cos(theta_i)); the radiance model (render/layout.py) ignores any light (no cosine or
    shadow test, weight = exposure). Camera visibility, masks, saturation and grazing-view
    rejection are the same for both. The reflectance path does the arithmetic it did before the option."""
    no_light = bool(radiance)

    @wp.func
    def observe(images: wp.array3d(dtype=Any), depth: wp.array3d(dtype=wp.float32),
                shadow: wp.array3d(dtype=wp.float32), infos: wp.array(dtype=ImageInfo), k: int,
                tex: TexelFrames, i: int, opt: SampleOptions):
        """The distribution step for one (texel i, photo k).

        Returns (ok, radiance y, weight w, local light u, local view v, xs, ys): the photo's value,
        exposure * E * cos(theta_i) (the radiance model: exposure, see :func:`observe_func`; u = 0)
        and the local directions at the texel centre (at the pixel's
        surface point for point sampling; zero for filtered sampling, whose taps have their own),
        and the centre's continuous pixel coordinates (pixel centres at integers), which
        :func:`sample_model` needs for filtered sampling.

        How the photo is sampled (``opt.sampling``):

        * bilinear: the seed's filter, the photo interpolated at the texel centre's projection, the
          model evaluated at the centre. Exact for radiance linear across the 2x2 taps; a highlight a
          few pixels wide is blurred, which a narrow lobe then fits as a broader, dimmer one.
        * point: the pixel nearest the projection, the model evaluated at the surface point that
          pixel's centre sees. No blur, but the sample point wanders up to half a pixel from the
          texel centre, which adds scatter where parameters change across a texel a pixel or two wide.
        * filtered: the same bilinear filter applied to the photo and to the model, evaluated at each
          tap's surface point (:func:`sample_model`): exact for any radiance the texel's parameters
          describe across the taps, 4 model evaluations per sample.
        """
        zero3 = wp.vec3(0.0)
        p = tex.pos[i]
        nrm = tex.nrm[i]
        tan = tex.tan[i]
        bit = tex.bit[i]
        pc = infos[k].rot @ p + infos[k].trans
        if pc[2] <= 0.0:
            return False, zero3, zero3, zero3, zero3, 0.0, 0.0
        xs = infos[k].fx * pc[0] / pc[2] + infos[k].cx - 0.5
        ys = infos[k].fy * pc[1] / pc[2] + infos[k].cy - 0.5
        if xs < 0.0 or ys < 0.0 or xs >= float(infos[k].width - 1) or ys >= float(infos[k].height - 1):
            return False, zero3, zero3, zero3, zero3, 0.0, 0.0
        vdir = wp.normalize(infos[k].center - p)
        cos_v = wp.dot(vdir, nrm)
        if cos_v < opt.cos_view_min:
            return False, zero3, zero3, zero3, zero3, 0.0, 0.0
        point = opt.sampling == SAMPLING_POINT and infos[k].depth_is_mask == 0
        x0 = int(xs)
        y0 = int(ys)
        if point:
            x0 = int(xs + 0.5)
            y0 = int(ys + 0.5)
            p, nrm, tan, bit = pixel_point(infos, k, tex, i, x0, y0)
            pc = infos[k].rot @ p + infos[k].trans
            vdir = wp.normalize(infos[k].center - p)
            cos_v = wp.dot(vdir, nrm)
            if cos_v < opt.cos_view_min:
                return False, zero3, zero3, zero3, zero3, 0.0, 0.0
        wi = zero3
        e_int = wp.vec3(1.0)
        cos_i = float(1.0)
        if wp.static(not no_light):
            wi, e_int, dist = incident_light(infos[k].light_kind, infos[k].light_vec, infos[k].light_intensity, p)
            cos_i = wp.dot(wi, nrm)
            if cos_i < opt.cos_light_min:
                return False, zero3, zero3, zero3, zero3, 0.0, 0.0
        if infos[k].depth_is_mask != 0:
            if not unmasked(depth, k, xs, ys):
                return False, zero3, zero3, zero3, zero3, 0.0, 0.0
        else:
            # a tap up to ~1.5 px away (0.5 px for a point sample's own pixel) on a surface tilted by
            # theta lies (z / fx) tan(theta) deeper per pixel; without this slack small photos reject
            # every sample tilted past ~30 degrees. tan is capped at 4 (76 degrees) so silhouettes
            # still reject the background.
            tan_v = wp.min(wp.sqrt(wp.max(1.0 - cos_v * cos_v, 0.0)) / cos_v, 4.0)
            if point:
                if not depth_tap_ok(depth, k, x0, y0, pc[2], opt.depth_tol, 0.5 * pc[2] / infos[k].fx * tan_v):
                    return False, zero3, zero3, zero3, zero3, 0.0, 0.0
            else:
                if not depth_consistent(depth, k, x0, y0, pc[2], opt.depth_tol, 1.5 * pc[2] / infos[k].fx * tan_v):
                    return False, zero3, zero3, zero3, zero3, 0.0, 0.0
        if wp.static(not no_light):
            if not lit(shadow, k, infos, p, opt.shadow_tol):
                return False, zero3, zero3, zero3, zero3, 0.0, 0.0
        y = wp.vec3(0.0)
        if point:
            y = wp.vec3(images[k, y0, x0])
            if wp.max(y[0], wp.max(y[1], y[2])) >= infos[k].saturation:
                return False, zero3, zero3, zero3, zero3, 0.0, 0.0
        else:
            fx = xs - float(x0)
            fy = ys - float(y0)
            c00 = wp.vec3(images[k, y0, x0])
            c01 = wp.vec3(images[k, y0, x0 + 1])
            c10 = wp.vec3(images[k, y0 + 1, x0])
            c11 = wp.vec3(images[k, y0 + 1, x0 + 1])
            tapmax = wp.max(wp.max(c00, c01), wp.max(c10, c11))
            if wp.max(tapmax[0], wp.max(tapmax[1], tapmax[2])) >= infos[k].saturation:
                return False, zero3, zero3, zero3, zero3, 0.0, 0.0
            y = (1.0 - fy) * ((1.0 - fx) * c00 + fx * c01) + fy * ((1.0 - fx) * c10 + fx * c11)
        w = infos[k].exposure * cos_i * e_int
        if opt.sampling == SAMPLING_FILTERED and infos[k].depth_is_mask == 0:
            if wp.static(no_light):
                # the view-dependent radiance reads the texel centre's view for all four taps
                return True, y, w, zero3, to_local(vdir, tan, bit, nrm), xs, ys
            return True, y, w, zero3, zero3, xs, ys  # sample_model takes each tap's own directions
        return True, y, w, to_local(wi, tan, bit, nrm), to_local(vdir, tan, bit, nrm), xs, ys

    return observe


observe = observe_func(False)


@wp.func
def unlit_photo(infos: wp.array(dtype=ImageInfo), k: int):
    """Photo k's light is exactly 0 in every channel (taken with the flash off, capture_json.py ``no_flash``): it
    lit nothing, wherever the capture places it."""
    e = infos[k].light_intensity
    return e[0] == 0.0 and e[1] == 0.0 and e[2] == 0.0


@functools.cache
def observe_with_unlit_func():
    """:func:`observe` of the reflectance models for photos that may include unlit ones (:func:`unlit_photo`): a lit
    photo's sample is observe's, to the bit; an unlit photo's takes the camera's tests alone (the light-free observe
    of the radiance model: projection, depth or mask, grazing view, saturation), as a light that lit nothing can
    neither face away nor cast a shadow, with the weight 0 and no light direction (u = 0: the lobes see no light).
    The ambient layouts' samples (fit/kernels/accumulate.py), the initial guess and the tiles' visibility use it;
    the other kernels compile the code (and Warp hashes the source) they did."""
    lit_observe = observe_func(False)
    camera_observe = observe_func(True)

    @wp.func
    def observe_with_unlit(images: wp.array3d(dtype=Any), depth: wp.array3d(dtype=wp.float32),
                           shadow: wp.array3d(dtype=wp.float32), infos: wp.array(dtype=ImageInfo), k: int,
                           tex: TexelFrames, i: int, opt: SampleOptions):
        if unlit_photo(infos, k):
            ok, y, _w, _u, v, xs, ys = camera_observe(images, depth, shadow, infos, k, tex, i, opt)
            return ok, y, wp.vec3(0.0), wp.vec3(0.0), v, xs, ys
        return lit_observe(images, depth, shadow, infos, k, tex, i, opt)

    return observe_with_unlit


@wp.func
def to_compute3(a: wp.vec3, one: Any):
    return wp.vector(type(one)(a[0]), type(one)(a[1]), type(one)(a[2]))


@wp.func
def kahan_add(total: Any, comp: Any, term: Any):
    """Kahan-compensated ``total + term`` (seed Alg. 14), scalar or vector: (total, compensation)."""
    y = term - comp
    t = total + y
    return t, (t - total) - y


@wp.func
def trace_stats(wm: Any, fitted: Any, y: wp.vec3, c: int):
    """(1/3 sample, r^2, |r|, |y|) of channel c in radiance space, in fp64, for the trace
    (``wm`` = W_c m_c, the model's radiance, ``fitted`` what it fits, ``y`` the photo's value)."""
    rr = wp.float64(wm) - wp.float64(fitted[c])
    return wp.vec4d(wp.float64(1.0 / 3.0), rr * rr, wp.abs(rr), wp.abs(wp.float64(y[c])))


@functools.cache
def initial_guess_kernel_for(radiance: bool = False):
    """The initial-guess kernel for reflectance models (``radiance`` False, photos observed by
    :func:`observe_with_unlit_func`, as the passes of a layout with the ambient observe them) or the radiance model
    (:func:`observe_func`)."""
    obs = observe_func(True) if radiance else observe_with_unlit_func()

    def initial_guess(tex: TexelFrames, images: wp.array3d(dtype=Any),
                      depth: wp.array3d(dtype=wp.float32), shadow: wp.array3d(dtype=wp.float32),
                      infos: wp.array(dtype=ImageInfo), img_begin: int, img_end: int, opt: SampleOptions,
                      rank: int, keep_smallest: int, low: wp.array(dtype=wp.vec3), high: wp.array(dtype=wp.vec3),
                      count: wp.array(dtype=wp.int32), smallest: wp.array(dtype=wp.mat44)):
        """Per texel: the ``rank``-th smallest observed reflectance y / (exposure E cos) per channel
        (a low percentile, McAllister's diffuse estimate used by the seed; for the radiance model
        y / exposure, a low percentile of the radiance, below any highlight), the largest, and the
        number of samples. A channel of weight 0 (an unlit photo's: the flash off) counts its sample but says
        nothing of the reflectance. Windows accumulate (call with the outputs pre-filled). ``keep_smallest``
        1 also writes the 4 smallest per channel (rows: channel; ascending, 1e30 where none) to
        ``smallest``: photos split over devices merge them exactly (:func:`merge_smallest_kernel`);
        2 resumes from ``smallest`` (the earlier windows' list) and writes it back, so windows of photos
        give the one-pass values exactly."""
        i = wp.tid()
        lo = wp.mat44(0.0)  # rows: channel, columns: the 4 smallest so far, ascending
        for c in range(3):
            for j in range(4):
                lo[c, j] = 1.0e30
        if keep_smallest == 2:
            lo = smallest[i]
        hi = high[i]
        n = count[i]
        for k in range(img_begin, img_end):
            ok, y, w, u, v, xs, ys = obs(images, depth, shadow, infos, k, tex, i, opt)
            if ok:
                n = n + 1
                for c in range(3):
                    if w[c] > 0.0:
                        val = y[c] / w[c]
                        hi[c] = wp.max(hi[c], val)
                        lo = with_smallest(lo, c, val)
        if keep_smallest != 0:
            smallest[i] = lo
        est = low[i]
        for c in range(3):
            pick = rank_pick(lo, c, rank)
            if pick < 1.0e29:
                if count[i] > 0 and keep_smallest != 2:
                    est[c] = wp.min(est[c], pick)  # without the earlier windows' list: the smaller estimate
                else:
                    est[c] = pick
        low[i] = est
        high[i] = hi
        count[i] = n

    kernel = wp.kernel(initial_guess, name="initial_guess_radiance" if radiance else "initial_guess",
                       enable_backward=False, module="unique")
    declare(kernel, images=IMAGE_PIXEL)  # the default run's overload (fit/kernels/overloads.py)
    return kernel


@wp.func
def with_smallest(lo: wp.mat44, c: int, val: float):
    """``lo`` with ``val`` kept among row ``c``'s 4 smallest values (ascending; 1e30 where none yet)."""
    out = wp.mat44(lo)
    if val < out[c, 3]:
        out[c, 3] = val
        for jj in range(3):
            j = 2 - jj
            if out[c, j + 1] < out[c, j]:
                t = out[c, j]
                out[c, j] = out[c, j + 1]
                out[c, j + 1] = t
    return out


@wp.func
def rank_pick(lo: wp.mat44, c: int, rank: int):
    """The ``rank``-th (0..3) smallest of row ``c`` (ascending, 1e30 where none), or the largest there is."""
    r = wp.clamp(rank, 0, 3)
    pick = lo[c, 0]
    for j in range(4):
        if j <= r and lo[c, j] < 1.0e29:
            pick = lo[c, j]
    return pick


@wp.kernel
def merge_smallest_kernel(smallest: wp.array2d(dtype=wp.mat44), highs: wp.array2d(dtype=wp.vec3),
                          counts: wp.array2d(dtype=wp.int32), parts: int, rank: int,
                          low: wp.array(dtype=wp.vec3), high: wp.array(dtype=wp.vec3),
                          count: wp.array(dtype=wp.int32)):
    """The initial guess of photos split over devices: row d of each input is part d's
    ``initial_guess`` (4 smallest per channel, largest, count; outputs unfilled); the 4 smallest of
    the union are the 4 smallest of the parts' lists, so ``low`` is the one-pass value exactly."""
    i = wp.tid()
    lo = wp.mat44(0.0)
    for c in range(3):
        for j in range(4):
            lo[c, j] = 1.0e30
    hi = wp.vec3(0.0)
    n = int(0)
    for d in range(parts):
        part = smallest[d, i]
        n = n + counts[d, i]
        h = highs[d, i]
        for c in range(3):
            hi[c] = wp.max(hi[c], h[c])
            for k in range(4):
                lo = with_smallest(lo, c, part[c, k])
    est = wp.vec3(0.0)
    for c in range(3):
        pick = rank_pick(lo, c, rank)
        if pick < 1.0e29:
            est[c] = pick
    low[i] = est
    high[i] = hi
    count[i] = n


initial_guess_kernel = initial_guess_kernel_for(False)
