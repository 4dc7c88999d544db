"""The image-streaming distribution step and per-texel accumulation (seed ch. 4-5, 8).

One launch covers a range of photos: thread (g, i) takes texel i and loops over photo group g,
projecting the texel, testing visibility against the photo's depth map and the light's shadow
map, sampling the photo (:func:`observe`: the nearest pixel with the model evaluated at the
surface point it sees, or the seed's bilinear filter), rejecting grazing / masked / clipped / out-of-frame /
occluded samples, and accumulating the objective, gradient and curvature terms in registers.
Each thread writes its partial sums once; :func:`reduce_partials_kernel` adds the groups in a
fixed order, so results are deterministic (no float atomics). Nothing per (texel, photo) is stored.

Residuals (per colour channel c, radiance-space weight w_c = exposure * E_c * cos(theta_i)):
    radiance space   : r_c = w_c m_c - y_c
    reflectance space: r_c = m_c - y_c / w_c       (the seed's choice; needs cos(theta_i) >= 0.1)
Both are r_c = s_c (m_c - y_c / w_c) with s_c = w_c or 1, so J_r = s_c J_m and
d^T H_r d = s_c d^T H_m d.
"""

from __future__ import annotations

from typing import Any

import warp as wp

from .lafortune_grad import lafortune_dhd, lafortune_eval, lobe_features, model_from_features
from .shading import incident_light, to_local

# no kernel here is differentiated (the fit writes its own derivatives): skipping Warp's adjoint
# code generation roughly halves compile time
wp.set_module_options({"enable_backward": False})


@wp.struct
class ImageInfo:
    """Per-photo camera, light and photometric constants (float32, world units)."""

    rot: wp.mat33
    trans: wp.vec3
    center: wp.vec3
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    exposure: float
    saturation: float
    light_kind: int
    light_vec: wp.vec3
    light_intensity: wp.vec3
    has_shadow: int
    sh_rot: wp.mat33
    sh_trans: wp.vec3
    sh_fx: float
    sh_fy: float
    sh_cx: float
    sh_cy: float
    sh_ortho: int
    sh_size: int
    depth_is_mask: int
    """1: the photo has no geometry (single-view fits, fit/photometric_stereo.py); its depth map
    holds 1 where the photo may be sampled and 0 where masked, and the depth test becomes a mask
    test at the nearest pixel. 0 (the default of a zeroed struct): the depth test above."""


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


@wp.struct
class SampleOptions:
    """Rejection thresholds and what to accumulate (see FitConfig for the meaning)."""

    cos_light_min: float
    cos_view_min: float
    depth_tol: float
    shadow_tol: float
    reflectance_space: int
    want_grad: int
    want_dhd: int
    full_hessian: int
    kahan: int
    sampling: int
    """SAMPLING_BILINEAR (0), SAMPLING_POINT (1) or SAMPLING_FILTERED (2): how a texel samples a
    photo (see :func:`observe`)."""
    want_diag: int
    """1: also accumulate the Gauss-Newton diagonal D_k = sum (s_c J_c,k)^2 into ``out_diag``
    (the Jacobi preconditioner of CG / L-BFGS); 0 (the default of a zeroed struct): ``out_diag``
    is not touched, so passes that do not need it pay nothing but a branch."""


@wp.func
def depth_consistent(depth: wp.array3d(dtype=wp.float32), k: int, x0: int, y0: int, z: float, tol: float,
                     slack: float):
    """All four bilinear taps see this surface (masked or empty pixels hold 0 and fail).

    A tap may differ from the texel's depth by ``tol * z`` plus ``slack``, the depth change a tilted
    surface shows across the bilinear footprint (see :func:`observe`)."""
    ok = True
    for dy in range(2):
        for dx in range(2):
            dz = depth[k, y0 + dy, x0 + dx]
            if wp.abs(dz - z) > tol * z + slack:
                ok = False
    return ok


@wp.func
def unmasked(depth: wp.array3d(dtype=wp.float32), k: int, xs: float, ys: float):
    """Mask-only visibility (``ImageInfo.depth_is_mask``): the pixel nearest (xs, ys) is not masked.

    Nearest, not all four taps: single-view texels sit on pixel centres, where float rounding may
    pick a neighbour as the first bilinear tap with a weight of ~1e-6."""
    return depth[k, int(ys + 0.5), int(xs + 0.5)] > 0.0


@wp.func
def lit(shadow: wp.array3d(dtype=wp.float32), k: int, info: ImageInfo, p: wp.vec3, tol: float):
    """Point ``p`` is lit when no shadow-map tap around its projection is closer to the light."""
    if info.has_shadow == 0:
        return True
    pl = info.sh_rot @ p + info.sh_trans
    if pl[2] <= 0.0:
        return False
    sx = 0.0
    sy = 0.0
    if info.sh_ortho != 0:
        sx = info.sh_fx * pl[0] + info.sh_cx - 0.5
        sy = info.sh_fy * pl[1] + info.sh_cy - 0.5
    else:
        sx = info.sh_fx * pl[0] / pl[2] + info.sh_cx - 0.5
        sy = info.sh_fy * pl[1] / pl[2] + info.sh_cy - 0.5
    if sx < 0.0 or sy < 0.0 or sx >= float(info.sh_size - 1) or sy >= float(info.sh_size - 1):
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
def pixel_point(info: ImageInfo, tex: TexelFrames, i: int, x: int, y: int):
    """Where pixel (x, y)'s centre ray meets texel i's face plane: (point, shading normal, tangent,
    bitangent). The normal is the interpolated vertex normal there (``dn_dp``), as the renderer's
    :func:`surface_frame` gives it; a ray nearly parallel to the plane keeps the texel's frame."""
    p = tex.pos[i]
    ray = wp.transpose(info.rot) @ wp.vec3((float(x) + 0.5 - info.cx) / info.fx, (float(y) + 0.5 - info.cy) / info.fy, 1.0)
    ng = tex.face_nrm[i]
    den = wp.dot(ray, ng)
    if wp.abs(den) <= 1.0e-3 * wp.length(ray):
        return p, tex.nrm[i], tex.tan[i], tex.bit[i]
    q = info.center + ray * (wp.dot(p - info.center, ng) / den)
    nrm = wp.normalize(tex.nrm[i] + tex.dn_dp[i] @ (q - p))
    tan = wp.normalize(tex.tan[i] - nrm * wp.dot(nrm, tex.tan[i]))
    return q, nrm, tan, wp.cross(nrm, tan)


@wp.func
def observe(images: wp.array3d(dtype=Any), depth: wp.array3d(dtype=wp.float32),
            shadow: wp.array3d(dtype=wp.float32), info: ImageInfo, k: int,
            tex: TexelFrames, i: int, opt: SampleOptions):
    """The distribution step for one (texel i, photo k).

    Returns (ok, radiance y, weight w, local light u, local view v, xs, ys): the photo's value,
    exposure * E * cos(theta_i) and the local directions at the texel centre (at the pixel's
    surface point for point sampling), and the centre's continuous pixel coordinates (pixel
    centres at integers), which :func:`sample_model` needs for filtered sampling.

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
    pc = info.rot @ p + info.trans
    if pc[2] <= 0.0:
        return False, zero3, zero3, zero3, zero3, 0.0, 0.0
    xs = info.fx * pc[0] / pc[2] + info.cx - 0.5
    ys = info.fy * pc[1] / pc[2] + info.cy - 0.5
    if xs < 0.0 or ys < 0.0 or xs >= float(info.width - 1) or ys >= float(info.height - 1):
        return False, zero3, zero3, zero3, zero3, 0.0, 0.0
    vdir = wp.normalize(info.center - p)
    cos_v = wp.dot(vdir, nrm)
    if cos_v < opt.cos_view_min:
        return False, zero3, zero3, zero3, zero3, 0.0, 0.0
    point = opt.sampling == SAMPLING_POINT and info.depth_is_mask == 0
    x0 = int(xs)
    y0 = int(ys)
    if point:
        x0 = int(xs + 0.5)
        y0 = int(ys + 0.5)
        p, nrm, tan, bit = pixel_point(info, tex, i, x0, y0)
        pc = info.rot @ p + info.trans
        vdir = wp.normalize(info.center - p)
        cos_v = wp.dot(vdir, nrm)
        if cos_v < opt.cos_view_min:
            return False, zero3, zero3, zero3, zero3, 0.0, 0.0
    wi, e_int, dist = incident_light(info.light_kind, info.light_vec, info.light_intensity, p)
    cos_i = wp.dot(wi, nrm)
    if cos_i < opt.cos_light_min:
        return False, zero3, zero3, zero3, zero3, 0.0, 0.0
    if info.depth_is_mask != 0:
        if not unmasked(depth, k, xs, ys):
            return False, zero3, zero3, zero3, zero3, 0.0, 0.0
    else:
        # a tap up to ~1.5 px away (0.5 px for a point sample's own pixel) on a surface tilted by
        # theta lies (z / fx) tan(theta) deeper per pixel; without this slack small photos reject
        # every sample tilted past ~30 degrees. tan is capped at 4 (76 degrees) so silhouettes
        # still reject the background.
        tan_v = wp.min(wp.sqrt(wp.max(1.0 - cos_v * cos_v, 0.0)) / cos_v, 4.0)
        if point:
            if not depth_tap_ok(depth, k, x0, y0, pc[2], opt.depth_tol, 0.5 * pc[2] / info.fx * tan_v):
                return False, zero3, zero3, zero3, zero3, 0.0, 0.0
        else:
            if not depth_consistent(depth, k, x0, y0, pc[2], opt.depth_tol, 1.5 * pc[2] / info.fx * tan_v):
                return False, zero3, zero3, zero3, zero3, 0.0, 0.0
    if not lit(shadow, k, info, p, opt.shadow_tol):
        return False, zero3, zero3, zero3, zero3, 0.0, 0.0
    y = wp.vec3(0.0)
    if point:
        y = wp.vec3(images[k, y0, x0])
        if wp.max(y[0], wp.max(y[1], y[2])) >= info.saturation:
            return False, zero3, zero3, zero3, zero3, 0.0, 0.0
    else:
        fx = xs - float(x0)
        fy = ys - float(y0)
        c00 = wp.vec3(images[k, y0, x0])
        c01 = wp.vec3(images[k, y0, x0 + 1])
        c10 = wp.vec3(images[k, y0 + 1, x0])
        c11 = wp.vec3(images[k, y0 + 1, x0 + 1])
        tapmax = wp.max(wp.max(c00, c01), wp.max(c10, c11))
        if wp.max(tapmax[0], wp.max(tapmax[1], tapmax[2])) >= info.saturation:
            return False, zero3, zero3, zero3, zero3, 0.0, 0.0
        y = (1.0 - fy) * ((1.0 - fx) * c00 + fx * c01) + fy * ((1.0 - fx) * c10 + fx * c11)
    w = info.exposure * cos_i * e_int
    return True, y, w, to_local(wi, tan, bit, nrm), to_local(vdir, tan, bit, nrm), xs, ys


@wp.func
def sample_model(pv: Any, dv: Any, n_lobes: int, aniso: int, want_hm: int, info: ImageInfo, tex: TexelFrames,
                 i: int, xs: float, ys: float, w: wp.vec3, u: wp.vec3, v: wp.vec3, opt: SampleOptions, one: Any):
    """The model side of one sample: (weight W, model M, dM/dp per channel, d^T (Hess M) d).

    The residual is W M - y (radiance space). Bilinear and point sampling: W = w and M the
    texel's BRDF at (u, v). Filtered sampling: the photo's bilinear filter applied to the model,
    W = sum_t b_t w_t and M = sum_t b_t w_t m_t / W over the four taps t (bilinear weights b_t,
    each tap's own surface point, light and view), so W M is the filtered radiance. w_t is the
    light's RGB intensity times a scalar a_t (exposure, cosine, falloff), so M = sum_t omega_t m_t
    with omega_t = b_t a_t / sum b a the same for every channel: the taps' lobe features are
    averaged (:func:`lobe_features`) and M and its Jacobian assembled once, exactly.
    """
    uc = to_compute3(u, one)
    vc = to_compute3(v, one)
    zero = one - one
    if opt.sampling != SAMPLING_FILTERED or info.depth_is_mask != 0:
        m, jr, jg, jb = lafortune_eval(pv, n_lobes, aniso, uc, vc, one)
        hm = type(uc)(zero, zero, zero)
        if want_hm != 0:
            hm = lafortune_dhd(pv, dv, n_lobes, aniso, uc, vc, one)
        return to_compute3(w, one), m, jr, jg, jb, hm
    x0 = int(xs)
    y0 = int(ys)
    fx = xs - float(x0)
    fy = ys - float(y0)
    asum = float(0.0)
    feat = pv * zero
    hsum = type(uc)(zero, zero, zero)
    # a run-time trip count (4 here): Warp unrolls loops over literal ranges, and four inlined
    # copies of the tap (lobe features, optionally d^T H d) made the CPU kernels compile 30% slower
    n_taps = opt.sampling + 2
    for t in range(n_taps):
        dx = t % 2
        dy = t // 2
        b = (fx * float(dx) + (1.0 - fx) * float(1 - dx)) * (fy * float(dy) + (1.0 - fy) * float(1 - dy))
        p, nrm, tan, bit = pixel_point(info, tex, i, x0 + dx, y0 + dy)
        wi, falloff, dist = incident_light(info.light_kind, info.light_vec, wp.vec3(1.0), p)
        a = b * info.exposure * wp.max(wp.dot(wi, nrm), 0.0) * falloff[0]
        ut = to_compute3(to_local(wi, tan, bit, nrm), one)
        vt = to_compute3(to_local(wp.normalize(info.center - p), tan, bit, nrm), one)
        ac = type(one)(a)
        feat = feat + ac * lobe_features(pv, n_lobes, aniso, ut, vt, one)
        if want_hm != 0:
            hsum = hsum + ac * lafortune_dhd(pv, dv, n_lobes, aniso, ut, vt, one)
        asum = asum + a
    inv = one / type(one)(wp.max(asum, 1.0e-30))  # every tap unlit: M = the diffuse part, W = 0
    m, jr, jg, jb = model_from_features(pv, feat * inv, n_lobes, aniso, one)
    return to_compute3(info.light_intensity * asum, one), m, jr, jg, jb, hsum * inv


@wp.func
def to_compute3(a: wp.vec3, one: Any):
    return wp.vector(type(one)(a[0]), type(one)(a[1]), type(one)(a[2]))


@wp.func
def load_params(params: wp.array2d(dtype=Any), i: int, n_params: int, like: Any, one: Any):
    out = like * (one - one)
    for k in range(n_params):
        out[k] = type(one)(params[i, k])
    return out


@wp.func
def channel_residual(m: Any, yc: Any, wc: Any, jr: Any, jg: Any, jb: Any, c: int, reflectance_space: int, one: Any):
    """Residual r_c, its scale s_c (see the module doc) and the model's Jacobian row of channel c."""
    s = one
    r = m[c] - yc[c] / wc[c]
    if reflectance_space == 0:
        s = wc[c]
        r = wc[c] * m[c] - yc[c]
    jc = jr
    if c == 1:
        jc = jg
    if c == 2:
        jc = jb
    return r, s, jc


@wp.func
def trace_stats(w: Any, m: Any, y: wp.vec3, c: int):
    """(1/3 sample, r^2, |r|, |y|) of channel c in radiance space, in fp64, for the trace."""
    rr = wp.float64(w[c]) * wp.float64(m[c]) - wp.float64(y[c])
    return wp.vec4d(wp.float64(1.0 / 3.0), rr * rr, wp.abs(rr), wp.abs(wp.float64(y[c])))


@wp.kernel
def accumulate_kernel(
    tex: TexelFrames, params: wp.array2d(dtype=Any), direction: wp.array2d(dtype=Any),
    active: wp.array(dtype=wp.int32), n_params: int, n_lobes: int, aniso: int,
    images: wp.array3d(dtype=Any), depth: wp.array3d(dtype=wp.float32),
    shadow: wp.array3d(dtype=wp.float32), infos: wp.array(dtype=ImageInfo),
    img_begin: int, img_end: int, per_group: int, opt: SampleOptions, like: Any, one: Any,
    out_f: wp.array2d(dtype=Any), out_g: wp.array2d(dtype=Any), out_dhd: wp.array2d(dtype=Any),
    out_stats: wp.array2d(dtype=wp.vec4d), out_diag: wp.array2d(dtype=Any)):
    """Partial objective, gradient and d^T H d of texel i over photo group g (see module doc).

    out_stats holds (samples, sum r_radiance^2, sum |r_radiance|, sum |y|) for the trace.
    out_diag (written only when ``opt.want_diag``) holds the Gauss-Newton diagonal
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
        pv = load_params(params, i, n_params, like, one)
        dv = like * zero
        if opt.want_dhd != 0:
            dv = load_params(direction, i, n_params, like, one)
        k0 = img_begin + g * per_group
        k1 = wp.min(k0 + per_group, img_end)
        for k in range(k0, k1):
            info = infos[k]
            ok, y, w, u, v, xs, ys = observe(images, depth, shadow, info, k, tex, i, opt)
            if ok:
                want_hm = opt.want_dhd * opt.full_hessian
                wc, m, jr, jg, jb, hm = sample_model(pv, dv, n_lobes, aniso, want_hm, info, tex, i, xs, ys, w, u, v,
                                                     opt, one)
                yc = to_compute3(y, one)
                for c in range(3):
                    r, s, jc = channel_residual(m, yc, wc, jr, jg, jb, c, opt.reflectance_space, one)
                    term = type(one)(0.5) * r * r
                    if opt.kahan != 0:
                        yk = term - fc
                        tk = f + yk
                        fc = (tk - f) - yk
                        f = tk
                    else:
                        f = f + term
                    if opt.want_grad != 0:
                        gterm = (r * s) * jc
                        if opt.kahan != 0:
                            ygk = gterm - gc
                            tgk = grad + ygk
                            gc = (tgk - grad) - ygk
                            grad = tgk
                        else:
                            grad = grad + gterm
                    if opt.want_diag != 0:
                        sj = s * jc
                        diag = diag + wp.cw_mul(sj, sj)
                    if opt.want_dhd != 0:
                        jd = s * wp.dot(jc, dv)
                        dhd = dhd + jd * jd
                        if opt.full_hessian != 0:
                            dhd = dhd + r * s * hm[c]
                    st = st + trace_stats(wc, m, y, c)
    out_f[g, i] = f
    out_g[g, i] = grad
    out_dhd[g, i] = dhd
    out_stats[g, i] = st
    if opt.want_diag != 0:
        out_diag[g, i] = diag


@wp.kernel
def accumulate_lm_kernel(
    tex: TexelFrames, params: wp.array2d(dtype=Any),
    active: wp.array(dtype=wp.int32), n_params: int, n_lobes: int, aniso: int,
    images: wp.array3d(dtype=Any), depth: wp.array3d(dtype=wp.float32),
    shadow: wp.array3d(dtype=wp.float32), infos: wp.array(dtype=ImageInfo),
    img_begin: int, img_end: int, per_group: int, opt: SampleOptions, like: Any, like_m: Any, one: Any,
    out_f: wp.array2d(dtype=Any), out_g: wp.array2d(dtype=Any), out_jtj: wp.array2d(dtype=Any),
    out_stats: wp.array2d(dtype=wp.vec4d)):
    """Partial objective, J^T r and J^T J of texel i over photo group g (Gauss-Newton / LM)."""
    g, i = wp.tid()
    zero = one - one
    f = zero
    grad = like * zero
    jtj = like_m * zero
    st = wp.vec4d(0.0)
    if active[i] != 0:
        pv = load_params(params, i, n_params, like, one)
        k0 = img_begin + g * per_group
        k1 = wp.min(k0 + per_group, img_end)
        for k in range(k0, k1):
            info = infos[k]
            ok, y, w, u, v, xs, ys = observe(images, depth, shadow, info, k, tex, i, opt)
            if ok:
                wc, m, jr, jg, jb, hm = sample_model(pv, pv, n_lobes, aniso, 0, info, tex, i, xs, ys, w, u, v, opt, one)
                yc = to_compute3(y, one)
                for c in range(3):
                    r, s, jc = channel_residual(m, yc, wc, jr, jg, jb, c, opt.reflectance_space, one)
                    f = f + type(one)(0.5) * r * r
                    sj = s * jc
                    grad = grad + r * sj
                    jtj = jtj + wp.outer(sj, sj)
                    st = st + trace_stats(wc, m, y, c)
    out_f[g, i] = f
    out_g[g, i] = grad
    out_jtj[g, i] = jtj
    out_stats[g, i] = st


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


@wp.kernel
def initial_guess_kernel(tex: TexelFrames, images: wp.array3d(dtype=Any),
                         depth: wp.array3d(dtype=wp.float32), shadow: wp.array3d(dtype=wp.float32),
                         infos: wp.array(dtype=ImageInfo), img_begin: int, img_end: int, opt: SampleOptions,
                         rank: int, low: wp.array(dtype=wp.vec3), high: wp.array(dtype=wp.vec3),
                         count: wp.array(dtype=wp.int32)):
    """Per texel: the ``rank``-th smallest observed reflectance y / (exposure E cos) per channel
    (a low percentile, McAllister's diffuse estimate used by the seed), the largest, and the
    number of samples. Windows accumulate (call with the outputs pre-filled)."""
    i = wp.tid()
    lo = wp.mat44(0.0)  # rows: channel, columns: the 4 smallest so far, ascending
    for c in range(3):
        for j in range(4):
            lo[c, j] = 1.0e30
    # resume from previous windows: low[i] holds the rank-th value only, so windows restart the
    # small-value list (documented: with streamed windows the estimate is per-window min-merged)
    hi = high[i]
    n = count[i]
    for k in range(img_begin, img_end):
        ok, y, w, u, v, xs, ys = observe(images, depth, shadow, infos[k], k, tex, i, opt)
        if ok:
            n = n + 1
            for c in range(3):
                val = y[c] / w[c]
                hi[c] = wp.max(hi[c], val)
                if val < lo[c, 3]:
                    lo[c, 3] = val
                    for jj in range(3):
                        j = 2 - jj
                        if lo[c, j + 1] < lo[c, j]:
                            t = lo[c, j]
                            lo[c, j] = lo[c, j + 1]
                            lo[c, j + 1] = t
    r = wp.clamp(rank, 0, 3)
    est = low[i]
    for c in range(3):
        pick = lo[c, 0]
        for j in range(4):
            if j <= r and lo[c, j] < 1.0e29:
                pick = lo[c, j]
        if pick < 1.0e29:
            if count[i] > 0:
                est[c] = wp.min(est[c], pick)
            else:
                est[c] = pick
    low[i] = est
    high[i] = hi
    count[i] = n
