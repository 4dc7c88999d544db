"""Warp kernels of the photometric shading normals (geometry/refine.py ``ShadingNormals``): every vertex's
shading normal tilted so that the photos under known lights agree with one texture. The observation model
and its robust weights are the refinement's (geometry/refine_kernels.py). Imports only numpy and warp.
"""

from __future__ import annotations

import warp as wp

from texstream.render.camera import ImageInfo
from texstream.render.shading import incident_light

from .refine_kernels import ROLE_FIT, Observation, huber_loss, huber_weight, observe, texel_normal

wp.set_module_options({"enable_backward": False})


# Photometric normals under known lights: each welded vertex's shading normal is its start normal b (unit)
# tilted in its tangent plane, n = normalize(b + x0 tu + x1 tv) with (tu, tv, b) orthonormal; a texel's
# shading normal interpolates its face's vertex normals, n_t = normalize(sum_c beta_c n_c). A sample's model
# is C_t s_k (wi . n_t) (s_k: exposure times the light's irradiance), compared in intensities, the residuals
# averaged over each vertex's patch (geometry/refine.py ShadingNormals); with C_t held (the closed-form colour
# of the current normals), a damped Gauss-Newton step moves every vertex's tilt.

NORMAL_TERMS = 5
"""per welded vertex: the lumped 2x2 J^T J of its tilt (entries 00, 01, 11) and the gradient (2)"""


@wp.func
def tilted_normal(base: wp.vec3, tu: wp.vec3, tv: wp.vec3, x: wp.vec2):
    """The unit normal ``base`` tilted by ``x`` along the tangents (tu, tv)."""
    return wp.normalize(base + x[0] * tu + x[1] * tv)


@wp.func
def cosine_tilt_derivative(wi: wp.vec3, n_t: wp.vec3, m_len: float, n_c: wp.vec3, q_len: float, tu: wp.vec3,
                           tv: wp.vec3):
    """d (wi . n_t) / d x_c per unit barycentric share: texel normal n_t = m / |m|, m = sum_c beta_c n_c,
    vertex normal n_c = q / |q|, q = b + x0 tu + x1 tv. With P_a = I - a a^T, d n_t / d x_c,j = beta_c P_t P_c
    e_j / (|m| |q|); this returns it without beta_c (the caller weighs by it)."""
    a = wi - wp.dot(wi, n_t) * n_t
    s = 1.0 / (m_len * q_len)
    au = tu - wp.dot(n_c, tu) * n_c
    av = tv - wp.dot(n_c, tv) * n_c
    return wp.vec2(s * wp.dot(a, au), s * wp.dot(a, av))


@wp.func
def observe_lit_fit(infos: wp.array(dtype=ImageInfo), images: wp.array3d(dtype=wp.vec3),
                    depth: wp.array3d(dtype=wp.float32), role: wp.array(dtype=wp.int32),
                    known: wp.array(dtype=wp.int32), k: int, t: int, p: wp.array(dtype=wp.vec3),
                    n: wp.array(dtype=wp.vec3), ns: wp.array(dtype=wp.vec3), cos_view_min: float, depth_tol: float):
    """:func:`observe` of texel ``t`` in photo ``k`` for the shading normals: only a fitting photo with a known
    light and a texel with a colour give a sample (``ok`` 0 otherwise)."""
    if role[k] != ROLE_FIT or known[t] == 0 or infos[k].light_kind == 2:
        ob = Observation()
        ob.ok = 0
        return ob
    return observe(infos, images, depth, k, p[t], n[t], ns[t], cos_view_min, depth_tol)


@wp.func
def patch_tilt_derivatives(wi: wp.vec3, f: wp.vec3i, b: wp.vec3, weld: wp.array(dtype=wp.int32),
                           shade: wp.array(dtype=wp.vec3), base: wp.array(dtype=wp.vec3),
                           tu: wp.array(dtype=wp.vec3), tv: wp.array(dtype=wp.vec3), tilt: wp.array(dtype=wp.vec2)):
    """Row c (3x2): :func:`cosine_tilt_derivative` for the c-th vertex of a texel on face ``f`` at barycentrics
    ``b``, its shading normal interpolating the vertices' ``shade``."""
    m = b[0] * shade[weld[f[0]]] + b[1] * shade[weld[f[1]]] + b[2] * shade[weld[f[2]]]
    m_len = wp.length(m)
    n_t = m / m_len
    v0, v1, v2 = weld[f[0]], weld[f[1]], weld[f[2]]
    q0 = base[v0] + tilt[v0][0] * tu[v0] + tilt[v0][1] * tv[v0]
    q1 = base[v1] + tilt[v1][0] * tu[v1] + tilt[v1][1] * tv[v1]
    q2 = base[v2] + tilt[v2][0] * tu[v2] + tilt[v2][1] * tv[v2]
    return wp.matrix_from_rows(cosine_tilt_derivative(wi, n_t, m_len, shade[v0], wp.length(q0), tu[v0], tv[v0]),
                               cosine_tilt_derivative(wi, n_t, m_len, shade[v1], wp.length(q1), tu[v1], tv[v1]),
                               cosine_tilt_derivative(wi, n_t, m_len, shade[v2], wp.length(q2), tu[v2], tv[v2]))


@wp.kernel
def tilted_normals_kernel(base: wp.array(dtype=wp.vec3), tu: wp.array(dtype=wp.vec3),
                          tv: wp.array(dtype=wp.vec3), tilt: wp.array(dtype=wp.vec2),
                          shade: wp.array(dtype=wp.vec3)):
    v = wp.tid()
    shade[v] = tilted_normal(base[v], tu[v], tv[v], tilt[v])


@wp.kernel
def texel_normals_kernel(face: wp.array(dtype=wp.int32), bary: wp.array(dtype=wp.vec3),
                         faces: wp.array(dtype=wp.vec3i), normals: wp.array(dtype=wp.vec3),
                         weld: wp.array(dtype=wp.int32), n_out: wp.array(dtype=wp.vec3)):
    t = wp.tid()
    n_out[t] = texel_normal(face[t], bary[t], faces, normals, weld)


@wp.kernel
def patch_residual_kernel(infos: wp.array(dtype=ImageInfo), images: wp.array3d(dtype=wp.vec3),
                          depth: wp.array3d(dtype=wp.float32), role: wp.array(dtype=wp.int32),
                          face: wp.array(dtype=wp.int32), bary: wp.array(dtype=wp.vec3),
                          faces: wp.array(dtype=wp.vec3i), weld: wp.array(dtype=wp.int32),
                          p: wp.array(dtype=wp.vec3), n: wp.array(dtype=wp.vec3), ns: wp.array(dtype=wp.vec3),
                          shade: wp.array(dtype=wp.vec3), base: wp.array(dtype=wp.vec3),
                          tu: wp.array(dtype=wp.vec3), tv: wp.array(dtype=wp.vec3),
                          tilt: wp.array(dtype=wp.vec2), colour: wp.array(dtype=wp.vec3),
                          known: wp.array(dtype=wp.int32), cos_view_min: float,
                          depth_tol: float, with_jacobian: int, weight: wp.array2d(dtype=float),
                          residual: wp.array2d(dtype=wp.vec3), jac_u: wp.array2d(dtype=wp.vec3),
                          jac_v: wp.array2d(dtype=wp.vec3)):
    """Per (photo, welded vertex), over the fitting photos' samples under a known light, sums over the
    vertex's patch (its faces' texels, each weighted by the vertex's barycentric share beta times the sample
    weight w): sum beta w, sum beta w r and (``with_jacobian``) sum beta w dr/dx of the residual
    r = I - s (wi . n_t) C with the colours held, x the tilt of the patch's normals in the vertex's tangents
    (lumped: the texel's three vertex normals tilted together). ``n``: the texels' surface normals
    (visibility, weights), ``ns``: their shading normals, ``shade``: the vertices'."""
    k, t = wp.tid()
    ob = observe_lit_fit(infos, images, depth, role, known, k, t, p, n, ns, cos_view_min, depth_tol)
    if ob.ok == 0:
        return
    info = infos[k]
    c = colour[t]
    r = ob.value - wp.cw_mul(ob.shading, c)
    f = faces[face[t]]
    b = bary[t]
    if with_jacobian == 0:
        for i in range(3):
            v = weld[f[i]]
            wt = b[i] * ob.weight
            wp.atomic_add(weight, k, v, wt)
            wp.atomic_add(residual, k, v, wt * r)
        return
    wi, irradiance, _dist = incident_light(info.light_kind, info.light_vec, info.light_intensity, p[t])
    dr = -info.exposure * wp.cw_mul(irradiance, c)  # d r / d (wi . n_t), per channel
    d = patch_tilt_derivatives(wi, f, b, weld, shade, base, tu, tv, tilt)
    for i in range(3):
        v = weld[f[i]]
        wt = b[i] * ob.weight
        wp.atomic_add(weight, k, v, wt)
        wp.atomic_add(residual, k, v, wt * r)
        a = d[i]
        wp.atomic_add(jac_u, k, v, (wt * a[0]) * dr)
        wp.atomic_add(jac_v, k, v, (wt * a[1]) * dr)


@wp.kernel
def patch_system_kernel(weight: wp.array2d(dtype=float), residual: wp.array2d(dtype=wp.vec3),
                        jac_u: wp.array2d(dtype=wp.vec3), jac_v: wp.array2d(dtype=wp.vec3), huber: float,
                        with_system: int, system: wp.array2d(dtype=wp.float64),
                        objective: wp.array2d(dtype=wp.float64), back: wp.array2d(dtype=wp.vec3)):
    """Per (photo, welded vertex): the Huber objective of the vertex's patch mean residual R = sum beta w r /
    W, weighted by W = sum beta w (``objective[v]`` += W rho(R), W), and (``with_system``) the lumped
    curvature of the vertex's tilt, W psi'(R) |J|^2 with J = sum beta w dr/dx / W (``system[v]`` entries 00,
    01, 11), and the objective's derivative per unit of a sample's weighted residual, ``back[k, v]`` = psi(R)
    (what :func:`normal_gradient_kernel` hands back to the samples). The mean over a patch keeps the shading
    (smooth on the surface) and averages out most of what the texture's point samples leave (the photos alias
    the texture, each view its own way)."""
    k, v = wp.tid()
    big_w = weight[k, v]
    if big_w <= 0.0:
        return
    r = residual[k, v] / big_w
    wp.atomic_add(objective, v, 0, wp.float64(big_w * huber_loss(r, huber)))
    wp.atomic_add(objective, v, 1, wp.float64(big_w))
    if with_system == 0:
        return
    hw = huber_weight(r, huber)
    back[k, v] = hw * r
    ju = jac_u[k, v] / big_w
    jv = jac_v[k, v] / big_w
    h = big_w * hw
    wp.atomic_add(system, v, 0, wp.float64(h * wp.dot(ju, ju)))
    wp.atomic_add(system, v, 1, wp.float64(h * wp.dot(ju, jv)))
    wp.atomic_add(system, v, 2, wp.float64(h * wp.dot(jv, jv)))


@wp.kernel
def normal_gradient_kernel(infos: wp.array(dtype=ImageInfo), images: wp.array3d(dtype=wp.vec3),
                           depth: wp.array3d(dtype=wp.float32), role: wp.array(dtype=wp.int32),
                           face: wp.array(dtype=wp.int32), bary: wp.array(dtype=wp.vec3),
                           faces: wp.array(dtype=wp.vec3i), weld: wp.array(dtype=wp.int32),
                           p: wp.array(dtype=wp.vec3), n: wp.array(dtype=wp.vec3),
                           ns: wp.array(dtype=wp.vec3), shade: wp.array(dtype=wp.vec3),
                           base: wp.array(dtype=wp.vec3),
                           tu: wp.array(dtype=wp.vec3), tv: wp.array(dtype=wp.vec3),
                           tilt: wp.array(dtype=wp.vec2), colour: wp.array(dtype=wp.vec3),
                           known: wp.array(dtype=wp.int32), cos_view_min: float, depth_tol: float,
                           back: wp.array2d(dtype=wp.vec3), system: wp.array2d(dtype=wp.float64)):
    """The gradient of the patch objective with respect to every vertex's tilt (``system[v]`` entries 3, 4): a
    sample's residual enters the patches of its texel's three vertices, d E / d r = w sum_c beta_c psi(R_c)
    (``back``), and d r / d x_u = beta_u (d r / d (wi . n_t)) (d (wi . n_t) / d x_u) for each of them
    (:func:`cosine_tilt_derivative`)."""
    k, t = wp.tid()
    ob = observe_lit_fit(infos, images, depth, role, known, k, t, p, n, ns, cos_view_min, depth_tol)
    if ob.ok == 0:
        return
    info = infos[k]
    f = faces[face[t]]
    b = bary[t]
    lam = ob.weight * (b[0] * back[k, weld[f[0]]] + b[1] * back[k, weld[f[1]]] + b[2] * back[k, weld[f[2]]])
    wi, irradiance, _dist = incident_light(info.light_kind, info.light_vec, info.light_intensity, p[t])
    dr = -info.exposure * wp.cw_mul(irradiance, colour[t])  # d r / d (wi . n_t), per channel
    g = wp.dot(lam, dr)
    d = patch_tilt_derivatives(wi, f, b, weld, shade, base, tu, tv, tilt)
    for i in range(3):
        v = weld[f[i]]
        a = d[i]
        wp.atomic_add(system, v, 3, wp.float64(g * b[i] * a[0]))
        wp.atomic_add(system, v, 4, wp.float64(g * b[i] * a[1]))


@wp.kernel
def mean_tilt_curvature_kernel(system: wp.array2d(dtype=wp.float64), out: wp.array(dtype=wp.float64)):
    """out[0] += half the trace of J^T J, out[1] += 1 over vertices some sample tilts (the priors' scale)."""
    v = wp.tid()
    c = wp.float64(0.5) * (system[v, 0] + system[v, 2])
    if c > wp.float64(0.0):
        wp.atomic_add(out, 0, c)
        wp.atomic_add(out, 1, wp.float64(1.0))


@wp.kernel
def tilt_sweep_kernel(current: wp.array(dtype=wp.vec2), system: wp.array2d(dtype=wp.float64),
                      offsets: wp.array(dtype=wp.int32), neighbours: wp.array(dtype=wp.int32),
                      base: wp.array(dtype=wp.vec3), tu: wp.array(dtype=wp.vec3), tv: wp.array(dtype=wp.vec3),
                      mean: wp.array(dtype=wp.float64), smoothness: float, prior: float,
                      damping: wp.array(dtype=wp.float64), x_in: wp.array(dtype=wp.vec2),
                      x_out: wp.array(dtype=wp.vec2)):
    """One Jacobi sweep of the damped Gauss-Newton step of the tilts with two priors: minimises per vertex 1/2
    (x - x0)^T H~ (x - x0) + g^T (x - x0) + lambda sum_neighbours |T x - T_j x_j|^2 + mu |x|^2, with H~ = H +
    damping diag(H), T = (tu, tv), x_j the neighbour's tilt at its current sweep value, lambda =
    ``smoothness`` and mu = ``prior`` times the mean half-trace of H. lambda keeps the correction of the start
    normals smooth (vertices no photo tilts follow their neighbours), mu holds it small. The smoothness is on
    the correction, not on the normals themselves: the normals' own Dirichlet energy is flat along the
    conformal maps of the sphere of directions, so weakly seen regions would drift along them at no cost."""
    v = wp.tid()
    scale = mean[0] / wp.max(mean[1], wp.float64(1.0))
    lam = wp.float64(smoothness) * scale
    mu = wp.float64(prior) * scale
    d = wp.float64(1.0) + damping[v]
    h00 = system[v, 0] * d
    h01 = system[v, 1]
    h11 = system[v, 2] * d
    x0 = current[v]
    r0 = h00 * wp.float64(x0[0]) + h01 * wp.float64(x0[1]) - system[v, 3]
    r1 = h01 * wp.float64(x0[0]) + h11 * wp.float64(x0[1]) - system[v, 4]
    deg = wp.float64(0.0)
    for e in range(offsets[v], offsets[v + 1]):
        j = neighbours[e]
        dj = x_in[j][0] * tu[j] + x_in[j][1] * tv[j]
        r0 = r0 + wp.float64(2.0) * lam * wp.float64(wp.dot(tu[v], dj))
        r1 = r1 + wp.float64(2.0) * lam * wp.float64(wp.dot(tv[v], dj))
        deg = deg + wp.float64(1.0)
    diag = wp.float64(2.0) * (lam * deg + mu)
    a00 = h00 + diag
    a11 = h11 + diag
    det = a00 * a11 - h01 * h01
    if det > wp.float64(0.0):
        x_out[v] = wp.vec2(float((a11 * r0 - h01 * r1) / det), float((a00 * r1 - h01 * r0) / det))
    else:
        x_out[v] = x0


@wp.kernel
def apply_tilt_kernel(proposed: wp.array(dtype=wp.vec2), max_step: float, max_total: float,
                      current: wp.array(dtype=wp.vec2), saved: wp.array(dtype=wp.vec2),
                      base: wp.array(dtype=wp.vec3), tu: wp.array(dtype=wp.vec3), tv: wp.array(dtype=wp.vec3),
                      shade: wp.array(dtype=wp.vec3)):
    """Clamp each vertex's tilt step and total tilt (tangents of the angles), keep the old tilt in ``saved``,
    tilt the vertex's shading normal."""
    v = wp.tid()
    x = current[v]
    saved[v] = x
    step = proposed[v] - x
    ls = wp.length(step)
    if ls > max_step:
        step = step * (max_step / ls)
    y = x + step
    ly = wp.length(y)
    if ly > max_total:
        y = y * (max_total / ly)
    current[v] = y
    shade[v] = tilted_normal(base[v], tu[v], tv[v], y)


@wp.kernel
def tilt_prior_kernel(tilt: wp.array(dtype=wp.vec2), offsets: wp.array(dtype=wp.int32),
                      neighbours: wp.array(dtype=wp.int32), base: wp.array(dtype=wp.vec3),
                      tu: wp.array(dtype=wp.vec3), tv: wp.array(dtype=wp.vec3),
                      mean: wp.array(dtype=wp.float64), smoothness: float, prior: float,
                      out: wp.array(dtype=wp.float64)):
    """Per vertex, the priors of :func:`tilt_sweep_kernel` at the current tilts: mu |x|^2 + lambda
    sum_neighbours |T x - T_j x_j|^2."""
    v = wp.tid()
    scale = mean[0] / wp.max(mean[1], wp.float64(1.0))
    x = tilt[v]
    dv = x[0] * tu[v] + x[1] * tv[v]
    e = wp.float64(0.0)
    for k in range(offsets[v], offsets[v + 1]):
        j = neighbours[k]
        d = dv - (tilt[j][0] * tu[j] + tilt[j][1] * tv[j])
        e = e + wp.float64(wp.dot(d, d))
    out[v] = scale * (wp.float64(smoothness) * e + wp.float64(prior) * wp.float64(wp.dot(x, x)))


@wp.kernel
def tilt_accept_kernel(before: wp.array2d(dtype=wp.float64), after: wp.array2d(dtype=wp.float64),
                       prior_before: wp.array(dtype=wp.float64), prior_after: wp.array(dtype=wp.float64),
                       saved: wp.array(dtype=wp.vec2), current: wp.array(dtype=wp.vec2),
                       base: wp.array(dtype=wp.vec3), tu: wp.array(dtype=wp.vec3),
                       tv: wp.array(dtype=wp.vec3), shade: wp.array(dtype=wp.vec3),
                       damping: wp.array(dtype=wp.float64),
                       accepted: wp.array(dtype=wp.int32)):
    """Keep a vertex's tilt step where its patch's objective plus its priors fell (and trust the quadratic
    model more), else restore its tilt and damp its next step ten times more."""
    v = wp.tid()
    if after[v, 0] + prior_after[v] <= before[v, 0] + prior_before[v]:
        damping[v] = wp.max(damping[v] * wp.float64(0.3), wp.float64(1.0e-4))
        if before[v, 1] > wp.float64(0.0):
            wp.atomic_add(accepted, 0, 1)
    else:
        current[v] = saved[v]
        shade[v] = tilted_normal(base[v], tu[v], tv[v], saved[v])
        damping[v] = wp.min(damping[v] * wp.float64(10.0), wp.float64(1.0e6))

