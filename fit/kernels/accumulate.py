"""Per-texel accumulation of the image-streaming passes (seed ch. 4-5, 8): objective, gradient and curvature.

One launch covers a range of photos: thread (g, i) takes texel i and loops over photo group g, each
(texel, photo) sample observed as :mod:`texstream.fit.kernels.stream` says, and accumulates the objective,
gradient and curvature terms in registers. Each thread writes its partial sums once;
:func:`reduce_partials_kernel` adds the groups in a fixed order, so results are deterministic (no float
atomics). Nothing per (texel, photo) is stored.

Keeping a GPU thread's state in registers decides the speed (benchmarks/results/h100_kernels): the
accumulation kernels are compiled per model layout and pass kind (:func:`accumulate_kernel`,
:func:`accumulate_lm_kernel`) so that no vector is indexed at run time.

Residuals (per colour channel c, radiance-space weight w_c = exposure * E_c * cos(theta_i)):
    radiance space   : r_c = w_c m_c - y_c
    reflectance space: r_c = m_c - y_c / w_c       (the seed's choice; needs cos(theta_i) >= 0.1)
Both are r_c = s_c (m_c - y_c / w_c) with s_c = w_c or 1, so J_r = s_c J_m and
d^T H_r d = s_c d^T H_m d. The radiance model (render/layout.py) has w_c = exposure: its passes are
compiled without the light (:func:`~texstream.fit.kernels.stream.observe_func`, ``layout_funcs(radiance=True)``).

One sample's model (:func:`_sample_model_func`). The residual is W M + N - y (radiance space), M
the model of the features f (``lafortune_funcs``). Bilinear and point sampling: W = w, f the texel's features at
(u, v) and N = 0. Filtered sampling: the photo's bilinear filter applied to the model, W = sum_t b_t w_t and M =
sum_t b_t w_t m_t / W over the four taps t (bilinear weights b_t, each tap's own surface point, light and view),
so W M is the filtered radiance. w_t is the light's RGB intensity times a scalar a_t (exposure, cosine,
falloff), so M = sum_t omega_t m_t with omega_t = b_t a_t / sum b a the same for every channel: the taps'
features are averaged, and M and its Jacobian follow from the mean exactly.

With the renderer's lookup (``lookup``, filtered sampling only) a tap's BRDF is o_t m_t + n_t, o_t the texel's
own bilinear weight there and n_t its neighbours' blended BRDFs at their held values (:func:`texel_blend`): the
taps' features are averaged with weights b_t a_t o_t into W M, and N = L sum_t b_t a_t n_t is a constant of the
texel's parameters. A sample whose taps all miss the texel (o_t = 0) is not usable.

A tap's surface point, normal (and tangent) come from the texel's face plane (:func:`ray_surface`, the
interpolated normal extended to first order, texel coordinates extended linearly: no mesh access) or, with
``traced``, from the tap's pixel ray traced to the mesh (:func:`traced_tap`: the point, frame, UV and cast
shadow the renderer sees, so a tap that leaves the texel's face, e.g. on curved or coarse geometry, lands where
the photo's pixel looks).

The radiance model (``radiance``) has no light: w_t = b_t exposure (times 1 or 0 for a traced tap that hits the
mesh or misses, :func:`traced_texel`), W = sum_t w_t and N the neighbours' blended radiance sum_t w_t n_t.

The ambient radiance (``ambient``) adds exposure A to every tap whatever its light (sum_t b_t = 1): its feature is
a_c = exposure / W_c (fit/kernels/lafortune_grad.py), with the lookup exposure sum_t b_t o_t / W_c and the
neighbours' blended ambient exposure sum_t b_t n^A_t added to N. Samples of a lit photo whose taps are all unlit
stay unusable (the observation already rejects shadowed and grazing texel centres). A photo whose light is exactly 0
(taken with the flash off, capture_json.py ``no_flash``) sees the room alone: in a channel whose W_c is 0 the
sample's only feature is A's, a_c = exposure sum_t b_t o_t itself, with the weight 1 (r_c = a_c A_c + N_c - y_c, no
division by W), and such a photo's sample is usable wherever the camera's tests pass (the observation skips the
light's cosine and shadow tests, ``stream.observe_with_unlit_func``) and texel i has a share of its taps, wherever
its light sits (:func:`_unlit_sample_func`, ``lafortune_grad.unlit_funcs``). The functions that do it are the ambient
layouts' own, wrapped around the others, so the layouts without the ambient compile the code (and Warp hashes the
source) they did; the ambient layouts' arithmetic on lit samples is unchanged, so their results are bit-identical.
Without the ambient such a sample has W = 0: in radiance space r = -y with a zero Jacobian, no information
(reflectance space, which divides by W, is refused with no-flash photos: fit/models/per_texel/ambient.py).

The data term is sum rho(r_c) with rho(r) = r^2 / 2 (least squares) or a robust loss (Huber, Cauchy;
``accumulate_kernel``'s ``robust``), applied per sample as iteratively reweighted least squares.
"""

from __future__ import annotations

import functools
from typing import Any, NamedTuple

import warp as wp

from texstream.fit.kernels.lafortune_grad import lafortune_funcs, view_radiance_funcs
from texstream.fit.kernels.overloads import (IMAGE_PIXEL, STORAGE_SCALAR, at_every_count, at_every_precision,
                                             declare, param_overload)
from texstream.render.shading import incident_light, to_local
from texstream.fit.kernels.stream import (SAMPLING_FILTERED, ImageInfo, SampleOptions, TexelFrames, kahan_add,
                                          observe_func, observe_with_unlit_func, plane_texel_coords, ray_surface,
                                          tangent_frame, texel_blend, texel_blend_ambient, to_compute3, trace_stats,
                                          traced_tap, traced_texel)

# no kernel here is differentiated (the fit writes its own derivatives): skipping Warp's adjoint
# code generation roughly halves compile time
wp.set_module_options({"enable_backward": False})


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
                 radiance: bool = False, ambient: bool = False) -> LayoutFuncs:
    """The sample functions the accumulation kernels share, specialised to one model layout
    (loops over lobes and columns with compile-time trip counts, see ``lafortune_funcs``), to
    the model's texture lookup (``lookup``: the renderer's bilinear blend with the neighbours, see
    ``sample_model``), to the filtered taps' geometry (``traced``: each tap's ray traced to the
    mesh, :func:`traced_tap`; else the texel's face plane, :func:`ray_surface`) and to the light
    (``radiance``: 1 the radiance model, no lobes, no light, W = exposure, :func:`observe_func`; 2 the
    view-dependent radiance, the same with ``view_radiance_funcs`` of the local view direction) and to the
    ambient radiance (``ambient``: 1 a lit model's per-texel A, 2 the room light's per-texel S, render/layout.py
    ``extra_term``, its columns last)."""
    view = int(radiance) == 2
    ambient = 0 if radiance else int(ambient)  # 1 the free ambient, 2 the room light's S (render/layout.py)
    lf = view_radiance_funcs() if view else lafortune_funcs(n_lobes, anisotropic, ambient)
    n_params = 18 if view else 3 + int(n_lobes) * (6 + int(anisotropic)) + 3 * int(bool(ambient))
    load_params, channel_residual = _parameter_funcs(lf, n_params)
    frame_directions, lobe_directions = _direction_funcs(anisotropic)
    sample_model = _sample_model_func(lf, frame_directions, lobe_directions, bool(lookup), bool(traced),
                                      bool(radiance), ambient)
    if ambient:  # its own functions around the sample, for photos whose light is 0: the others compile as they did
        sample = _unlit_sample_func(_sample_func(observe_with_unlit_func(), sample_model, bool(lookup)),
                                    3 + int(n_lobes) * (6 + int(anisotropic)))
    else:
        sample = _sample_func(observe_func(bool(radiance)), sample_model, bool(lookup))
    return LayoutFuncs(lf, load_params, sample, channel_residual, n_params)


def _parameter_funcs(lf, n_params: int):
    """(load_params, channel_residual): a texel's parameters read into a vector, and a channel's model,
    residual and scale from the features (``lf``: the layout's ``lafortune_funcs``)."""

    @wp.func
    def load_params(params: wp.array2d(dtype=Any), i: int, like: Any, one: Any):
        out = like * (one - one)
        for k in range(wp.static(n_params)):
            out[k] = type(one)(params[i, k])
        return out

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

    return load_params, channel_residual


def _direction_funcs(anisotropic: int):
    """(frame_directions, lobe_directions): the light and view directions as the lobes see them, with a
    tangent frame only for ``anisotropic`` lobes."""

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

    return frame_directions, lobe_directions


def _sample_model_func(lf, frame_directions, lobe_directions, blend: bool, trace: bool, no_light: bool,
                       ambient: bool = False):
    """The model side of one sample (``sample_model``; ``blend``, ``trace``, ``no_light`` and ``ambient`` are
    :func:`layout_funcs`'s ``lookup``, ``traced``, ``radiance`` and ``ambient``), as the module doc's "One
    sample's model" says."""

    @wp.func
    def sample_model(pv: Any, dv: Any, infos: wp.array(dtype=ImageInfo), k: int, tex: TexelFrames, i: int, xs: float,
                     ys: float, w: wp.vec3, u: wp.vec3, v: wp.vec3, opt: SampleOptions, want_hm: int, one: Any):
        """(usable, weight W, lobe features f, d^T (Hess M) d, offset N) of one sample (:func:`_sample_model_func`)."""
        uc = to_compute3(u, one)
        vc = to_compute3(v, one)
        zero = one - one
        if opt.sampling != SAMPLING_FILTERED or infos[k].depth_is_mask != 0:
            hm = type(uc)(zero, zero, zero)
            if want_hm != 0:
                hm = lf.dhd(pv, dv, uc, vc, one)
            wc0 = to_compute3(w, one)
            feat0 = lf.set_ambient(lf.features(pv, uc, vc, one), type(one)(infos[k].exposure), wc0)
            return True, wc0, feat0, hm, wp.vec3(0.0)
        x0 = int(xs)
        y0 = int(ys)
        fx = xs - float(x0)
        fy = ys - float(y0)
        asum = float(0.0)
        nsum = wp.vec3(0.0)
        feat = pv * zero
        hsum = type(uc)(zero, zero, zero)
        ambient_col = 3 + tex.n_lobes * (6 + tex.anisotropic)  # the layout's ambient columns (lookup_params)
        own_b = float(0.0)  # sum_t b_t o_t: texel i's share of the taps' ambient (1 without the lookup)
        amb_other = wp.vec3(0.0)  # sum_t b_t n^A_t: the neighbours' (the lookup's)
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
                if wp.static(ambient):
                    own_b = own_b + b * own
                    amb_other = amb_other + b * texel_blend_ambient(tex, i, tx, ty, ambient_col,
                                                                             wp.static(int(ambient) == 2))
            elif wp.static(ambient):
                own_b = own_b + b
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
        weight = to_compute3(infos[k].light_intensity * asum, one)
        if wp.static(ambient):
            offset = offset + exposure * amb_other
        return asum > 0.0, weight, lf.set_ambient(feat * inv, type(one)(exposure * own_b), weight), hsum * inv, offset

    return sample_model


def _sample_func(observe_sample, sample_model, blend: bool):
    """The whole (texel, photo) sample (``sample``): the photo observed, then the model's side."""

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

    return sample


def _unlit_sample_func(sample, ambient_col: int):
    """The sample (``sample``) of a layout with the ambient (columns from ``ambient_col``), with photos whose
    light is 0 (the flash off): a channel ``set_ambient`` marks unlit (f[c] = 1, its weight W_c 0) has the weight 1
    and no d^T (Hess M) d, its residual the ambient's alone (``lafortune_grad.unlit_funcs``); a photo whose light is
    0 in every channel gives a usable sample wherever the photo sees texel i's share of the ambient (observed, and
    with the lookup a tap on the texel), whatever its light's cosine over the taps (module doc)."""

    @wp.func
    def unlit_sample(pv: Any, dv: Any, images: wp.array3d(dtype=Any), depth: wp.array3d(dtype=wp.float32),
                     shadow: wp.array3d(dtype=wp.float32), infos: wp.array(dtype=ImageInfo), k: int, tex: TexelFrames,
                     i: int, opt: SampleOptions, want_hm: int, one: Any):
        use, wc, feat, hm, fitted, y = sample(pv, dv, images, depth, shadow, infos, k, tex, i, opt, want_hm, one)
        zero = one - one
        for c in range(3):
            if feat[c] != zero:
                wc[c] = one
                hm[c] = zero
        light = infos[k].light_intensity
        if light[0] == 0.0 and light[1] == 0.0 and light[2] == 0.0:
            use = feat[wp.static(ambient_col)] > zero
        return use, wc, feat, hm, fitted, y

    return unlit_sample


@functools.cache
def accumulate_kernel(n_lobes: int, anisotropic: int, kahan: bool, diag: bool, dhd: bool, full_hessian: bool,
                      max_registers: int = 0, lookup: bool = False, traced: bool = False, radiance: bool = False,
                      robust: int = ROBUST_NONE, ambient: bool = False):
    """The objective / gradient pass of one model layout and pass kind.

    What a pass accumulates beside f and the gradient is fixed when the kernel compiles rather
    than tested per sample, so a pass carries no registers for what it does not compute:
    ``kahan`` (compensated sums), ``diag`` (the Gauss-Newton diagonal), ``dhd`` (d^T H d along
    ``direction``) and ``full_hessian`` (its r d^T (Hess r) d term). The Jacobian rows are built
    with literal indices (``LafortuneFuncs.jacobian_row``), so they stay in registers.
    ``max_registers`` caps registers per CUDA thread (0: none); ``lookup`` selects the renderer's
    texture lookup, ``traced`` the traced tap geometry and ``radiance`` the light-free radiance
    model and ``ambient`` the ambient radiance (``layout_funcs``). Each kernel lives in a module of its own, so
    compiling one does not recompile the others.

    ``robust`` (``ROBUST_LOSSES``) replaces each channel's r^2 / 2 by a robust loss rho(r) of scale
    ``opt.robust_scale``, as iteratively reweighted least squares: objective rho(r), gradient
    rho'(r) s J, Gauss-Newton curvature w(r) (s J d)^2 with the IRLS weight w = rho'(r) / r (also in
    the Jacobi diagonal), and the full d^T H d rho''(r) (s J d)^2 + rho'(r) s d^T (Hess m) d, the
    exact second derivative. The weights follow the current residuals in every pass (no host
    round trip); ``ROBUST_NONE`` compiles the least-squares pass unchanged.
    """
    fn = layout_funcs(n_lobes, anisotropic, lookup, traced, radiance, ambient)
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
                                             ("view", int(radiance) == 2), ("ambient", int(ambient) == 1),
                                             ("room", int(ambient) == 2)) if on]
                    + ([_robust_name(robust)] if robust_on else []))
    if max_registers:
        name += f"_maxreg{max_registers}"
    kernel = wp.kernel(accumulate, name=name, enable_backward=False, module="unique",
                       cuda_max_registers=max_registers or None)
    at_every_precision(functools.partial(_declare_gradient_pass, kernel, fn.n_params))
    return kernel


def _declare_gradient_pass(kernel, n_params: int, scalar) -> None:
    """A gradient pass kernel's overload of the compute scalar ``scalar`` (fit/kernels/overloads.py)."""
    s, v, _ = param_overload(n_params, scalar)
    declare(kernel, params=STORAGE_SCALAR, direction=STORAGE_SCALAR, images=IMAGE_PIXEL, like=v, one=s, out_f=s,
            out_g=v, out_dhd=s, out_diag=v)


@functools.cache
def accumulate_lm_kernel(n_lobes: int, anisotropic: int, max_registers: int = 0, lookup: bool = False,
                         traced: bool = False, radiance: bool = False, robust: int = ROBUST_NONE,
                         ambient: bool = False):
    """The Gauss-Newton / LM pass of one model layout: f, J^T r and J^T J per (photo group, texel).

    J^T J is summed over the structurally non-zero entries of each channel's Jacobian row only
    (``LafortuneFuncs.row_entry``; 33 of the 81 entries of one isotropic lobe) into its upper
    triangle and mirrored once at the end, so the sums stay in registers on a GPU.

    ``robust``: the robust loss as in :func:`accumulate_kernel`, f = sum rho(r), J^T psi(r) and
    J^T W J with the IRLS weights W = psi(r) / r (iteratively reweighted least squares: every
    pass reweights at its own point).
    """
    fn = layout_funcs(n_lobes, anisotropic, lookup, traced, radiance, ambient)
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
                    + ([_robust_name(robust)] if robust_on else []) + (["ambient"] if int(ambient) == 1 else [])
                    + (["room"] if int(ambient) == 2 else []))
    if max_registers:
        name += f"_maxreg{max_registers}"
    kernel = wp.kernel(accumulate_lm, name=name, enable_backward=False, module="unique",
                       cuda_max_registers=max_registers or None)
    at_every_precision(functools.partial(_declare_lm_pass, kernel, n_params))
    return kernel


def _declare_lm_pass(kernel, n_params: int, scalar) -> None:
    """An LM pass kernel's overload of the compute scalar ``scalar`` (fit/kernels/overloads.py)."""
    s, v, m = param_overload(n_params, scalar)
    declare(kernel, params=STORAGE_SCALAR, images=IMAGE_PIXEL, like=v, like_m=m, one=s, out_f=s, out_g=v, out_jtj=m)


@wp.kernel(enable_backward=False, module="unique")
def hold_lookup_params_kernel(params: wp.array2d(dtype=Any), relaxation: float, held: wp.array2d(dtype=wp.float32)):
    """``held[i, k] += relaxation * (params[i, k] - held[i, k])`` in float32 (1: ``held = params``):
    the values the renderer's lookup reads for texel i's neighbours until the next refresh (rows
    past the parameters, the defaults, untouched)."""
    i, k = wp.tid()
    h = held[i, k]
    held[i, k] = h + relaxation * (wp.float32(params[i, k]) - h)


@wp.kernel(enable_backward=False, module="unique")
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


def _declare_reduce_overloads(scalar, n_params: int) -> None:
    """reduce_partials_kernel's overloads of the compute scalar ``scalar`` and one declared parameter count
    (fit/kernels/overloads.py): LM's J^T J, CG's d^T H d."""
    _s, _v, _m = param_overload(n_params, scalar)
    for _h in (_m, _s):
        declare(reduce_partials_kernel, pf=_s, pg=_v, ph=_h, f=_s, g=_v, h=_h)


at_every_count(_declare_reduce_overloads)


@wp.kernel(enable_backward=False, module="unique")
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
