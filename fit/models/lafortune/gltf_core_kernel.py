"""The glTF core-material fit (gltf_core.py's module doc) as one Warp kernel: one thread per texel, float64.

The same search as the moment-based numpy version it replaces (kept as the reference in
tests/test_gltf_core_kernel.py): for each roughness of the geometric grid, the weighted moments of the GGX terms
and the Lafortune radiance over the direction samples, then the best metallic of the 101-step grid in closed
form (base colour the clipped least-squares value per channel); the coarse best refined by four factors; then
KHR_materials_specular's F0 and the four relative RMS scores. Ties go to the first value, as numpy's argmin and
the strict ``<`` did. Why a kernel: the numpy version took 8 s of the README demo's export on the CPU (numpy
temporaries of texels x samples x channels per roughness), and ran on the CPU whatever device the run had; the
kernel reads each sample's terms once per roughness and keeps nothing per sample. The moments of the coarse grid's
GGX terms that do not depend on the texel are summed once for all texels (geometry_moments_kernel), in the order
each texel summed them, so the maps are the same to the bit (a 204,000-texel block of the 6 MP facade's diffuse
model: 5.7 -> 5.0 CPU s).
"""

from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import warp as wp

from texstream.fit.multi.cpu_threads import usable_cpus
from texstream.render.shading import lafortune_brdf

INV_PI = wp.constant(wp.float64(1.0 / math.pi))
F0_DIELECTRIC = wp.constant(wp.float64(0.04))


@wp.func
def _ggx(ell: wp.vec3d, v: wp.vec3d, alpha: wp.float64):
    """(D * Vis, (1 - l.h)^5): gltf_core.py ``ggx_terms`` for one direction pair."""
    h = ell + v
    hn = wp.length(h)
    if hn > wp.float64(1.0e-30):
        h = h / hn
    else:
        h = h / wp.float64(1.0e-30)
    zero, one = wp.float64(0.0), wp.float64(1.0)
    nl = wp.clamp(ell[2], zero, one)
    nv = wp.clamp(v[2], zero, one)
    nh = wp.clamp(h[2], zero, one)
    lh = wp.clamp(wp.dot(ell, h), zero, one)
    a2 = alpha * alpha
    den = nh * nh * (a2 - one) + one
    d = a2 / (wp.float64(math.pi) * den * den)
    vis = wp.float64(0.5) / wp.max(nl * wp.sqrt(a2 + (one - a2) * nv * nv) + nv * wp.sqrt(a2 + (one - a2) * nl * nl),
                                    wp.float64(1.0e-12))
    x = one - lh
    return d * vis, x * x * x * x * x


@wp.func
def _core(b: wp.vec3d, m: wp.float64, f0d: wp.vec3d, dv: wp.float64, x5: wp.float64):
    """The core BRDF (gltf_core.py ``core_brdf``) from one sample's GGX terms."""
    one = wp.float64(1.0)
    f0 = (one - m) * f0d + m * b
    return b * ((one - m) * INV_PI) + f0 * (dv * (one - x5)) + wp.vec3d(dv * x5, dv * x5, dv * x5)


GeometryMoments = wp.types.vector(length=10, dtype=wp.float64)
"""the weighted moments of one roughness's sample terms that do not depend on the texel: sw, sq, sqq, s1, t1, qs,
qt, ss, st, tt (:func:`_geometry_moments`)"""


@wp.func
def _sample_terms(light: wp.array(dtype=wp.vec3d), view: wp.array(dtype=wp.vec3d),
                  table_dv: wp.array2d(dtype=wp.float64), table_x5: wp.array2d(dtype=wp.float64), row: int,
                  alpha: wp.float64, k: int):
    """(q, s, tt) of sample ``k``: g0 = s + m tt and g1 = p + m q (:func:`_best_metallic`), from row ``row`` of the
    tables or, for ``row`` < 0, from ``alpha``."""
    dv = wp.float64(0.0)
    x5 = wp.float64(0.0)
    if row >= 0:
        dv = table_dv[row, k]
        x5 = table_x5[row, k]
    else:
        dv, x5 = _ggx(light[k], view[k], alpha)
    a = dv * (wp.float64(1.0) - x5)
    return a - INV_PI, dv * x5 + F0_DIELECTRIC * a, -F0_DIELECTRIC * a


@wp.func
def _sample_moments(w: wp.float64, q: wp.float64, s: wp.float64, tt: wp.float64):
    """One sample's weighted terms of :data:`GeometryMoments`."""
    return GeometryMoments(w, w * q, w * q * q, w * s, w * tt, w * q * s, w * q * tt, w * s * s, w * s * tt,
                           w * tt * tt)


@wp.func
def _geometry_moments(light: wp.array(dtype=wp.vec3d), view: wp.array(dtype=wp.vec3d),
                      weight: wp.array(dtype=wp.float64), table_dv: wp.array2d(dtype=wp.float64),
                      table_x5: wp.array2d(dtype=wp.float64), row: int, alpha: wp.float64):
    """The texel-independent moments of one roughness (:data:`GeometryMoments`)."""
    out = GeometryMoments()
    for k in range(light.shape[0]):
        q, s, tt = _sample_terms(light, view, table_dv, table_x5, row, alpha, k)
        out += _sample_moments(weight[k], q, s, tt)
    return out


@wp.kernel
def geometry_moments_kernel(light: wp.array(dtype=wp.vec3d), view: wp.array(dtype=wp.vec3d),
                            weight: wp.array(dtype=wp.float64), table_dv: wp.array2d(dtype=wp.float64),
                            table_x5: wp.array2d(dtype=wp.float64), out: wp.array(dtype=GeometryMoments)):
    """The moments of every coarse roughness: the same for every texel, so summed once, not once a texel."""
    i = wp.tid()
    out[i] = _geometry_moments(light, view, weight, table_dv, table_x5, i, wp.float64(0.0))


@wp.func
def _best_metallic(radiance: wp.array2d(dtype=wp.vec3d), t: int, light: wp.array(dtype=wp.vec3d),
                   view: wp.array(dtype=wp.vec3d), weight: wp.array(dtype=wp.float64),
                   table_dv: wp.array2d(dtype=wp.float64), table_x5: wp.array2d(dtype=wp.float64), row: int,
                   alpha: wp.float64, yy: wp.vec3d, y1: wp.vec3d, g: GeometryMoments, m_steps: int):
    """(err, m, b) of the best metallic for one roughness (gltf_core.py ``_best_for_roughness``): g0 = s + m t
    and g1 = p + m q per sample, the base colour's model b g1 + g0 affine in b. The GGX terms come from row
    ``row`` of the tables (the coarse grid, the same for every texel), or for ``row`` < 0 from ``alpha``; ``g``
    their texel-independent moments (summed here for ``row`` < 0), ``y1`` the texel's weighted radiance sum (each
    sum in the sample order it always had: the maps are the same to the bit as when every texel summed them all)."""
    p = INV_PI
    own = GeometryMoments()  # a refined roughness's (row < 0), summed with the texel's in one pass over the samples
    qy = wp.vec3d()
    sy = wp.vec3d()
    ty = wp.vec3d()
    for k in range(light.shape[0]):
        w = weight[k]
        q, s, tt = _sample_terms(light, view, table_dv, table_x5, row, alpha, k)
        if row < 0:
            own += _sample_moments(w, q, s, tt)
        y = radiance[t, k]
        qy += (w * q) * y
        sy += (w * s) * y
        ty += (w * tt) * y
    if row < 0:
        g = own
    sw, sq, sqq, s1, t1 = g[0], g[1], g[2], g[3], g[4]
    qs, qt, ss_, st_, stt = g[5], g[6], g[7], g[8], g[9]
    pp, pq, ps, pt = p * p * sw, p * sq, p * s1, p * t1
    py = p * y1
    best_err = wp.float64(1.0e300)
    best_m = wp.float64(0.0)
    best_b = wp.vec3d()
    for i in range(m_steps):
        m = wp.float64(i) / wp.float64(m_steps - 1)
        g2 = pp + wp.float64(2.0) * m * pq + m * m * sqq
        err = wp.float64(0.0)
        b = wp.vec3d()
        for c in range(3):
            gy = py[c] + m * qy[c] - (ps + m * (qs + pt) + m * m * qt)
            r2 = yy[c] - wp.float64(2.0) * (sy[c] + m * ty[c]) + ss_ + wp.float64(2.0) * m * st_ + m * m * stt
            bc = wp.clamp(gy / wp.max(g2, wp.float64(1.0e-300)), wp.float64(0.0), wp.float64(1.0))
            b[c] = bc
            err += r2 - wp.float64(2.0) * bc * gy + bc * bc * g2
        if err < best_err:
            best_err = err
            best_m = m
            best_b = b
    return best_err, best_m, best_b


@wp.kernel
def lafortune_samples_kernel(rows: wp.array2d(dtype=wp.float64), first: int, n_lobes: int, aniso: int,
                             light: wp.array(dtype=wp.vec3d), view: wp.array(dtype=wp.vec3d),
                             radiance: wp.array2d(dtype=wp.vec3d)):
    """The Lafortune BRDF of texel ``first + t`` at every direction sample (the fit's target, read ~30 times)."""
    t, k = wp.tid()
    radiance[t, k] = lafortune_brdf(rows, first + t, n_lobes, aniso, light[k], view[k], wp.float64(1.0))


@wp.kernel
def ggx_table_kernel(light: wp.array(dtype=wp.vec3d), view: wp.array(dtype=wp.vec3d),
                     rough: wp.array(dtype=wp.float64), dv: wp.array2d(dtype=wp.float64),
                     x5: wp.array2d(dtype=wp.float64)):
    """GGX terms of the coarse roughness grid at every sample: the same for every texel."""
    i, k = wp.tid()
    a, b = _ggx(light[k], view[k], rough[i] * rough[i])
    dv[i, k] = a
    x5[i, k] = b


@wp.kernel
def core_material_kernel(radiance: wp.array2d(dtype=wp.vec3d), first: int,
                         light: wp.array(dtype=wp.vec3d), view: wp.array(dtype=wp.vec3d),
                         weight: wp.array(dtype=wp.float64), coarse: wp.array(dtype=wp.float64),
                         table_dv: wp.array2d(dtype=wp.float64), table_x5: wp.array2d(dtype=wp.float64),
                         table_moments: wp.array(dtype=GeometryMoments),
                         refine: wp.array(dtype=wp.float64), rough_min: wp.float64, m_steps: int,
                         old_base: wp.array(dtype=wp.vec3d), old_f0: wp.array(dtype=wp.vec3d),
                         old_rough: wp.array(dtype=wp.float64),
                         base: wp.array(dtype=wp.vec3d), metallic: wp.array(dtype=wp.float64),
                         roughness: wp.array(dtype=wp.float64), f0d: wp.array(dtype=wp.vec3d),
                         rel: wp.array2d(dtype=wp.float64)):
    """One texel (``radiance``'s row ``t``, output row ``first + t``): its core material, F0_d and relative RMS
    scores (module doc)."""
    t = wp.tid()
    o = first + t
    yy = wp.vec3d()
    y1 = wp.vec3d()
    for k in range(light.shape[0]):
        y = radiance[t, k]
        yy += weight[k] * wp.cw_mul(y, y)
        y1 += weight[k] * y
    best_err = wp.float64(1.0e308)
    best_m = wp.float64(0.0)
    best_r = wp.float64(1.0)
    best_b = wp.vec3d()
    for i in range(coarse.shape[0]):
        r = coarse[i]
        err, m, b = _best_metallic(radiance, t, light, view, weight, table_dv, table_x5, i, r * r, yy, y1,
                                   table_moments[i], m_steps)
        if err < best_err:
            best_err = err
            best_m = m
            best_r = r
            best_b = b
    coarse_best = best_r
    for i in range(refine.shape[0]):
        r = wp.clamp(coarse_best * refine[i], rough_min, wp.float64(1.0))
        err, m, b = _best_metallic(radiance, t, light, view, weight, table_dv, table_x5, -1, r * r, yy, y1,
                                   GeometryMoments(), m_steps)
        if err < best_err:
            best_err = err
            best_m = m
            best_r = r
            best_b = b
    # KHR_materials_specular's dielectric F0 with (b, m, r) fixed: affine per channel, least squares in [0, 1]
    dielectric = wp.vec3d(F0_DIELECTRIC, F0_DIELECTRIC, F0_DIELECTRIC)
    num = wp.vec3d()
    den = wp.float64(0.0)
    one = wp.float64(1.0)
    for k in range(light.shape[0]):
        dv, x5 = _ggx(light[k], view[k], best_r * best_r)
        kk = (one - best_m) * dv * (one - x5)
        g = _core(best_b, best_m, dielectric, dv, x5) - F0_DIELECTRIC * wp.vec3d(kk, kk, kk)
        y = radiance[t, k]
        num += (weight[k] * kk) * (y - g)
        den += weight[k] * kk * kk
    f = dielectric
    if den > wp.float64(0.0):
        for c in range(3):
            f[c] = wp.clamp(num[c] / den, wp.float64(0.0), one)
    base[o] = best_b
    metallic[o] = best_m
    roughness[o] = best_r
    f0d[o] = f
    # relative RMS radiance error over the samples: core, core + extension, the export before (both)
    e0 = wp.float64(0.0)
    e1 = wp.float64(0.0)
    e2 = wp.float64(0.0)
    e3 = wp.float64(0.0)
    zero = wp.float64(0.0)
    ob = old_base[o]
    for k in range(light.shape[0]):
        w = weight[k]
        y = radiance[t, k]
        dv, x5 = _ggx(light[k], view[k], best_r * best_r)
        e0 += w * wp.length_sq(_core(best_b, best_m, dielectric, dv, x5) - y)
        e1 += w * wp.length_sq(_core(best_b, best_m, f, dv, x5) - y)
        dv, x5 = _ggx(light[k], view[k], old_rough[o] * old_rough[o])
        e2 += w * wp.length_sq(_core(ob, zero, dielectric, dv, x5) - y)
        e3 += w * wp.length_sq(_core(ob, zero, old_f0[o], dv, x5) - y)
    total = wp.max(yy[0] + yy[1] + yy[2], wp.float64(1.0e-300))
    rel[0, o] = wp.sqrt(e0 / total)
    rel[1, o] = wp.sqrt(e1 / total)
    rel[2, o] = wp.sqrt(e2 / total)
    rel[3, o] = wp.sqrt(e3 / total)


TEXEL_CHUNK = 16384  # texels per launch: their samples' radiance (S x 24 bytes each, ~4.5 KB) stays ~75 MB a thread


def fit_rows(rows: np.ndarray, layout, light: np.ndarray, view: np.ndarray, weight: np.ndarray,
             old: tuple[np.ndarray, np.ndarray, np.ndarray], coarse: np.ndarray, refine: tuple, rough_min: float,
             metallic_steps: int, device: str) -> tuple[np.ndarray, ...]:
    """The core material of texels ``rows`` (T, P) under direction samples (S, 3) and normalised weights (S,):
    (base (T, 3), metallic (T,), roughness (T,), F0_d (T, 3), relative RMS (4, T)); ``old``: the export
    before's (base (T, 3), F0 (T, 3), roughness (T,)), scored beside."""
    n, s = len(rows), len(light)
    with wp.ScopedDevice(device):
        def arr(a, dtype):
            return wp.array(np.ascontiguousarray(a, dtype=np.float64), dtype=dtype)

        outs = (wp.zeros(n, dtype=wp.vec3d), wp.zeros(n, dtype=wp.float64), wp.zeros(n, dtype=wp.float64),
                wp.zeros(n, dtype=wp.vec3d), wp.zeros((4, n), dtype=wp.float64))
        if n == 0:
            return tuple(o.numpy() for o in outs)
        grid, light_w, view_w = arr(rows, wp.float64), arr(light, wp.vec3d), arr(view, wp.vec3d)
        coarse_w = arr(coarse, wp.float64)
        table_dv, table_x5 = wp.empty((len(coarse), s), dtype=wp.float64), wp.empty((len(coarse), s), dtype=wp.float64)
        wp.launch(ggx_table_kernel, dim=(len(coarse), s), inputs=[light_w, view_w, coarse_w], outputs=[table_dv, table_x5])
        weight_w = arr(weight, wp.float64)
        moments = wp.empty(len(coarse), dtype=GeometryMoments)
        wp.launch(geometry_moments_kernel, dim=len(coarse), inputs=[light_w, view_w, weight_w, table_dv, table_x5],
                  outputs=[moments])
        fixed = [weight_w, coarse_w, table_dv, table_x5, moments, arr(np.asarray(refine), wp.float64),
                 wp.float64(rough_min), int(metallic_steps), arr(old[0], wp.vec3d), arr(old[1], wp.vec3d),
                 arr(old[2], wp.float64)]
        firsts = list(range(0, n, TEXEL_CHUNK))
        threads = min(len(firsts), usable_cpus()) if wp.get_device(device).is_cpu else 1
        # chunk k on thread k % threads, each with its own radiance buffer: the chunks write disjoint texels, so
        # the maps are the same to the bit on any number of threads
        buffers = [wp.empty((min(n, TEXEL_CHUNK), s), dtype=wp.vec3d) for _ in range(threads)]

        def run_chunks(t: int) -> None:
            for first in firsts[t::threads]:
                count = min(TEXEL_CHUNK, n - first)
                wp.launch(lafortune_samples_kernel, dim=(count, s), device=device, inputs=[
                    grid, first, layout.n_lobes, int(layout.anisotropic), light_w, view_w], outputs=[buffers[t]])
                wp.launch(core_material_kernel, dim=count, device=device,
                          inputs=[buffers[t], first, light_w, view_w] + fixed, outputs=list(outs))

        if threads == 1:
            run_chunks(0)
        else:  # a CPU launch runs on its caller's thread and releases the GIL (fit/multi/cpu_threads.py)
            with ThreadPoolExecutor(threads) as pool:
                for done in [pool.submit(run_chunks, t) for t in range(threads)]:
                    done.result()
        return tuple(o.numpy() for o in outs)
