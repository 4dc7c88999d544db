"""Warp kernels of the photometric refinement (geometry/refine.py): cameras and mesh moved so that every
photo agrees with one texture.

The model a photo is compared with: texel t's colour C_t (RGB) times the photo's shading s_kt (exposure, and
under a known light its irradiance times the cosine: what a Lambertian texel of albedo C_t shows), sampled
bilinearly from the photo at the texel's projection. Residual r_kt = I_k(u_kt) - s_kt * C_t. A pose update
(omega, tau) moves the camera frame point X_c to X_c + omega x X_c + tau; a vertex displacement d moves the
surface along the vertex normal. Both are Gauss-Newton steps on the Huber loss of r with the photo's image
gradient (the photos are blurred first, coarse to fine, so the gradient sees a few pixels around the
projection). The derivative of the shading with respect to pose and position is left out: under a flash or a
distant lamp it varies far more slowly than the texture.

The shading's cosine takes the texel's shading normal, which the photometric shading normals
(geometry/refine_normal_kernels.py) fit; visibility and a sample's weight take its surface normal.

Every per-sample kernel runs over (photo, texel); per-photo and per-vertex sums are atomic adds. Imports only
numpy and warp.
"""

from __future__ import annotations

import warp as wp

from texstream.render.camera import ImageInfo
from texstream.render.shading import incident_light
from texstream.render.visibility import depth_consistent

wp.set_module_options({"enable_backward": False})

UNUSED, FIT, ALIGN = 0, 1, 2
"""photo roles: unused; FIT moves the texture, the mesh and its own pose; ALIGN moves only its own pose (a
held-out photo aligned to the texture the others made)"""
ROLE_UNUSED = wp.constant(UNUSED)
ROLE_FIT = wp.constant(FIT)
ROLE_ALIGN = wp.constant(ALIGN)

MAT36 = wp.types.matrix(shape=(3, 6), dtype=wp.float32)
MAT66D = wp.types.matrix(shape=(6, 6), dtype=wp.float64)
VEC6D = wp.types.vector(length=6, dtype=wp.float64)

POSE_TERMS = 28
"""per photo: 21 entries of the upper triangle of J^T J, 6 of J^T r, and the sample count"""


@wp.func
def sym_index(i: int, j: int):
    """Index of entry (i, j), i <= j, of a 6x6 symmetric matrix's upper triangle stored row by row."""
    return i * 6 - (i * (i - 1)) // 2 + (j - i)


@wp.func
def bilinear_with_gradient(images: wp.array3d(dtype=wp.vec3), k: int, x: float, y: float):
    """Bilinear value of photo ``k`` at continuous pixel coordinates (x, y) (pixel centres at +0.5) and its
    derivatives along x and y. The caller keeps (x, y) at least half a pixel inside the photo."""
    xs = x - 0.5
    ys = y - 0.5
    x0 = int(wp.floor(xs))
    y0 = int(wp.floor(ys))
    fx = xs - float(x0)
    fy = ys - float(y0)
    a = images[k, y0, x0]
    b = images[k, y0, x0 + 1]
    c = images[k, y0 + 1, x0]
    d = images[k, y0 + 1, x0 + 1]
    top = a + fx * (b - a)
    bottom = c + fx * (d - c)
    return top + fy * (bottom - top), (b - a) + fy * ((d - c) - (b - a)), bottom - top


@wp.func
def texel_point(face: int, bary: wp.vec3, faces: wp.array(dtype=wp.vec3i), points: wp.array(dtype=wp.vec3)):
    f = faces[face]
    return bary[0] * points[f[0]] + bary[1] * points[f[1]] + bary[2] * points[f[2]]


@wp.func
def texel_normal(face: int, bary: wp.vec3, faces: wp.array(dtype=wp.vec3i), normals: wp.array(dtype=wp.vec3),
                 weld: wp.array(dtype=wp.int32)):
    f = faces[face]
    n = bary[0] * normals[weld[f[0]]] + bary[1] * normals[weld[f[1]]] + bary[2] * normals[weld[f[2]]]
    return wp.normalize(n)


@wp.struct
class Observation:
    """One texel seen in one photo: ``ok`` when it projects inside the photo's usable area, faces the
    camera and passes the depth test."""

    ok: int
    p_cam: wp.vec3
    value: wp.vec3
    grad_x: wp.vec3
    grad_y: wp.vec3
    shading: wp.vec3
    weight: float


@wp.func
def observe(infos: wp.array(dtype=ImageInfo), images: wp.array3d(dtype=wp.vec3),
            depth: wp.array3d(dtype=wp.float32), k: int, p: wp.vec3, n: wp.vec3, n_shade: wp.vec3,
            cos_view_min: float, depth_tol: float):
    """Texel at ``p`` in photo ``k``: its surface normal ``n`` decides whether the camera sees it and weighs
    the sample (the view cosine); its shading normal ``n_shade`` sets a known light's cosine."""
    ob = Observation()
    ob.ok = 0
    info = infos[k]
    pc = info.rot @ p + info.trans
    if pc[2] <= 0.0:
        return ob
    to_cam = wp.normalize(info.center - p)
    cos_view = wp.dot(n, to_cam)
    if cos_view < cos_view_min:
        return ob
    x = info.fx * pc[0] / pc[2] + info.cx
    y = info.fy * pc[1] / pc[2] + info.cy
    # one pixel of margin: the bilinear footprint and a step's worth of motion stay inside
    if x < 1.5 or y < 1.5 or x > float(info.width) - 1.5 or y > float(info.height) - 1.5:
        return ob
    x0 = int(wp.floor(x - 0.5))
    y0 = int(wp.floor(y - 0.5))
    # the fit's slack (fit/kernels/stream.py observe): a tap up to ~1.5 px away on a surface tilted by theta lies
    # (z / fx) tan(theta) deeper per pixel. Without it small photos keep only the surface facing each camera
    # within ~20 degrees (24x24 photos of a sphere: a held-out photo then shared no texel with the fitted ones,
    # issue 41); tan capped at 4 (76 degrees) so silhouettes still reject the background.
    tan_v = wp.min(wp.sqrt(wp.max(1.0 - cos_view * cos_view, 0.0)) / cos_view, 4.0)
    if not depth_consistent(depth, k, x0, y0, pc[2], depth_tol, 1.5 * pc[2] / info.fx * tan_v):
        return ob
    value, gx, gy = bilinear_with_gradient(images, k, x, y)
    shading = wp.vec3(info.exposure, info.exposure, info.exposure)
    if info.light_kind != 2:  # a known light: Lambertian shading (render/shading.py LIGHT_*)
        wi, irradiance, dist = incident_light(info.light_kind, info.light_vec, info.light_intensity, p)
        cos_light = wp.dot(n_shade, wi)
        if cos_light < 0.1:  # the fit's grazing-light rejection (StreamConfig.cos_light_min)
            return ob
        if wp.max(irradiance) <= 0.0:  # a no-flash photo (flash intensity 0): nothing lit to compare
            return ob
        shading = info.exposure * cos_light * irradiance
    ob.ok = 1
    ob.p_cam = pc
    ob.value = value
    ob.grad_x = gx
    ob.grad_y = gy
    ob.shading = shading
    ob.weight = cos_view
    return ob


@wp.func
def huber_weight(r: wp.vec3, scale: float):
    """IRLS weight of the Huber loss for residual norm |r| (1 inside ``scale``)."""
    m = wp.length(r)
    if m <= scale:
        return 1.0
    return scale / m


@wp.func
def huber_loss(r: wp.vec3, scale: float):
    m = wp.length(r)
    if m <= scale:
        return 0.5 * m * m
    return scale * (m - 0.5 * scale)


@wp.kernel
def texel_points_kernel(face: wp.array(dtype=wp.int32), bary: wp.array(dtype=wp.vec3),
                        faces: wp.array(dtype=wp.vec3i), points: wp.array(dtype=wp.vec3),
                        normals: wp.array(dtype=wp.vec3), weld: wp.array(dtype=wp.int32),
                        p_out: wp.array(dtype=wp.vec3), n_out: wp.array(dtype=wp.vec3)):
    t = wp.tid()
    p_out[t] = texel_point(face[t], bary[t], faces, points)
    n_out[t] = texel_normal(face[t], bary[t], faces, normals, weld)


@wp.kernel
def albedo_sums_kernel(infos: wp.array(dtype=ImageInfo), images: wp.array3d(dtype=wp.vec3),
                       depth: wp.array3d(dtype=wp.float32), role: wp.array(dtype=wp.int32),
                       p: wp.array(dtype=wp.vec3), n: wp.array(dtype=wp.vec3), ns: wp.array(dtype=wp.vec3),
                       cos_view_min: float, depth_tol: float, num: wp.array(dtype=wp.vec3),
                       den: wp.array(dtype=wp.vec3)):
    """Weighted least-squares sums of each texel's colour over the fitting photos: C = sum w s I / sum w s^2
    (``n``: the texels' surface normals, ``ns``: their shading normals)."""
    k, t = wp.tid()
    if role[k] != ROLE_FIT:
        return
    ob = observe(infos, images, depth, k, p[t], n[t], ns[t], cos_view_min, depth_tol)
    if ob.ok == 0:
        return
    s = ob.shading
    wp.atomic_add(num, t, ob.weight * wp.cw_mul(s, ob.value))
    wp.atomic_add(den, t, ob.weight * wp.cw_mul(s, s))


@wp.kernel
def albedo_kernel(num: wp.array(dtype=wp.vec3), den: wp.array(dtype=wp.vec3), colour: wp.array(dtype=wp.vec3),
                  known: wp.array(dtype=wp.int32)):
    t = wp.tid()
    d = den[t]
    if d[0] > 0.0 and d[1] > 0.0 and d[2] > 0.0:
        colour[t] = wp.cw_div(num[t], d)
        known[t] = 1
    else:
        colour[t] = wp.vec3(0.0)
        known[t] = 0


@wp.kernel
def pose_system_kernel(infos: wp.array(dtype=ImageInfo), images: wp.array3d(dtype=wp.vec3),
                       depth: wp.array3d(dtype=wp.float32), role: wp.array(dtype=wp.int32),
                       p: wp.array(dtype=wp.vec3), n: wp.array(dtype=wp.vec3), ns: wp.array(dtype=wp.vec3),
                       colour: wp.array(dtype=wp.vec3), known: wp.array(dtype=wp.int32), cos_view_min: float,
                       depth_tol: float, huber: float, with_system: int, system: wp.array2d(dtype=wp.float64),
                       objective: wp.array2d(dtype=wp.float64)):
    """Per photo: the Huber objective of its samples and their count (``objective[k]``: sum, count) and
    (``with_system``) the Gauss-Newton system of its pose update (omega, tau) (:data:`POSE_TERMS` entries)."""
    k, t = wp.tid()
    if role[k] == ROLE_UNUSED or known[t] == 0:
        return
    ob = observe(infos, images, depth, k, p[t], n[t], ns[t], cos_view_min, depth_tol)
    if ob.ok == 0:
        return
    r = ob.value - wp.cw_mul(ob.shading, colour[t])
    wp.atomic_add(objective, k, 0, wp.float64(ob.weight * huber_loss(r, huber)))
    wp.atomic_add(objective, k, 1, wp.float64(ob.weight))
    if with_system == 0:
        return
    info = infos[k]
    pc = ob.p_cam
    iz = 1.0 / pc[2]
    du = wp.vec3(info.fx * iz, 0.0, -info.fx * pc[0] * iz * iz)  # d x / d p_cam
    dv = wp.vec3(0.0, info.fy * iz, -info.fy * pc[1] * iz * iz)
    du_w = wp.cross(pc, du)  # d x / d omega: p_cam moves by omega x p_cam
    dv_w = wp.cross(pc, dv)
    w = ob.weight * huber_weight(r, huber)
    jac = MAT36()
    for c in range(3):
        gx = ob.grad_x[c]
        gy = ob.grad_y[c]
        for j in range(3):
            jac[c, j] = gx * du_w[j] + gy * dv_w[j]
            jac[c, j + 3] = gx * du[j] + gy * dv[j]
    for i in range(6):
        for j in range(i, 6):
            h = jac[0, i] * jac[0, j] + jac[1, i] * jac[1, j] + jac[2, i] * jac[2, j]
            wp.atomic_add(system, k, sym_index(i, j), wp.float64(w * h))
        g = jac[0, i] * r[0] + jac[1, i] * r[1] + jac[2, i] * r[2]
        wp.atomic_add(system, k, 21 + i, wp.float64(w * g))
    wp.atomic_add(system, k, 27, wp.float64(1.0))


@wp.func
def rotation_from_vector(w: wp.vec3):
    """exp([w]x) by Rodrigues' formula."""
    a = wp.length(w)
    if a < 1.0e-12:
        return wp.identity(n=3, dtype=float)
    axis = w / a
    kx = wp.skew(axis)
    return wp.identity(n=3, dtype=float) + wp.sin(a) * kx + (1.0 - wp.cos(a)) * (kx @ kx)


@wp.func
def orthonormalize(m: wp.mat33):
    """The nearest rotation to a nearly orthonormal matrix (rows re-orthogonalised; float32 drift only)."""
    r0 = wp.normalize(wp.vec3(m[0, 0], m[0, 1], m[0, 2]))
    r1 = wp.vec3(m[1, 0], m[1, 1], m[1, 2])
    r1 = wp.normalize(r1 - wp.dot(r1, r0) * r0)
    r2 = wp.cross(r0, r1)
    return wp.matrix_from_rows(r0, r1, r2)


@wp.kernel
def pose_step_kernel(system: wp.array2d(dtype=wp.float64), damping: wp.array(dtype=wp.float64),
                     max_rotation: float, max_translation: wp.array(dtype=float), min_samples: int,
                     light_attached: wp.array(dtype=wp.int32), light_offset: wp.array(dtype=wp.vec3),
                     infos: wp.array(dtype=ImageInfo), saved: wp.array(dtype=ImageInfo)):
    """Solve (J^T J + damping diag) delta = -J^T r per photo (Cholesky), clamp the step, apply it to the pose
    (and to a light fixed to the camera), keeping the old record in ``saved``."""
    k = wp.tid()
    saved[k] = infos[k]
    if system[k, 27] < wp.float64(min_samples):
        return
    a = MAT66D()
    b = VEC6D()
    lam = damping[k]
    for i in range(6):
        for j in range(i, 6):
            v = system[k, sym_index(i, j)]
            a[i, j] = v
            a[j, i] = v
        a[i, i] = a[i, i] * (wp.float64(1.0) + lam) + wp.float64(1.0e-12)
        b[i] = -system[k, 21 + i]
    # Cholesky a = L L^T in place (lower triangle), then two triangular solves
    for j in range(6):
        s = a[j, j]
        for m in range(j):
            s = s - a[j, m] * a[j, m]
        if s <= wp.float64(0.0):
            return
        ljj = wp.sqrt(s)
        a[j, j] = ljj
        for i in range(j + 1, 6):
            s2 = a[i, j]
            for m in range(j):
                s2 = s2 - a[i, m] * a[j, m]
            a[i, j] = s2 / ljj
    y = VEC6D()
    for i in range(6):
        s = b[i]
        for m in range(i):
            s = s - a[i, m] * y[m]
        y[i] = s / a[i, i]
    x = VEC6D()
    for ii in range(6):
        i = 5 - ii
        s = y[i]
        for m in range(i + 1, 6):
            s = s - a[m, i] * x[m]
        x[i] = s / a[i, i]
    omega = wp.vec3(float(x[0]), float(x[1]), float(x[2]))
    tau = wp.vec3(float(x[3]), float(x[4]), float(x[5]))
    lo = wp.length(omega)
    if lo > max_rotation:
        omega = omega * (max_rotation / lo)
    lt = wp.length(tau)
    if lt > max_translation[k]:
        tau = tau * (max_translation[k] / lt)
    info = infos[k]
    dr = rotation_from_vector(omega)
    info.rot = orthonormalize(dr @ info.rot)
    info.trans = dr @ info.trans + tau
    info.center = -(wp.transpose(info.rot) @ info.trans)
    if light_attached[k] != 0:
        info.light_vec = wp.transpose(info.rot) @ (light_offset[k] - info.trans)
    infos[k] = info


@wp.kernel
def pose_accept_kernel(before: wp.array2d(dtype=wp.float64), after: wp.array2d(dtype=wp.float64),
                       saved: wp.array(dtype=ImageInfo), infos: wp.array(dtype=ImageInfo),
                       damping: wp.array(dtype=wp.float64), accepted: wp.array(dtype=wp.int32)):
    """Keep a photo's step where its mean objective per sample fell (and trust the quadratic model more), else
    restore its pose and damp the next step ten times more."""
    k = wp.tid()
    if after[k, 0] * before[k, 1] <= before[k, 0] * after[k, 1]:
        damping[k] = wp.max(damping[k] * wp.float64(0.3), wp.float64(1.0e-6))
        accepted[k] = accepted[k] + 1
    else:
        infos[k] = saved[k]
        damping[k] = wp.min(damping[k] * wp.float64(10.0), wp.float64(1.0e8))


@wp.kernel
def vertex_system_kernel(infos: wp.array(dtype=ImageInfo), images: wp.array3d(dtype=wp.vec3),
                         depth: wp.array3d(dtype=wp.float32), role: wp.array(dtype=wp.int32),
                         face: wp.array(dtype=wp.int32), bary: wp.array(dtype=wp.vec3),
                         faces: wp.array(dtype=wp.vec3i), weld: wp.array(dtype=wp.int32),
                         direction: wp.array(dtype=wp.vec3), p: wp.array(dtype=wp.vec3),
                         n: wp.array(dtype=wp.vec3), ns: wp.array(dtype=wp.vec3),
                         colour: wp.array(dtype=wp.vec3), known: wp.array(dtype=wp.int32),
                         cos_view_min: float, depth_tol: float, huber: float,
                         curvature: wp.array(dtype=wp.float64), gradient: wp.array(dtype=wp.float64)):
    """Per welded vertex: the lumped diagonal of J^T J and J^T r of its displacement along ``direction`` over
    the fitting photos (a texel moves with the barycentric share of each of its face's vertices)."""
    k, t = wp.tid()
    if role[k] != ROLE_FIT or known[t] == 0:
        return
    ob = observe(infos, images, depth, k, p[t], n[t], ns[t], cos_view_min, depth_tol)
    if ob.ok == 0:
        return
    info = infos[k]
    r = ob.value - wp.cw_mul(ob.shading, colour[t])
    pc = ob.p_cam
    iz = 1.0 / pc[2]
    du = wp.transpose(info.rot) @ wp.vec3(info.fx * iz, 0.0, -info.fx * pc[0] * iz * iz)  # d x / d p (world)
    dv = wp.transpose(info.rot) @ wp.vec3(0.0, info.fy * iz, -info.fy * pc[1] * iz * iz)
    w = ob.weight * huber_weight(r, huber)
    f = faces[face[t]]
    b = bary[t]
    for c in range(3):
        v = weld[f[c]]
        e = direction[v]
        jr = ob.grad_x * wp.dot(du, e) + ob.grad_y * wp.dot(dv, e)  # d r / d (texel moved along e), per channel
        # the lumped (row-sum) diagonal: b_c (sum_j b_j) |jr|^2 with sum_j b_j = 1; the plain diagonal b_c^2 |jr|^2
        # would let the three vertices of a texel each take the whole step
        wp.atomic_add(curvature, v, wp.float64(w * b[c] * wp.dot(jr, jr)))
        wp.atomic_add(gradient, v, wp.float64(w * b[c] * wp.dot(jr, r)))


@wp.kernel
def mean_curvature_kernel(curvature: wp.array(dtype=wp.float64), out: wp.array(dtype=wp.float64)):
    """out[0] += curvature, out[1] += 1 over vertices some sample moves (for the smoothness's scale)."""
    v = wp.tid()
    c = curvature[v]
    if c > wp.float64(0.0):
        wp.atomic_add(out, 0, c)
        wp.atomic_add(out, 1, wp.float64(1.0))


@wp.kernel
def displacement_sweep_kernel(current: wp.array(dtype=wp.float64), curvature: wp.array(dtype=wp.float64),
                              gradient: wp.array(dtype=wp.float64), offsets: wp.array(dtype=wp.int32),
                              neighbours: wp.array(dtype=wp.int32), mean: wp.array(dtype=wp.float64),
                              smoothness: float, damping: wp.array(dtype=wp.float64), x_in: wp.array(dtype=wp.float64),
                              x_out: wp.array(dtype=wp.float64)):
    """One Jacobi sweep of the damped Gauss-Newton step with a graph-Laplacian smoothness on the
    displacements: minimises 1/2 (1 + damping) H (x - d)^2 + g (x - d) + lambda sum_edges (x_i - x_j)^2
    + mu x_i^2 per vertex, lambda = ``smoothness`` times the mean H, mu = 1e-3 lambda (keeps vertices no
    photo moves where their neighbours put them, and the whole surface from drifting)."""
    v = wp.tid()
    lam = wp.float64(smoothness) * mean[0] / wp.max(mean[1], wp.float64(1.0))
    mu = wp.float64(1.0e-3) * lam
    h = curvature[v] * (wp.float64(1.0) + damping[0])
    acc = h * current[v] - gradient[v]
    deg = wp.float64(0.0)
    for e in range(offsets[v], offsets[v + 1]):
        acc = acc + wp.float64(2.0) * lam * x_in[neighbours[e]]
        deg = deg + wp.float64(1.0)
    den = h + wp.float64(2.0) * lam * deg + wp.float64(2.0) * mu
    if den > wp.float64(0.0):
        x_out[v] = acc / den
    else:
        x_out[v] = current[v]


@wp.kernel
def apply_displacement_kernel(proposed: wp.array(dtype=wp.float64), max_step: float, max_total: float,
                              current: wp.array(dtype=wp.float64), saved: wp.array(dtype=wp.float64),
                              base: wp.array(dtype=wp.vec3), direction: wp.array(dtype=wp.vec3),
                              welded_points: wp.array(dtype=wp.vec3)):
    """Clamp each vertex's step and total displacement, keep the old value in ``saved``, move the vertex."""
    v = wp.tid()
    d = current[v]
    saved[v] = d
    x = wp.clamp(proposed[v], d - wp.float64(max_step), d + wp.float64(max_step))
    x = wp.clamp(x, wp.float64(-max_total), wp.float64(max_total))
    current[v] = x
    welded_points[v] = base[v] + float(x) * direction[v]


@wp.kernel
def scatter_points_kernel(welded_points: wp.array(dtype=wp.vec3), weld: wp.array(dtype=wp.int32),
                          points: wp.array(dtype=wp.vec3)):
    """Every mesh vertex takes its welded vertex's position (seams stay closed)."""
    i = wp.tid()
    points[i] = welded_points[weld[i]]


@wp.kernel
def displacement_accept_kernel(before: wp.array(dtype=wp.float64), after: wp.array(dtype=wp.float64),
                               saved: wp.array(dtype=wp.float64), current: wp.array(dtype=wp.float64),
                               base: wp.array(dtype=wp.vec3), direction: wp.array(dtype=wp.vec3),
                               welded_points: wp.array(dtype=wp.vec3), damping: wp.array(dtype=wp.float64),
                               accepted: wp.array(dtype=wp.int32)):
    """Keep the displacement step when the fitting photos' total objective fell, else restore it (one
    thread per welded vertex; thread 0 updates the damping and the count of kept steps)."""
    v = wp.tid()
    keep = step_kept(before, after)
    if not keep:
        current[v] = saved[v]
        welded_points[v] = base[v] + float(saved[v]) * direction[v]
    if v == 0:
        if keep:
            damping[0] = wp.max(damping[0] * wp.float64(0.3), wp.float64(1.0e-3))
            accepted[0] = accepted[0] + 1
        else:
            damping[0] = wp.min(damping[0] * wp.float64(10.0), wp.float64(1.0e6))


@wp.func
def step_kept(before: wp.array(dtype=wp.float64), after: wp.array(dtype=wp.float64)):
    """Whether a displacement step was kept (:func:`displacement_accept_kernel`'s test)."""
    return after[0] * before[1] <= before[0] * after[1]  # mean per sample: the visible set may change


@wp.kernel
def keep_depth_kernel(before: wp.array(dtype=wp.float64), after: wp.array(dtype=wp.float64),
                      saved: wp.array3d(dtype=wp.float32), depth: wp.array3d(dtype=wp.float32)):
    """The depth maps of the geometry a displacement step left: the step's own (in ``depth``) when it was kept,
    else those from before it (``saved``; the refused step restored the vertices to the bit)."""
    k, y, x = wp.tid()
    if not step_kept(before, after):
        depth[k, y, x] = saved[k, y, x]


@wp.kernel
def kept_objective_kernel(before: wp.array(dtype=wp.float64), after: wp.array(dtype=wp.float64),
                          obj_before: wp.array2d(dtype=wp.float64), obj_after: wp.array2d(dtype=wp.float64),
                          out: wp.array2d(dtype=wp.float64)):
    """Each photo's objective after a displacement step: the step's when it was kept, else the one before it."""
    k = wp.tid()
    if step_kept(before, after):
        out[k, 0] = obj_after[k, 0]
        out[k, 1] = obj_after[k, 1]
    else:
        out[k, 0] = obj_before[k, 0]
        out[k, 1] = obj_before[k, 1]


@wp.kernel
def total_kernel(per_photo: wp.array2d(dtype=wp.float64), role: wp.array(dtype=wp.int32), out: wp.array(dtype=wp.float64)):
    """out[0:2] += the objective and sample count of the fitting photos."""
    k = wp.tid()
    if role[k] == ROLE_FIT:
        wp.atomic_add(out, 0, per_photo[k, 0])
        wp.atomic_add(out, 1, per_photo[k, 1])


@wp.kernel
def vertex_total_kernel(per_vertex: wp.array2d(dtype=wp.float64), out: wp.array(dtype=wp.float64)):
    """out[0:2] += every vertex's share of the objective and of the sample weight."""
    v = wp.tid()
    wp.atomic_add(out, 0, per_vertex[v, 0])
    wp.atomic_add(out, 1, per_vertex[v, 1])


@wp.kernel
def blur_axis_kernel(src: wp.array3d(dtype=wp.vec3), weights: wp.array(dtype=float), radius: int, along_x: int,
                     widths: wp.array(dtype=wp.int32), heights: wp.array(dtype=wp.int32),
                     dst: wp.array3d(dtype=wp.vec3)):
    """One pass of a separable Gaussian, along x (``along_x``) or y, within each photo's own size (edges
    clamped; the padding beyond it zero)."""
    k, y, x = wp.tid()
    w = widths[k]
    h = heights[k]
    if x >= w or y >= h:
        dst[k, y, x] = wp.vec3(0.0)
        return
    acc = wp.vec3(0.0)
    for i in range(-radius, radius + 1):
        if along_x != 0:
            acc = acc + weights[i + radius] * src[k, y, wp.clamp(x + i, 0, w - 1)]
        else:
            acc = acc + weights[i + radius] * src[k, wp.clamp(y + i, 0, h - 1), x]
    dst[k, y, x] = acc


@wp.kernel
def subtract_kernel(b: wp.array3d(dtype=wp.vec3), a: wp.array3d(dtype=wp.vec3)):
    """a -= b (a photo's detail: its blur less a wider blur)."""
    k, y, x = wp.tid()
    a[k, y, x] = a[k, y, x] - b[k, y, x]
