"""The image-streaming distribution step and per-texel accumulation (seed ch. 4-5, 8).

One launch covers a range of photos: thread (g, i) takes texel i and loops over photo group g,
projecting the texel, testing visibility against the photo's depth map and the light's shadow
map, sampling the photo (:func:`observe`: the nearest pixel with the model evaluated at the
surface point it sees, or the seed's bilinear filter), rejecting grazing / masked / clipped / out-of-frame /
occluded samples, and accumulating the objective, gradient and curvature terms in registers.
Each thread writes its partial sums once; :func:`reduce_partials_kernel` adds the groups in a
fixed order, so results are deterministic (no float atomics). Nothing per (texel, photo) is stored.

Keeping a GPU thread's state in registers decides the speed (benchmarks/results/h100_kernels): the
accumulation kernels are compiled per model layout and pass kind (:func:`accumulate_kernel`,
:func:`accumulate_lm_kernel`) so that no vector is indexed at run time, and the functions read a
photo's constants as ``infos[k].field`` where they use them, because a local copy of the whole
``ImageInfo`` (about 50 words) is loaded at once and stays live through the sample.

Residuals (per colour channel c, radiance-space weight w_c = exposure * E_c * cos(theta_i)):
    radiance space   : r_c = w_c m_c - y_c
    reflectance space: r_c = m_c - y_c / w_c       (the seed's choice; needs cos(theta_i) >= 0.1)
Both are r_c = s_c (m_c - y_c / w_c) with s_c = w_c or 1, so J_r = s_c J_m and
d^T H_r d = s_c d^T H_m d. The radiance model (fit/models.py) has w_c = exposure: its passes are
compiled without the light (:func:`observe_func`, ``layout_funcs(radiance=True)``).

The data term is sum rho(r_c) with rho(r) = r^2 / 2 (least squares) or a robust loss (Huber, Cauchy;
``accumulate_kernel``'s ``robust``), applied per sample as iteratively reweighted least squares.
"""

from __future__ import annotations

import functools
from typing import Any, NamedTuple

import warp as wp

from texstream.fit.kernels.lafortune_grad import lafortune_funcs, view_radiance_funcs
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
    exposure * E * cos(theta_i)); the radiance model (fit/models.py) ignores any light (no cosine or
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


ROBUST_NONE = 0
ROBUST_HUBER = 1
ROBUST_CAUCHY = 2
ROBUST_LOSSES = {"none": ROBUST_NONE, "huber": ROBUST_HUBER, "cauchy": ROBUST_CAUCHY}
"""Robust losses rho(r) of a channel residual r (``FitConfig.robust_loss``), compiled into the passes."""


@wp.func
def huber_loss(r: Any, k: Any):
    """Huber's loss with scale k: rho = r^2 / 2 for |r| <= k, k (|r| - k / 2) beyond.

    Returns (rho, rho' = psi, the IRLS weight psi / r, rho''). Convex; an outlier's influence
    psi is capped at k."""
    zero = r - r
    one = zero + type(r)(1.0)
    a = wp.abs(r)
    if a <= k:
        return type(r)(0.5) * r * r, r, one, one
    psi = k
    if r < zero:
        psi = -k
    return k * (a - type(r)(0.5) * k), psi, k / a, zero


@wp.func
def cauchy_loss(r: Any, k: Any):
    """The Cauchy (Lorentzian) loss with scale k: rho = (k^2 / 2) ln(1 + (r / k)^2).

    Returns (rho, psi = r / (1 + (r/k)^2), the IRLS weight 1 / (1 + (r/k)^2),
    rho'' = (1 - (r/k)^2) / (1 + (r/k)^2)^2). Redescending: an outlier's influence falls as k^2 / r,
    so a highlight many k above the rest pulls the fit by almost nothing; not convex (rho'' < 0
    beyond |r| = k), hence the Gauss-Newton passes use the IRLS weight, which stays positive."""
    one = type(r)(1.0)
    t = r / k
    t2 = t * t
    q = one + t2
    return type(r)(0.5) * k * k * wp.log(q), r / q, one / q, (one - t2) / (q * q)


def _robust_func(robust: int):
    """The wp.func of a robust loss kind (Huber stands in for ``ROBUST_NONE``, whose passes never call it)."""
    if int(robust) not in ROBUST_LOSSES.values():
        raise ValueError(f"unknown robust loss {robust!r}")
    return cauchy_loss if int(robust) == ROBUST_CAUCHY else huber_loss


def _robust_name(robust: int) -> str:
    return {v: k for k, v in ROBUST_LOSSES.items()}[int(robust)]


class LayoutFuncs(NamedTuple):
    """The per-sample functions of one model layout (:func:`layout_funcs`)."""

    lf: Any
    load_params: Any
    sample: Any
    channel_residual: Any
    n_params: int


@functools.cache
def layout_funcs(n_lobes: int, anisotropic: int, lookup: bool = False, traced: bool = False,
                 radiance: bool = False) -> LayoutFuncs:
    """The sample functions the accumulation kernels share, specialised to one model layout
    (loops over lobes and columns with compile-time trip counts, see ``lafortune_funcs``), to
    the model's texture lookup (``lookup``: the renderer's bilinear blend with the neighbours, see
    ``sample_model``), to the filtered taps' geometry (``traced``: each tap's ray traced to the
    mesh, :func:`traced_tap`; else the texel's face plane, :func:`ray_surface`) and to the light
    (``radiance``: 1 the radiance model, no lobes, no light, W = exposure, :func:`observe_func`; 2 the
    view-dependent radiance, the same with ``view_radiance_funcs`` of the local view direction)."""
    view = int(radiance) == 2
    lf = view_radiance_funcs() if view else lafortune_funcs(n_lobes, anisotropic)
    blend = bool(lookup)
    trace = bool(traced)
    no_light = bool(radiance)
    observe_sample = observe_func(no_light)
    n_params = 18 if view else 3 + int(n_lobes) * (6 + int(anisotropic))

    @wp.func
    def load_params(params: wp.array2d(dtype=Any), i: int, like: Any, one: Any):
        out = like * (one - one)
        for k in range(wp.static(n_params)):
            out[k] = type(one)(params[i, k])
        return out

    @wp.func
    def frame_directions(wi: wp.vec3, vdir: wp.vec3, nrm: wp.vec3, tan: wp.vec3, bit: wp.vec3):
        """Light and view directions (u, v) as the lobes see them at a surface point with normal
        ``nrm``: the local frame's components for anisotropic lobes. An isotropic lobe depends on
        u_x v_x + u_y v_y = u . v - u_z v_z and u_z v_z only, which need no tangent frame, so
        there (u . v - u_z v_z, 0, u_z) and (1, 0, v_z) stand in (``tan`` and ``bit`` unused): the
        same lobe weights for fewer registers and instructions per filtered tap."""
        if wp.static(anisotropic != 0):
            return to_local(wi, tan, bit, nrm), to_local(vdir, tan, bit, nrm)
        uz = wp.dot(wi, nrm)
        vz = wp.dot(vdir, nrm)
        return wp.vec3(wp.dot(wi, vdir) - uz * vz, 0.0, uz), wp.vec3(1.0, 0.0, vz)

    @wp.func
    def lobe_directions(wi: wp.vec3, vdir: wp.vec3, nrm: wp.vec3, tex: TexelFrames, i: int):
        """:func:`frame_directions` in texel i's tangent frame turned to the normal ``nrm`` (built
        only for anisotropic lobes)."""
        if wp.static(anisotropic != 0):
            tan, bit = tangent_frame(nrm, tex, i)
            return frame_directions(wi, vdir, nrm, tan, bit)
        return frame_directions(wi, vdir, nrm, nrm, nrm)

    @wp.func
    def sample_model(pv: Any, dv: Any, infos: wp.array(dtype=ImageInfo), k: int, tex: TexelFrames, i: int, xs: float,
                     ys: float, w: wp.vec3, u: wp.vec3, v: wp.vec3, opt: SampleOptions, want_hm: int, one: Any):
        """The model side of one sample: (usable, weight W, lobe features f, d^T (Hess M) d, offset N).

        The residual is W M + N - y (radiance space), M the model of the features f
        (``lafortune_funcs``). Bilinear and point sampling: W = w, f the texel's features at
        (u, v) and N = 0. Filtered sampling: the photo's bilinear filter applied to the model, W = sum_t
        b_t w_t and M = sum_t b_t w_t m_t / W over the four taps t (bilinear weights b_t, each
        tap's own surface point, light and view), so W M is the filtered radiance. w_t is the
        light's RGB intensity times a scalar a_t (exposure, cosine, falloff), so M = sum_t
        omega_t m_t with omega_t = b_t a_t / sum b a the same for every channel: the taps'
        features are averaged, and M and its Jacobian follow from the mean exactly.

        With the renderer's lookup (``lookup``, filtered sampling only) a tap's BRDF is
        o_t m_t + n_t, o_t the texel's own bilinear weight there and n_t its neighbours' blended
        BRDFs at their held values (:func:`texel_blend`): the taps' features are averaged
        with weights b_t a_t o_t into W M, and N = L sum_t b_t a_t n_t is a constant of the
        texel's parameters. A sample whose taps all miss the texel (o_t = 0) is not usable.

        A tap's surface point, normal (and tangent) come from the texel's face plane
        (:func:`ray_surface`, the interpolated normal extended to first order, texel coordinates
        extended linearly: no mesh access) or, with ``traced``, from the tap's pixel ray traced to
        the mesh (:func:`traced_tap`: the point, frame, UV and cast shadow the renderer sees, so a
        tap that leaves the texel's face, e.g. on curved or coarse geometry, lands where the photo's
        pixel looks).

        The radiance model (``radiance``) has no light: w_t = b_t exposure (times 1 or 0 for a
        traced tap that hits the mesh or misses, :func:`traced_texel`), W = sum_t w_t and N the
        neighbours' blended radiance sum_t w_t n_t.
        """
        uc = to_compute3(u, one)
        vc = to_compute3(v, one)
        zero = one - one
        if opt.sampling != SAMPLING_FILTERED or infos[k].depth_is_mask != 0:
            hm = type(uc)(zero, zero, zero)
            if want_hm != 0:
                hm = lf.dhd(pv, dv, uc, vc, one)
            return True, to_compute3(w, one), lf.features(pv, uc, vc, one), hm, wp.vec3(0.0)
        x0 = int(xs)
        y0 = int(ys)
        fx = xs - float(x0)
        fy = ys - float(y0)
        asum = float(0.0)
        nsum = wp.vec3(0.0)
        feat = pv * zero
        hsum = type(uc)(zero, zero, zero)
        # a run-time trip count (4 here): Warp unrolls loops over literal ranges, and four inlined
        # copies of the tap (lobe features, optionally d^T H d) made the CPU kernels compile 30% slower
        n_taps = opt.sampling + 2
        # the texel's geometry and the photo's constants are read once per sample, not per tap
        p0 = tex.pos[i]
        ng = tex.face_nrm[i]
        n0 = tex.nrm[i]
        jn = tex.dn_dp[i]
        cam = infos[k].center
        rt = wp.transpose(infos[k].rot)
        ifx = 1.0 / infos[k].fx
        ify = 1.0 / infos[k].fy
        px0 = float(x0) + 0.5 - infos[k].cx
        py0 = float(y0) + 0.5 - infos[k].cy
        light_kind = infos[k].light_kind
        light_vec = infos[k].light_vec
        exposure = infos[k].exposure
        plane = wp.dot(p0 - cam, ng)
        shadows = tex.shadow_rays
        for t in range(n_taps):
            dx = t % 2
            dy = t // 2
            b = (fx * float(dx) + (1.0 - fx) * float(1 - dx)) * (fy * float(dy) + (1.0 - fy) * float(1 - dy))
            ray = rt @ wp.vec3((px0 + float(dx)) * ifx, (py0 + float(dy)) * ify, 1.0)
            a = float(0.0)
            ul = wp.vec3(0.0)
            vl = wp.vec3(0.0)
            tx = float(0.0)
            ty = float(0.0)
            if wp.static(no_light):
                # the radiance model: W M = sum_t b_t exposure L_t, no light, cosine or shadow; the
                # view-dependent one sees every tap from the texel centre's view v (observe)
                a = b * exposure
                vl = v
                if wp.static(trace):
                    hit, tx, ty = traced_texel(tex, cam, ray)
                    a = a * hit
                elif wp.static(blend):
                    p, nrm = ray_surface(ray, cam, p0, ng, plane, n0, jn)
                    tx, ty = plane_texel_coords(tex, i, p)
            elif wp.static(trace):
                at, wi, p, nrm, tg, bt, tx, ty = traced_tap(tex, cam, ray, light_kind, light_vec, shadows)
                a = b * exposure * at
                ul, vl = frame_directions(wi, wp.normalize(cam - p), nrm, tg, bt)
            else:
                p, nrm = ray_surface(ray, cam, p0, ng, plane, n0, jn)
                wi, falloff, dist = incident_light(light_kind, light_vec, wp.vec3(1.0), p)
                a = b * exposure * wp.max(wp.dot(wi, nrm), 0.0) * falloff[0]
                ul, vl = lobe_directions(wi, wp.normalize(cam - p), nrm, tex, i)
                if wp.static(blend):
                    tx, ty = plane_texel_coords(tex, i, p)
            ut = to_compute3(ul, one)
            vt = to_compute3(vl, one)
            if wp.static(blend):
                own, other = texel_blend(tex, i, tx, ty, ul, vl)
                nsum = nsum + a * other
                a = a * own
            ac = type(one)(a)
            feat = feat + ac * lf.features(pv, ut, vt, one)
            if want_hm != 0:
                hsum = hsum + ac * lf.dhd(pv, dv, ut, vt, one)
            asum = asum + a
        # every tap unlit (or, with the lookup, off the texel): W = 0, not usable
        inv = one / type(one)(wp.max(asum, 1.0e-30))
        offset = wp.vec3(0.0)
        if wp.static(no_light):
            if wp.static(blend):
                offset = nsum
            return asum > 0.0, to_compute3(wp.vec3(asum), one), feat * inv, hsum * inv, offset
        if wp.static(blend):
            offset = wp.cw_mul(infos[k].light_intensity, nsum)
        return asum > 0.0, to_compute3(infos[k].light_intensity * asum, one), feat * inv, hsum * inv, offset

    @wp.func
    def sample(pv: Any, dv: Any, images: wp.array3d(dtype=Any), depth: wp.array3d(dtype=wp.float32),
               shadow: wp.array3d(dtype=wp.float32), infos: wp.array(dtype=ImageInfo), k: int, tex: TexelFrames,
               i: int, opt: SampleOptions, want_hm: int, one: Any):
        """One (texel i, photo k) sample, :func:`observe` then :func:`sample_model`: (usable, W, f,
        d^T (Hess M) d, the radiance W M fits, the photo's radiance y). With the lookup the model
        fits y minus the neighbours' held share N; else y itself."""
        ok, y, w, u, v, xs, ys = observe_sample(images, depth, shadow, infos, k, tex, i, opt)
        zero = one - one
        use = False
        wc = to_compute3(w, one)
        feat = pv * zero
        hm = wc * zero
        offset = wp.vec3(0.0)
        if ok:
            use, wc, feat, hm, offset = sample_model(pv, dv, infos, k, tex, i, xs, ys, w, u, v, opt, want_hm, one)
        fitted = y
        if wp.static(blend):
            fitted = y - offset
        return use, wc, feat, hm, to_compute3(fitted, one), y

    @wp.func
    def channel_residual(pv: Any, feat: Any, yc: Any, wc: Any, c: int, reflectance_space: int, one: Any):
        """Model m_c, residual r_c and its scale s_c (see the module doc) of channel c."""
        m = lf.model_value(pv, feat, c)
        s = one
        r = m - yc[c] / wc[c]
        if reflectance_space == 0:
            s = wc[c]
            r = wc[c] * m - yc[c]
        return m, r, s

    return LayoutFuncs(lf, load_params, sample, channel_residual, n_params)


@functools.cache
def accumulate_kernel(n_lobes: int, anisotropic: int, kahan: bool, diag: bool, dhd: bool, full_hessian: bool,
                      max_registers: int = 0, lookup: bool = False, traced: bool = False, radiance: bool = False,
                      robust: int = ROBUST_NONE):
    """The objective / gradient pass of one model layout and pass kind.

    What a pass accumulates beside f and the gradient is fixed when the kernel compiles rather
    than tested per sample, so a pass carries no registers for what it does not compute:
    ``kahan`` (compensated sums), ``diag`` (the Gauss-Newton diagonal), ``dhd`` (d^T H d along
    ``direction``) and ``full_hessian`` (its r d^T (Hess r) d term). The Jacobian rows are built
    with literal indices (``LafortuneFuncs.jacobian_row``), so they stay in registers.
    ``max_registers`` caps registers per CUDA thread (0: none); ``lookup`` selects the renderer's
    texture lookup, ``traced`` the traced tap geometry and ``radiance`` the light-free radiance
    model (``layout_funcs``). Each kernel lives in a module of its own, so compiling one does not
    recompile the others.

    ``robust`` (``ROBUST_LOSSES``) replaces each channel's r^2 / 2 by a robust loss rho(r) of scale
    ``opt.robust_scale``, as iteratively reweighted least squares: objective rho(r), gradient
    rho'(r) s J, Gauss-Newton curvature w(r) (s J d)^2 with the IRLS weight w = rho'(r) / r (also in
    the Jacobi diagonal), and the full d^T H d rho''(r) (s J d)^2 + rho'(r) s d^T (Hess m) d, the
    exact second derivative. The weights follow the current residuals in every pass (no host
    round trip); ``ROBUST_NONE`` compiles the least-squares pass unchanged.
    """
    fn = layout_funcs(n_lobes, anisotropic, lookup, traced, radiance)
    lf, load_params, sample, channel_residual = fn.lf, fn.load_params, fn.sample, fn.channel_residual
    use_kahan, want_diag, want_dhd, want_full = bool(kahan), bool(diag), bool(dhd), bool(dhd and full_hessian)
    robust_on = int(robust) != ROBUST_NONE
    robust_fn = _robust_func(robust)

    def accumulate(
        tex: TexelFrames, params: wp.array2d(dtype=Any), direction: wp.array2d(dtype=Any),
        active: wp.array(dtype=wp.int32),
        images: wp.array3d(dtype=Any), depth: wp.array3d(dtype=wp.float32),
        shadow: wp.array3d(dtype=wp.float32), infos: wp.array(dtype=ImageInfo),
        img_begin: int, img_end: int, per_group: int, opt: SampleOptions, like: Any, one: Any,
        out_f: wp.array2d(dtype=Any), out_g: wp.array2d(dtype=Any), out_dhd: wp.array2d(dtype=Any),
        out_stats: wp.array2d(dtype=wp.vec4d), out_diag: wp.array2d(dtype=Any)):
        """Partial objective, gradient and d^T H d of texel i over photo group g (see module doc).

        out_stats holds (samples, sum r_radiance^2, sum |r_radiance|, sum |y|) for the trace.
        out_diag (written only by ``diag`` kernels) holds the Gauss-Newton diagonal
        sum over samples and channels of (s_c dm_c/dp_k)^2, i.e. diag(J_r^T J_r).
        """
        g, i = wp.tid()
        zero = one - one
        f = zero
        fc = zero
        grad = like * zero
        gc = like * zero
        dhd = zero
        diag = like * zero
        st = wp.vec4d(0.0)
        if active[i] != 0:
            pv = load_params(params, i, like, one)
            dv = like * zero
            if wp.static(want_dhd):
                dv = load_params(direction, i, like, one)
            k0 = img_begin + g * per_group
            k1 = wp.min(k0 + per_group, img_end)
            scale = type(one)(opt.robust_scale)
            for k in range(k0, k1):
                use, wc, feat, hm, yc, y = sample(pv, dv, images, depth, shadow, infos, k, tex, i, opt,
                                                  wp.static(int(want_full)), one)
                if use:
                    for c in range(3):
                        m, r, s = channel_residual(pv, feat, yc, wc, c, opt.reflectance_space, one)
                        term = type(one)(0.5) * r * r
                        psi = r
                        wgt = one
                        curv = one
                        if wp.static(robust_on):
                            term, psi, wgt, curv = robust_fn(r, scale)
                        if wp.static(use_kahan):
                            f, fc = kahan_add(f, fc, term)
                        else:
                            f = f + term
                        jc = lf.jacobian_row(pv, feat, c)
                        gterm = (psi * s) * jc
                        if wp.static(use_kahan):
                            grad, gc = kahan_add(grad, gc, gterm)
                        else:
                            grad = grad + gterm
                        if wp.static(want_diag):
                            sj = s * jc
                            if wp.static(robust_on):
                                diag = diag + wgt * wp.cw_mul(sj, sj)
                            else:
                                diag = diag + wp.cw_mul(sj, sj)
                        if wp.static(want_dhd):
                            jd = s * wp.dot(jc, dv)
                            if wp.static(not robust_on):
                                dhd = dhd + jd * jd
                                if wp.static(want_full):
                                    dhd = dhd + r * s * hm[c]
                            elif wp.static(want_full):
                                dhd = dhd + curv * jd * jd + psi * s * hm[c]
                            else:
                                dhd = dhd + wgt * jd * jd
                        st = st + trace_stats(wc[c] * m, yc, y, c)
        out_f[g, i] = f
        out_g[g, i] = grad
        out_dhd[g, i] = dhd
        out_stats[g, i] = st
        if wp.static(want_diag):
            out_diag[g, i] = diag

    name = "_".join(["accumulate", f"{int(n_lobes)}lobes", "aniso" if anisotropic else "iso"]
                    + [flag for flag, on in (("kahan", use_kahan), ("diag", want_diag), ("dhd", want_dhd),
                                             ("full", want_full), ("lookup", bool(lookup)),
                                             ("traced", bool(traced)), ("radiance", bool(radiance)),
                                             ("view", int(radiance) == 2)) if on]
                    + ([_robust_name(robust)] if robust_on else []))
    if max_registers:
        name += f"_maxreg{max_registers}"
    return wp.kernel(accumulate, name=name, enable_backward=False, module="unique",
                     cuda_max_registers=max_registers or None)


@functools.cache
def accumulate_lm_kernel(n_lobes: int, anisotropic: int, max_registers: int = 0, lookup: bool = False,
                         traced: bool = False, radiance: bool = False, robust: int = ROBUST_NONE):
    """The Gauss-Newton / LM pass of one model layout: f, J^T r and J^T J per (photo group, texel).

    J^T J is summed over the structurally non-zero entries of each channel's Jacobian row only
    (``LafortuneFuncs.row_entry``; 33 of the 81 entries of one isotropic lobe) into its upper
    triangle and mirrored once at the end, so the sums stay in registers on a GPU.

    ``robust``: the robust loss as in :func:`accumulate_kernel`, f = sum rho(r), J^T psi(r) and
    J^T W J with the IRLS weights W = psi(r) / r (iteratively reweighted least squares: every
    pass reweights at its own point).
    """
    fn = layout_funcs(n_lobes, anisotropic, lookup, traced, radiance)
    lf, load_params, sample, channel_residual = fn.lf, fn.load_params, fn.sample, fn.channel_residual
    n_params = fn.n_params
    row_nonzeros = lf.row_nonzeros
    robust_on = int(robust) != ROBUST_NONE
    robust_fn = _robust_func(robust)

    def accumulate_lm(
        tex: TexelFrames, params: wp.array2d(dtype=Any),
        active: wp.array(dtype=wp.int32),
        images: wp.array3d(dtype=Any), depth: wp.array3d(dtype=wp.float32),
        shadow: wp.array3d(dtype=wp.float32), infos: wp.array(dtype=ImageInfo),
        img_begin: int, img_end: int, per_group: int, opt: SampleOptions, like: Any, like_m: Any, one: Any,
        out_f: wp.array2d(dtype=Any), out_g: wp.array2d(dtype=Any), out_jtj: wp.array2d(dtype=Any),
        out_stats: wp.array2d(dtype=wp.vec4d)):
        """Partial objective, J^T r and J^T J of texel i over photo group g (Gauss-Newton / LM).

        J^T J is summed over the structurally non-zero entries of each channel's Jacobian row
        into its upper triangle, then mirrored once (``LafortuneFuncs.row_entry``)."""
        g, i = wp.tid()
        zero = one - one
        f = zero
        grad = like * zero
        upper = like_m * zero
        st = wp.vec4d(0.0)
        if active[i] != 0:
            pv = load_params(params, i, like, one)
            k0 = img_begin + g * per_group
            k1 = wp.min(k0 + per_group, img_end)
            scale = type(one)(opt.robust_scale)
            for k in range(k0, k1):
                use, wc, feat, hm, yc, y = sample(pv, pv, images, depth, shadow, infos, k, tex, i, opt, 0, one)
                if use:
                    for c in range(3):
                        m, r, s = channel_residual(pv, feat, yc, wc, c, opt.reflectance_space, one)
                        term = type(one)(0.5) * r * r
                        rs = r * s
                        s2 = s * s
                        if wp.static(robust_on):
                            term, psi, wgt, curv = robust_fn(r, scale)
                            rs = psi * s
                            s2 = wgt * s2
                        f = f + term
                        for ta in range(wp.static(row_nonzeros)):
                            ca, va = lf.row_entry(pv, feat, c, ta)
                            grad[ca] = grad[ca] + rs * va
                            for tb in range(wp.static(row_nonzeros)):
                                if tb >= ta:
                                    cb, vb = lf.row_entry(pv, feat, c, tb)
                                    upper[wp.min(ca, cb), wp.max(ca, cb)] = upper[wp.min(ca, cb), wp.max(ca, cb)] + s2 * va * vb
                        st = st + trace_stats(wc[c] * m, yc, y, c)
        jtj = upper + wp.transpose(upper)
        for k in range(wp.static(n_params)):
            jtj[k, k] = upper[k, k]
        out_f[g, i] = f
        out_g[g, i] = grad
        out_jtj[g, i] = jtj
        out_stats[g, i] = st

    name = "_".join(["accumulate_lm", f"{int(n_lobes)}lobes", "aniso" if anisotropic else "iso"]
                    + (["lookup"] if lookup else []) + (["traced"] if traced else [])
                    + (["radiance"] if radiance else []) + (["view"] if int(radiance) == 2 else [])
                    + ([_robust_name(robust)] if robust_on else []))
    if max_registers:
        name += f"_maxreg{max_registers}"
    return wp.kernel(accumulate_lm, name=name, enable_backward=False, module="unique",
                     cuda_max_registers=max_registers or None)


@wp.kernel
def hold_lookup_params_kernel(params: wp.array2d(dtype=Any), relaxation: float, held: wp.array2d(dtype=wp.float32)):
    """``held[i, k] += relaxation * (params[i, k] - held[i, k])`` in float32 (1: ``held = params``):
    the values the renderer's lookup reads for texel i's neighbours until the next refresh (rows
    past the parameters, the defaults, untouched)."""
    i, k = wp.tid()
    h = held[i, k]
    held[i, k] = h + relaxation * (wp.float32(params[i, k]) - h)


@wp.kernel
def reduce_partials_kernel(pf: wp.array2d(dtype=Any), pg: wp.array2d(dtype=Any), ph: wp.array2d(dtype=Any),
                           pst: wp.array2d(dtype=wp.vec4d), n_groups: int, accumulate: int,
                           f: wp.array(dtype=Any), g: wp.array(dtype=Any), h: wp.array(dtype=Any),
                           st: wp.array(dtype=wp.vec4d)):
    """Sum the photo groups of each texel in a fixed order; ``accumulate`` adds to the outputs
    (used when photos stream through in several chunks)."""
    i = wp.tid()
    a = pf[0, i]
    b = pg[0, i]
    c = ph[0, i]
    s = pst[0, i]
    for k in range(1, n_groups):
        a = a + pf[k, i]
        b = b + pg[k, i]
        c = c + ph[k, i]
        s = s + pst[k, i]
    if accumulate != 0:
        a = a + f[i]
        b = b + g[i]
        c = c + h[i]
        s = s + st[i]
    f[i] = a
    g[i] = b
    h[i] = c
    st[i] = s


@wp.kernel
def reduce_vec_partials_kernel(pv: wp.array2d(dtype=Any), n_groups: int, accumulate: int, v: wp.array(dtype=Any)):
    """Sum one per-group vector output (the Gauss-Newton diagonal) over groups in a fixed order,
    like :func:`reduce_partials_kernel`; a separate launch so passes without it read nothing."""
    i = wp.tid()
    a = pv[0, i]
    for k in range(1, n_groups):
        a = a + pv[k, i]
    if accumulate != 0:
        a = a + v[i]
    v[i] = a


@functools.cache
def initial_guess_kernel_for(radiance: bool = False):
    """The initial-guess kernel for reflectance models (``radiance`` False) or the radiance model
    (:func:`observe_func`)."""
    obs = observe_func(bool(radiance))

    def initial_guess(tex: TexelFrames, images: wp.array3d(dtype=Any),
                      depth: wp.array3d(dtype=wp.float32), shadow: wp.array3d(dtype=wp.float32),
                      infos: wp.array(dtype=ImageInfo), img_begin: int, img_end: int, opt: SampleOptions,
                      rank: int, keep_smallest: int, low: wp.array(dtype=wp.vec3), high: wp.array(dtype=wp.vec3),
                      count: wp.array(dtype=wp.int32), smallest: wp.array(dtype=wp.mat44)):
        """Per texel: the ``rank``-th smallest observed reflectance y / (exposure E cos) per channel
        (a low percentile, McAllister's diffuse estimate used by the seed; for the radiance model
        y / exposure, a low percentile of the radiance, below any highlight), the largest, and the
        number of samples. Windows accumulate (call with the outputs pre-filled). ``keep_smallest``
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

    return wp.kernel(initial_guess, name="initial_guess_radiance" if radiance else "initial_guess",
                     enable_backward=False, module="unique")


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
