"""Warp kernels of light field mapping (LFM) fitted by image streaming (fit/models/lfm/problem.py).

Layout (fit/models/lfm/problem.py ``LFMGeometry``): N compact atlas texels; each texel s owns three *slots*
3 s + j, one per vertex j of its owner face (the surface maps g_k^{(t, v_j)} laid out in the
atlas); V (welded) vertices, each with a view map of M = R x R texels per term. Parameters, all
float64 with the three colour channels in one ``vec3d`` (the channels are independent problems):

- ``diffuse`` (N,) the view-independent term d(s) (fixed during the fit: mean or minimum),
- ``G`` (3 N, K) surface maps, row = slot,
- ``H`` (V K, M) view maps, row = v K + k.

Per (vertex v, channel) the *patch* objective (Hillesland 2005 ch. 7: one optimization per vertex)

    E_v = 1/2 sum_photos sum_{slots of v's ring} (L_j(s) (y - e d(s)) - e sum_k g_k(slot) h_k^v(w_v))^2
          + lam/2 sum_k sum_{masked view-map edges (q, q')} (h_k[q] - h_k[q'])^2

with L_j the barycentric hat function, e the photo's exposure and w_v the photo's view direction in
v's frame (one direction per vertex and photo, as the dissertation fits). Patches share no
parameter, so per-patch step sizes and acceptance are exact.

Every reduction is a gather owned by one thread (no float atomics, deterministic). Photos go
through in batches (one launch per kernel per batch): ``slot_pass_batch_kernel`` (one thread per
texel, loops its three slots and the batch's photos) accumulates the surface-map gradient and the
slot's objective and curvature and writes the slot's weighted residual of each photo;
``view_gather_batch_kernel`` (one thread per vertex and photo) reduces those over the vertex's ring
through the index table ``ring_slots[ring_start[v]:ring_start[v + 1]]``;
``view_scatter_batch_kernel`` (one thread per view-map row) adds them, photo by photo, into the
photos' view-map taps; ``patch_reduce_kernel`` reduces per-slot sums into per-vertex ones.
"""

from __future__ import annotations

from typing import Any

import warp as wp

from texstream.fit.kernels import stream
from texstream.fit.kernels.overloads import declare
from texstream.render.camera import ImageInfo
from texstream.render.shading import bilinear_taps, surface_frame, texel_coords

wp.set_module_options({"enable_backward": False})

MAP_DISK = wp.constant(0)
"""Nusselt / disk mapping: (w_x, w_y) of the unit view direction, the hemisphere projected on its base"""
MAP_HEMIOCT = wp.constant(1)
"""hemi-octahedral mapping: (w_x, w_y) / (|w_x| + |w_y| + w_z), rotated 45 degrees to fill the square"""
LOOKUP_NEAREST = wp.constant(0)
LOOKUP_BILINEAR = wp.constant(1)


@wp.func
def view_map_coords(w: wp.vec3d, mapping: int, res: int):
    """Continuous view-map coordinates (texel centres at i + 0.5) of a local direction ``w``
    (z = the vertex normal; below-horizon directions are projected onto the horizon)."""
    z = wp.max(w[2], wp.float64(0.0))
    x = w[0]
    y = w[1]
    n = wp.sqrt(x * x + y * y + z * z)
    if n <= wp.float64(0.0):
        return wp.float64(0.5) * wp.float64(res), wp.float64(0.5) * wp.float64(res)
    x = x / n
    y = y / n
    z = z / n
    u = x
    v = y
    if mapping == MAP_HEMIOCT:
        s = wp.abs(x) + wp.abs(y) + z
        px = x / s
        py = y / s
        u = px + py
        v = px - py
    half = wp.float64(0.5) * wp.float64(res)
    return (u + wp.float64(1.0)) * half, (v + wp.float64(1.0)) * half


@wp.func
def view_taps(w: wp.vec3d, mapping: int, res: int, lookup: int):
    """(indices, weights) of the view-map texels a lookup of direction ``w`` reads (unused taps
    have weight 0 and index 0)."""
    cx, cy = view_map_coords(w, mapping, res)
    idx = wp.vec4i(0, 0, 0, 0)
    wt = wp.vec4d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
    hi = res - 1
    if lookup == LOOKUP_NEAREST:
        ix = wp.clamp(int(wp.floor(cx)), 0, hi)
        iy = wp.clamp(int(wp.floor(cy)), 0, hi)
        idx[0] = iy * res + ix
        wt[0] = wp.float64(1.0)
        return idx, wt
    fx = cx - wp.float64(0.5)
    fy = cy - wp.float64(0.5)
    x0f = wp.floor(fx)
    y0f = wp.floor(fy)
    ax = fx - x0f
    ay = fy - y0f
    x0 = int(x0f)
    y0 = int(y0f)
    x1 = wp.clamp(x0 + 1, 0, hi)
    y1 = wp.clamp(y0 + 1, 0, hi)
    x0 = wp.clamp(x0, 0, hi)
    y0 = wp.clamp(y0, 0, hi)
    one = wp.float64(1.0)
    idx = wp.vec4i(y0 * res + x0, y0 * res + x1, y1 * res + x0, y1 * res + x1)
    wt = wp.vec4d((one - ax) * (one - ay), ax * (one - ay), (one - ax) * ay, ax * ay)
    return idx, wt


@wp.func
def local_dir(d: wp.vec3d, t: wp.vec3d, b: wp.vec3d, n: wp.vec3d):
    return wp.vec3d(wp.dot(d, t), wp.dot(d, b), wp.dot(d, n))


@wp.kernel
def vertex_taps_kernel(vpos: wp.array(dtype=wp.vec3d), vtan: wp.array(dtype=wp.vec3d), vbit: wp.array(dtype=wp.vec3d),
                       vnrm: wp.array(dtype=wp.vec3d), cam: wp.vec3d, mapping: int, res: int, lookup: int,
                       tap_idx: wp.array(dtype=wp.vec4i), tap_w: wp.array(dtype=wp.vec4d)):
    """The view-map taps of one photo at every vertex: its view direction from the vertex."""
    v = wp.tid()
    d = wp.normalize(cam - vpos[v])
    idx, wt = view_taps(local_dir(d, vtan[v], vbit[v], vnrm[v]), mapping, res, lookup)
    tap_idx[v] = idx
    tap_w[v] = wt


@wp.func
def lookup_h(H: wp.array2d(dtype=wp.vec3d), row: int, idx: wp.vec4i, wt: wp.vec4d):
    return wt[0] * H[row, idx[0]] + wt[1] * H[row, idx[1]] + wt[2] * H[row, idx[2]] + wt[3] * H[row, idx[3]]


# ---- batched photo passes (fit/models/lfm/problem.py ``LFMProblem.evaluate``): a batch of B photos per launch.
# Per-photo scratch is flat: observations obs[b * N + s], slot residuals slot_res[slot * B + b] (the
# photos of one slot adjacent: the gather's threads (v, b) read them coalesced), gathered sums
# gathered[(v K + k) * B + b]; the view-map taps of every photo, computed once, taps[p * V + v].
# Every accumulator is updated in photo order, as a photo-at-a-time loop would: the same sums.


@wp.kernel
def vertex_taps_all_kernel(vpos: wp.array(dtype=wp.vec3d), vtan: wp.array(dtype=wp.vec3d),
                           vbit: wp.array(dtype=wp.vec3d), vnrm: wp.array(dtype=wp.vec3d),
                           cams: wp.array(dtype=wp.vec3d), mapping: int, res: int, lookup: int,
                           tap_idx: wp.array(dtype=wp.vec4i), tap_w: wp.array(dtype=wp.vec4d)):
    """The view-map taps of every (photo p, vertex v), written at p * V + v; dim = (P, V)."""
    p, v = wp.tid()
    n_v = vpos.shape[0]
    d = wp.normalize(cams[p] - vpos[v])
    idx, wt = view_taps(local_dir(d, vtan[v], vbit[v], vnrm[v]), mapping, res, lookup)
    tap_idx[p * n_v + v] = idx
    tap_w[p * n_v + v] = wt


@wp.kernel
def slot_pass_batch_kernel(obs_y: wp.array(dtype=Any), obs_e: wp.array(dtype=Any), obs_base: int,
                           n_batch: int, batch: int, p0: int, diffuse: wp.array(dtype=wp.vec3d),
                           slot_vertex: wp.array(dtype=wp.int32), slot_hat: wp.array(dtype=wp.float64),
                           G: wp.array2d(dtype=wp.vec3d), H: wp.array2d(dtype=wp.vec3d),
                           DG: wp.array2d(dtype=wp.vec3d), DH: wp.array2d(dtype=wp.vec3d),
                           tap_idx: wp.array(dtype=wp.vec4i), tap_w: wp.array(dtype=wp.vec4d),
                           n_vertices: int, n_terms: int, want_grad: int, want_dhd: int, want_diag: int,
                           first_texel: int,
                           slot_f: wp.array(dtype=wp.vec3d), grad_G: wp.array2d(dtype=wp.vec3d),
                           slot_dhd: wp.array(dtype=wp.vec3d), slot_gn: wp.array(dtype=wp.vec3d),
                           slot_res: wp.array(dtype=wp.vec3d), diag_G: wp.array2d(dtype=wp.vec3d)):
    """Photos p0 .. p0 + n_batch - 1, one thread per texel: accumulate over the texel's three slots
    the objective, the surface-map gradient (-e r h_k) and, with ``want_dhd``, the exact second
    derivative along the direction (DG, DH) (m1^2 - 2 r m2, with the model along the line
    m0 + a m1 + a^2 m2) and its Gauss-Newton part m1^2, each photo added in order (the objective and
    curvature sums in registers across the batch); with ``want_grad`` write each slot's e r of photo b
    at slot_res[slot * batch + b] (0 where unobserved) for the view-map gather. Texels from ``first_texel``
    (the CPU's threads take a range each, fit/models/lfm/problem.py)."""
    s = wp.tid() + first_texel
    n = diffuse.shape[0]
    zero = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
    two = wp.float64(2.0)
    half = wp.float64(0.5)
    d = diffuse[s]
    for j in range(3):
        slot = 3 * s + j
        v = slot_vertex[slot]
        hat = slot_hat[slot]
        f_acc = slot_f[slot]
        dhd_acc = zero
        gn_acc = zero
        if want_dhd != 0:
            dhd_acc = slot_dhd[slot]
            gn_acc = slot_gn[slot]
        for b in range(n_batch):
            o = (obs_base + b) * n + s
            e = wp.float64(obs_e[o])
            if e <= wp.float64(0.0):
                if want_grad != 0:
                    slot_res[slot * batch + b] = zero
                continue
            idx = tap_idx[(p0 + b) * n_vertices + v]
            wt = tap_w[(p0 + b) * n_vertices + v]
            target = hat * (wp.vec3d(obs_y[o]) - e * d)
            model = zero
            for k in range(n_terms):
                model = model + wp.cw_mul(G[slot, k], lookup_h(H, v * n_terms + k, idx, wt))
            r = target - e * model
            f_acc = f_acc + half * wp.cw_mul(r, r)
            if want_grad != 0:
                for k in range(n_terms):
                    grad_G[slot, k] = grad_G[slot, k] - e * wp.cw_mul(r, lookup_h(H, v * n_terms + k, idx, wt))
            if want_grad != 0:
                slot_res[slot * batch + b] = e * r     # for the view-map gather (gradient passes only)
            if want_diag != 0:
                for k in range(n_terms):
                    h = e * lookup_h(H, v * n_terms + k, idx, wt)
                    diag_G[slot, k] = diag_G[slot, k] + wp.cw_mul(h, h)
            if want_dhd != 0:
                m1 = zero
                m2 = zero
                for k in range(n_terms):
                    row = v * n_terms + k
                    h = lookup_h(H, row, idx, wt)
                    dh = lookup_h(DH, row, idx, wt)
                    m1 = m1 + wp.cw_mul(DG[slot, k], h) + wp.cw_mul(G[slot, k], dh)
                    m2 = m2 + wp.cw_mul(DG[slot, k], dh)
                m1 = e * m1
                m2 = e * m2
                dhd_acc = dhd_acc + wp.cw_mul(m1, m1) - two * wp.cw_mul(r, m2)
                gn_acc = gn_acc + wp.cw_mul(m1, m1)
        slot_f[slot] = f_acc
        if want_dhd != 0:
            slot_dhd[slot] = dhd_acc
            slot_gn[slot] = gn_acc


@wp.kernel
def view_gather_batch_kernel(ring_start: wp.array(dtype=wp.int32), ring_slots: wp.array(dtype=wp.int32),
                             slot_res: wp.array(dtype=wp.vec3d), batch: int, G: wp.array2d(dtype=wp.vec3d),
                             n_terms: int, want_diag: int, obs_e: wp.array(dtype=Any), obs_base: int, n_texels: int,
                             first_vertex: int,
                             gathered: wp.array(dtype=wp.vec3d), gathered_diag: wp.array(dtype=wp.vec3d)):
    """Per (vertex v, batch photo b): sum over v's ring of e r g_k (index table), for every term k,
    written at gathered[(v K + k) * batch + b]; dim = (V, n_batch). Threads of one vertex share the
    ring walk and read the batch's residuals of one slot side by side. With ``want_diag`` also the
    sum of (e g_k)^2 (the view maps' Gauss-Newton diagonal, before the taps' weights). Vertices from
    ``first_vertex`` (a CPU thread's range)."""
    v, b = wp.tid()
    v = v + first_vertex
    for k in range(n_terms):
        acc = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
        acc2 = acc
        for e in range(ring_start[v], ring_start[v + 1]):
            slot = ring_slots[e]
            acc = acc + wp.cw_mul(slot_res[slot * batch + b], G[slot, k])
            if want_diag != 0:
                ex = wp.float64(obs_e[(obs_base + b) * n_texels + slot / 3])
                eg = ex * G[slot, k]
                acc2 = acc2 + wp.cw_mul(eg, eg)
        gathered[(v * n_terms + k) * batch + b] = acc
        if want_diag != 0:
            gathered_diag[(v * n_terms + k) * batch + b] = acc2


@wp.kernel
def view_scatter_batch_kernel(gathered: wp.array(dtype=wp.vec3d), n_batch: int, batch: int, p0: int,
                              tap_idx: wp.array(dtype=wp.vec4i), tap_w: wp.array(dtype=wp.vec4d), n_terms: int,
                              n_vertices: int, want_diag: int, gathered_diag: wp.array(dtype=wp.vec3d),
                              grad_H: wp.array2d(dtype=wp.vec3d), diag_H: wp.array2d(dtype=wp.vec3d)):
    """Per view-map row (v K + k): the view-map gradient, each batch photo's gathered sum
    -sum_{ring slots} e r g_k subtracted, in photo order, at the photo's taps; with ``want_diag`` the
    Gauss-Newton diagonal, each tap's weight squared times the photo's sum of (e g_k)^2."""
    row = wp.tid()
    v = row / n_terms
    for b in range(n_batch):
        tap = (p0 + b) * n_vertices + v
        idx = tap_idx[tap]
        wt = tap_w[tap]
        acc = gathered[row * batch + b]
        for t in range(4):
            if wt[t] != wp.float64(0.0):
                grad_H[row, idx[t]] = grad_H[row, idx[t]] - wt[t] * acc
                if want_diag != 0:
                    diag_H[row, idx[t]] = diag_H[row, idx[t]] + (wt[t] * wt[t]) * gathered_diag[row * batch + b]


@wp.kernel
def jacobi_G_kernel(diag: wp.array2d(dtype=wp.vec3d), out: wp.array2d(dtype=wp.vec3d)):
    """The inverse of the surface maps' Gauss-Newton diagonal, 0 where it is 0 (no sample: the
    gradient is 0 there too)."""
    s, k = wp.tid()
    d = diag[s, k]
    o = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
    for c in range(3):
        if d[c] > wp.float64(0.0):
            o[c] = wp.float64(1.0) / d[c]
    out[s, k] = o


@wp.kernel
def jacobi_H_kernel(diag: wp.array2d(dtype=wp.vec3d), lap_diag: wp.array(dtype=wp.float64),
                    out: wp.array2d(dtype=wp.vec3d)):
    """The inverse of the view maps' diagonal: Gauss-Newton data part plus the Laplacian's exact
    diagonal ``lap_diag`` (lam times the texel's masked stencil neighbours), 0 where it is 0."""
    r, q = wp.tid()
    d = diag[r, q]
    o = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
    for c in range(3):
        x = d[c] + lap_diag[q]
        if x > wp.float64(0.0):
            o[c] = wp.float64(1.0) / x
    out[r, q] = o


@wp.kernel
def cw_mul_kernel(a: wp.array2d(dtype=wp.vec3d), b: wp.array2d(dtype=wp.vec3d), out: wp.array2d(dtype=wp.vec3d)):
    """out = a * b entrywise (the preconditioned gradient z = P g)."""
    i, j = wp.tid()
    out[i, j] = wp.cw_mul(a[i, j], b[i, j])


@wp.kernel
def patch_reduce_kernel(ring_start: wp.array(dtype=wp.int32), ring_slots: wp.array(dtype=wp.int32),
                        slot_a: wp.array(dtype=wp.vec3d), slot_b: wp.array(dtype=wp.vec3d),
                        slot_c: wp.array(dtype=wp.vec3d),
                        out_a: wp.array(dtype=wp.vec3d), out_b: wp.array(dtype=wp.vec3d),
                        out_c: wp.array(dtype=wp.vec3d)):
    """Per vertex, the sums of three per-slot quantities over its ring (objective, d^T H d, its
    Gauss-Newton part)."""
    v = wp.tid()
    zero = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
    a = zero
    b = zero
    c = zero
    for e in range(ring_start[v], ring_start[v + 1]):
        slot = ring_slots[e]
        a = a + slot_a[slot]
        b = b + slot_b[slot]
        c = c + slot_c[slot]
    out_a[v] = a
    out_b[v] = b
    out_c[v] = c


@wp.kernel
def laplacian_kernel(H: wp.array2d(dtype=wp.vec3d), DH: wp.array2d(dtype=wp.vec3d),
                     mask: wp.array(dtype=wp.int32), res: int, n_terms: int, lam: wp.float64, want_grad: int,
                     want_dhd: int, f: wp.array(dtype=wp.vec3d), grad_H: wp.array2d(dtype=wp.vec3d),
                     dhd: wp.array(dtype=wp.vec3d), gn: wp.array(dtype=wp.vec3d)):
    """Per vertex, the view maps' Laplacian regularization lam/2 sum over the masked stencil's
    edges (q, q+x), (q, q+y) of (h[q] - h[q'])^2: added to the patch objective, gradient and
    curvature (exact: the term is quadratic)."""
    v = wp.tid()
    half = wp.float64(0.5)
    fa = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
    ha = fa
    for k in range(n_terms):
        row = v * n_terms + k
        for q in range(res * res):
            if mask[q] == 0:
                continue
            qx = q % res
            for dirn in range(2):
                q2 = q + 1
                if dirn == 0:
                    if qx + 1 >= res:
                        continue
                else:
                    q2 = q + res
                    if q2 >= res * res:
                        continue
                if mask[q2] == 0:
                    continue
                diff = H[row, q] - H[row, q2]
                fa = fa + half * lam * wp.cw_mul(diff, diff)
                if want_grad != 0:
                    grad_H[row, q] = grad_H[row, q] + lam * diff
                    grad_H[row, q2] = grad_H[row, q2] - lam * diff
                if want_dhd != 0:
                    dd = DH[row, q] - DH[row, q2]
                    ha = ha + lam * wp.cw_mul(dd, dd)
    f[v] = f[v] + fa
    if want_dhd != 0:
        dhd[v] = dhd[v] + ha
        gn[v] = gn[v] + ha


@wp.kernel
def patch_dot_kernel(ring_start: wp.array(dtype=wp.int32), ring_slots: wp.array(dtype=wp.int32),
                     aG: wp.array2d(dtype=wp.vec3d), bG: wp.array2d(dtype=wp.vec3d),
                     aH: wp.array2d(dtype=wp.vec3d), bH: wp.array2d(dtype=wp.vec3d), n_terms: int, m: int,
                     out: wp.array(dtype=wp.vec3d)):
    """Per vertex (and channel), the dot product of two parameter vectors over the patch: its ring's
    surface-map slots and its view maps."""
    v = wp.tid()
    acc = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
    for e in range(ring_start[v], ring_start[v + 1]):
        slot = ring_slots[e]
        for k in range(n_terms):
            acc = acc + wp.cw_mul(aG[slot, k], bG[slot, k])
    for k in range(n_terms):
        row = v * n_terms + k
        for q in range(m):
            acc = acc + wp.cw_mul(aH[row, q], bH[row, q])
    out[v] = acc


@wp.kernel
def step_kernel(f: wp.array(dtype=wp.vec3d), slope: wp.array(dtype=wp.vec3d), dhd: wp.array(dtype=wp.vec3d),
                gn: wp.array(dtype=wp.vec3d), scale: wp.array(dtype=wp.vec3d), hessian: int,
                alpha: wp.array(dtype=wp.vec3d)):
    """Per patch step size: the Hessian step -slope / d^T H d (its Gauss-Newton part where the exact
    curvature is not positive) times the patch's backtracking scale, or the scale alone
    (``hessian`` 0: backtracking from the last accepted step); 0 where the direction does not descend."""
    v = wp.tid()
    a = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
    for c in range(3):
        if slope[v][c] < wp.float64(0.0):
            if hessian != 0:
                h = dhd[v][c]
                if h <= wp.float64(0.0):
                    h = gn[v][c]
                if h > wp.float64(0.0):
                    a[c] = -slope[v][c] / h * scale[v][c]
            else:
                a[c] = scale[v][c]
    alpha[v] = a


@wp.kernel
def trial_G_kernel(G: wp.array2d(dtype=wp.vec3d), DG: wp.array2d(dtype=wp.vec3d), alpha: wp.array(dtype=wp.vec3d),
                   slot_vertex: wp.array(dtype=wp.int32), lower: wp.float64, upper: wp.float64,
                   out: wp.array2d(dtype=wp.vec3d)):
    """trial = clamp(G + alpha_v DG) for every (slot, term)."""
    s, k = wp.tid()
    a = alpha[slot_vertex[s]]
    t = G[s, k] + wp.cw_mul(a, DG[s, k])
    out[s, k] = wp.vec3d(wp.clamp(t[0], lower, upper), wp.clamp(t[1], lower, upper), wp.clamp(t[2], lower, upper))


@wp.kernel
def trial_H_kernel(H: wp.array2d(dtype=wp.vec3d), DH: wp.array2d(dtype=wp.vec3d), alpha: wp.array(dtype=wp.vec3d),
                   n_terms: int, mask: wp.array(dtype=wp.int32), lower: wp.float64, upper: wp.float64,
                   out: wp.array2d(dtype=wp.vec3d)):
    """trial = clamp(H + alpha_v DH) for every (view-map row, texel); texels outside the mask stay."""
    r, q = wp.tid()
    if mask[q] == 0:
        out[r, q] = H[r, q]
        return
    a = alpha[r / n_terms]
    t = H[r, q] + wp.cw_mul(a, DH[r, q])
    out[r, q] = wp.vec3d(wp.clamp(t[0], lower, upper), wp.clamp(t[1], lower, upper), wp.clamp(t[2], lower, upper))


@wp.kernel
def accept_kernel(f: wp.array(dtype=wp.vec3d), f_trial: wp.array(dtype=wp.vec3d), alpha: wp.array(dtype=wp.vec3d),
                  unit_cap: int, accepted: wp.array(dtype=wp.vec3d), scale: wp.array(dtype=wp.vec3d),
                  fout: wp.array(dtype=wp.vec3d)):
    """Per patch and channel: accept the trial where it lowers the patch objective (dissertation
    Eq. 7.6) and the step was not zero; the backtracking scale halves on a rejection and grows
    back (x2; at most 1 with ``unit_cap``: the Hessian step, L-BFGS's quasi-Newton step) on an acceptance."""
    v = wp.tid()
    acc = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
    sc = scale[v]
    fo = f[v]
    for c in range(3):
        if alpha[v][c] != wp.float64(0.0) and f_trial[v][c] < f[v][c]:
            acc[c] = wp.float64(1.0)
            fo[c] = f_trial[v][c]
            sc[c] = sc[c] * wp.float64(2.0)
            if unit_cap != 0:
                sc[c] = wp.min(sc[c], wp.float64(1.0))
        elif alpha[v][c] != wp.float64(0.0):
            sc[c] = sc[c] * wp.float64(0.5)
    accepted[v] = acc
    scale[v] = sc
    fout[v] = fo


@wp.kernel
def adopt_G_kernel(src: wp.array2d(dtype=wp.vec3d), accepted: wp.array(dtype=wp.vec3d),
                   slot_vertex: wp.array(dtype=wp.int32), dst: wp.array2d(dtype=wp.vec3d)):
    """dst = src on accepted patches' channels (surface-map entries)."""
    s, k = wp.tid()
    a = accepted[slot_vertex[s]]
    one = wp.vec3d(wp.float64(1.0), wp.float64(1.0), wp.float64(1.0))
    dst[s, k] = wp.cw_mul(a, src[s, k]) + wp.cw_mul(one - a, dst[s, k])


@wp.kernel
def adopt_H_kernel(src: wp.array2d(dtype=wp.vec3d), accepted: wp.array(dtype=wp.vec3d), n_terms: int,
                   dst: wp.array2d(dtype=wp.vec3d)):
    """dst = src on accepted patches' channels (view-map entries)."""
    r, q = wp.tid()
    a = accepted[r / n_terms]
    one = wp.vec3d(wp.float64(1.0), wp.float64(1.0), wp.float64(1.0))
    dst[r, q] = wp.cw_mul(a, src[r, q]) + wp.cw_mul(one - a, dst[r, q])


@wp.kernel
def beta_kernel(gg_new: wp.array(dtype=wp.vec3d), gg_mixed: wp.array(dtype=wp.vec3d), gg_old: wp.array(dtype=wp.vec3d),
                accepted: wp.array(dtype=wp.vec3d), variant: int, beta: wp.array(dtype=wp.vec3d)):
    """Per patch CG beta: Polak-Ribiere+ max(0, g.(g - g_old) / g_old.g_old) (``variant`` 0) or
    Fletcher-Reeves g.g / g_old.g_old (1); 0 (steepest descent restart) where the last trial was
    rejected or g_old is 0. ``variant`` -1: steepest descent (always 0)."""
    v = wp.tid()
    b = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
    if variant >= 0:
        for c in range(3):
            if accepted[v][c] > wp.float64(0.0) and gg_old[v][c] > wp.float64(0.0):
                if variant == 0:
                    b[c] = wp.max((gg_new[v][c] - gg_mixed[v][c]) / gg_old[v][c], wp.float64(0.0))
                else:
                    b[c] = gg_new[v][c] / gg_old[v][c]
    beta[v] = b


@wp.kernel
def direction_G_kernel(g: wp.array2d(dtype=wp.vec3d), beta: wp.array(dtype=wp.vec3d),
                       slot_vertex: wp.array(dtype=wp.int32), d: wp.array2d(dtype=wp.vec3d)):
    """d = -g + beta_v d (surface-map entries)."""
    s, k = wp.tid()
    d[s, k] = -g[s, k] + wp.cw_mul(beta[slot_vertex[s]], d[s, k])


@wp.kernel
def direction_H_kernel(g: wp.array2d(dtype=wp.vec3d), beta: wp.array(dtype=wp.vec3d), n_terms: int,
                       mask: wp.array(dtype=wp.int32), d: wp.array2d(dtype=wp.vec3d)):
    """d = -g + beta_v d (view-map entries; 0 outside the mask)."""
    r, q = wp.tid()
    if mask[q] == 0:
        d[r, q] = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
        return
    d[r, q] = -g[r, q] + wp.cw_mul(beta[r / n_terms], d[r, q])


@wp.kernel
def sum_vec3_kernel(a: wp.array(dtype=wp.vec3d), n: int, out: wp.array(dtype=wp.float64)):
    """out[0] = sum over all entries and channels (one thread: deterministic; a trace read)."""
    acc = wp.float64(0.0)
    for i in range(n):
        acc = acc + a[i][0] + a[i][1] + a[i][2]
    out[0] = acc


@wp.kernel
def diffuse_accumulate_kernel(obs_y: wp.array(dtype=wp.vec3d), obs_e: wp.array(dtype=wp.float64), mode: int,
                              num: wp.array(dtype=wp.vec3d), den: wp.array(dtype=wp.float64)):
    """One photo, one thread per texel: for the mean (``mode`` 0) the least-squares constant
    sum e y / sum e^2; for the minimum (1) the running minimum of y / e (``den`` counts samples)."""
    s = wp.tid()
    e = obs_e[s]
    if e <= wp.float64(0.0):
        return
    if mode == 0:
        num[s] = num[s] + e * obs_y[s]
        den[s] = den[s] + e * e
    else:
        y = obs_y[s] / e
        if den[s] == wp.float64(0.0):
            num[s] = y
        else:
            num[s] = wp.vec3d(wp.min(num[s][0], y[0]), wp.min(num[s][1], y[1]), wp.min(num[s][2], y[2]))
        den[s] = den[s] + wp.float64(1.0)


@wp.kernel
def diffuse_finish_kernel(num: wp.array(dtype=wp.vec3d), den: wp.array(dtype=wp.float64), mode: int,
                          out: wp.array(dtype=wp.vec3d)):
    s = wp.tid()
    if den[s] <= wp.float64(0.0):
        out[s] = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
    elif mode == 0:
        out[s] = num[s] / den[s]
    else:
        out[s] = num[s]


@wp.func
def texel_radiance(c: int, diffuse: wp.array(dtype=wp.vec3d), slot_vertex: wp.array(dtype=wp.int32),
                   G: wp.array2d(dtype=wp.vec3d), H: wp.array2d(dtype=wp.vec3d),
                   vpos: wp.array(dtype=wp.vec3d), vtan: wp.array(dtype=wp.vec3d), vbit: wp.array(dtype=wp.vec3d),
                   vnrm: wp.array(dtype=wp.vec3d), cam: wp.vec3d, point: wp.vec3d, view_interp: int,
                   n_terms: int, mapping: int, res: int, lookup: int):
    """The LFM radiance of compact texel c seen from ``cam``: d + sum over its face's three vertices
    and the K terms of g h, each vertex's view map read along the direction from the vertex
    (``view_interp`` 0, as the fit) or from the shaded ``point`` (1), in the vertex's frame."""
    out = diffuse[c]
    for j in range(3):
        slot = 3 * c + j
        v = slot_vertex[slot]
        src = vpos[v]
        if view_interp != 0:
            src = point
        d = wp.normalize(cam - src)
        idx, wt = view_taps(local_dir(d, vtan[v], vbit[v], vnrm[v]), mapping, res, lookup)
        for k in range(n_terms):
            out = out + wp.cw_mul(G[slot, k], lookup_h(H, v * n_terms + k, idx, wt))
    return out


@wp.kernel
def sample_kernel(obs_y: wp.array(dtype=wp.vec3d), obs_e: wp.array(dtype=wp.float64),
                  diffuse: wp.array(dtype=wp.vec3d), slot_vertex: wp.array(dtype=wp.int32),
                  G: wp.array2d(dtype=wp.vec3d), H: wp.array2d(dtype=wp.vec3d),
                  vpos: wp.array(dtype=wp.vec3d), vtan: wp.array(dtype=wp.vec3d), vbit: wp.array(dtype=wp.vec3d),
                  vnrm: wp.array(dtype=wp.vec3d), texel_pos: wp.array(dtype=wp.vec3d), cam: wp.vec3d,
                  view_interp: int, n_terms: int, mapping: int, res: int, lookup: int,
                  sse: wp.array(dtype=wp.vec3d), count: wp.array(dtype=wp.float64)):
    """One photo, one thread per texel: squared error of the full model (the sum of the texel's three
    vertex light fields plus d) against the photo's sample, accumulated per texel (sample PSNR)."""
    s = wp.tid()
    e = obs_e[s]
    if e <= wp.float64(0.0):
        return
    f = texel_radiance(s, diffuse, slot_vertex, G, H, vpos, vtan, vbit, vnrm, cam, texel_pos[s], view_interp,
                       n_terms, mapping, res, lookup)
    r = obs_y[s] - e * f
    sse[s] = sse[s] + wp.cw_mul(r, r)
    count[s] = count[s] + wp.float64(1.0)


observe_radiance = stream.observe_func(True)


@wp.kernel
def observe_kernel(tex: stream.TexelFrames, images: wp.array3d(dtype=wp.vec3), depth: wp.array3d(dtype=wp.float32),
                   shadow: wp.array3d(dtype=wp.float32), infos: wp.array(dtype=ImageInfo), k: int,
                   opt: stream.SampleOptions, obs_y: wp.array(dtype=wp.vec3d), obs_e: wp.array(dtype=wp.float64)):
    """The distribution step of one photo (fit/kernels/stream.py ``observe``, light-free): per texel
    the photo's value and the exposure, 0 where the texel is not seen (occluded, masked, grazing,
    saturated or outside the photo)."""
    s = wp.tid()
    ok, y, w, u, v, xs, ys = observe_radiance(images, depth, shadow, infos, k, tex, s, opt)
    if ok:
        obs_y[s] = wp.vec3d(wp.float64(y[0]), wp.float64(y[1]), wp.float64(y[2]))
        obs_e[s] = wp.float64(w[0])
    else:
        obs_y[s] = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
        obs_e[s] = wp.float64(0.0)


@wp.kernel
def observe_batch_kernel(tex: stream.TexelFrames, images: wp.array3d(dtype=wp.vec3),
                         depth: wp.array3d(dtype=wp.float32), shadow: wp.array3d(dtype=wp.float32),
                         infos: wp.array(dtype=ImageInfo), p0: int, opt: stream.SampleOptions,
                         obs_y: wp.array(dtype=wp.vec3), obs_e: wp.array(dtype=wp.float32)):
    """:func:`observe_kernel` for photos p0 + b, written at b * N + s in float32 (the distribution
    step's own precision: exact); dim = (n_batch, N)."""
    b, s = wp.tid()
    n = tex.pos.shape[0]
    ok, y, w, u, v, xs, ys = observe_radiance(images, depth, shadow, infos, p0 + b, tex, s, opt)
    o = b * n + s
    if ok:
        obs_y[o] = y
        obs_e[o] = w[0]
    else:
        obs_y[o] = wp.vec3(0.0)
        obs_e[o] = 0.0


@wp.kernel
def render_lfm_kernel(mesh_id: wp.uint64, points: wp.array(dtype=wp.vec3), indices: wp.array(dtype=wp.int32),
                      normals: wp.array(dtype=wp.vec3), uvs: wp.array(dtype=wp.vec2),
                      grid_source: wp.array(dtype=wp.int32), tex_w: int, tex_h: int, surface_bilinear: int,
                      diffuse: wp.array(dtype=wp.vec3d), slot_vertex: wp.array(dtype=wp.int32),
                      G: wp.array2d(dtype=wp.vec3d), H: wp.array2d(dtype=wp.vec3d),
                      vpos: wp.array(dtype=wp.vec3d), vtan: wp.array(dtype=wp.vec3d), vbit: wp.array(dtype=wp.vec3d),
                      vnrm: wp.array(dtype=wp.vec3d), cam: ImageInfo, view_interp: int, n_terms: int,
                      mapping: int, res: int, lookup: int,
                      radiance: wp.array2d(dtype=wp.vec3), mask: wp.array2d(dtype=wp.uint8)):
    """Render an LFM model (radiance, no exposure); dim = (height, width). The atlas lookup reads the
    nearest texel or blends the four around the hit's UV; each tap is the full model of its compact
    texel (:func:`texel_radiance`), padding texels read the texel they copy (``grid_source``, -1:
    none, skipped and the weights renormalised)."""
    j, i = wp.tid()
    d_cam = wp.vec3((float(i) + 0.5 - cam.cx) / cam.fx, (float(j) + 0.5 - cam.cy) / cam.fy, 1.0)
    rt = wp.transpose(cam.rot)
    origin = -(rt @ cam.trans)
    d = wp.normalize(rt @ d_cam)
    radiance[j, i] = wp.vec3(0.0)
    mask[j, i] = wp.uint8(0)
    hit = wp.mesh_query_ray(mesh_id, origin, d, 1.0e30)
    if not hit.result:
        return
    pos, uv, n, tg, bt = surface_frame(points, indices, normals, uvs, hit.face, hit.u, hit.v)
    x, y = texel_coords(uv, tex_w, tex_h)
    camd = wp.vec3d(wp.float64(origin[0]), wp.float64(origin[1]), wp.float64(origin[2]))
    pd = wp.vec3d(wp.float64(pos[0]), wp.float64(pos[1]), wp.float64(pos[2]))
    acc = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
    wsum = wp.float64(0.0)
    if surface_bilinear == 0:
        xi = wp.clamp(int(wp.floor(x + 0.5)), 0, tex_w - 1)
        yi = wp.clamp(int(wp.floor(y + 0.5)), 0, tex_h - 1)
        c = grid_source[yi * tex_w + xi]
        if c >= 0:
            acc = texel_radiance(c, diffuse, slot_vertex, G, H, vpos, vtan, vbit, vnrm, camd, pd, view_interp,
                                 n_terms, mapping, res, lookup)
            wsum = wp.float64(1.0)
    else:
        x0, y0, fx, fy = bilinear_taps(x, y, tex_w, tex_h)
        for t in range(4):
            xi = x0 + t % 2
            yi = y0 + t / 2
            wx = fx
            if t % 2 == 0:
                wx = 1.0 - fx
            wy = fy
            if t / 2 == 0:
                wy = 1.0 - fy
            w = wp.float64(wx * wy)
            c = grid_source[yi * tex_w + xi]
            if c >= 0 and w > wp.float64(0.0):
                acc = acc + w * texel_radiance(c, diffuse, slot_vertex, G, H, vpos, vtan, vbit, vnrm, camd, pd,
                                               view_interp, n_terms, mapping, res, lookup)
                wsum = wsum + w
    if wsum <= wp.float64(0.0):
        return
    acc = acc / wsum
    # radiance is not negative: the mean-subtracted terms may extrapolate below 0 in unseen directions
    acc = wp.vec3d(wp.max(acc[0], wp.float64(0.0)), wp.max(acc[1], wp.float64(0.0)), wp.max(acc[2], wp.float64(0.0)))
    mask[j, i] = wp.uint8(1)
    radiance[j, i] = wp.vec3(float(acc[0]), float(acc[1]), float(acc[2]))


@wp.kernel
def balance_kernel(ring_start: wp.array(dtype=wp.int32), ring_slots: wp.array(dtype=wp.int32), n_terms: int, m: int,
                   shrink_only: int, G: wp.array2d(dtype=wp.vec3d), H: wp.array2d(dtype=wp.vec3d)):
    """Per vertex, term and channel, fix the scale gauge of g h (g c, h / c leave the data term
    unchanged): scale so that the patch's surface-map and view-map norms are equal (better
    conditioned for CG). With ``shrink_only`` (a view-map Laplacian in the objective: it costs
    1 / c^2 as much at h / c) only c >= 1 is applied, so the objective never rises."""
    v = wp.tid()
    for k in range(n_terms):
        ng = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
        nh = ng
        for e in range(ring_start[v], ring_start[v + 1]):
            ng = ng + wp.cw_mul(G[ring_slots[e], k], G[ring_slots[e], k])
        row = v * n_terms + k
        for q in range(m):
            nh = nh + wp.cw_mul(H[row, q], H[row, q])
        sc = wp.vec3d(wp.float64(1.0), wp.float64(1.0), wp.float64(1.0))
        for c in range(3):
            if ng[c] > wp.float64(0.0) and nh[c] > wp.float64(0.0):
                sc[c] = wp.pow(nh[c] / ng[c], wp.float64(0.25))
                if shrink_only != 0:
                    sc[c] = wp.max(sc[c], wp.float64(1.0))
        for e in range(ring_start[v], ring_start[v + 1]):
            G[ring_slots[e], k] = wp.cw_mul(G[ring_slots[e], k], sc)
        for q in range(m):
            H[row, q] = wp.cw_div(H[row, q], sc)


# the generic batched passes' overloads for the run's photo samples (fit/models/lfm/problem.py PhotoSamples
# obs_types: the distribution step's float32), in the module before its first launch: declared at a launch, each
# added the module's rehash and a second and third compile of this large module (fit/kernels/overloads.py)
declare(slot_pass_batch_kernel, obs_y=wp.vec3, obs_e=wp.float32)
declare(view_gather_batch_kernel, obs_e=wp.float32)
