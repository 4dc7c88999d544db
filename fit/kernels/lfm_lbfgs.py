"""Warp kernels of the light field mapping fit's L-BFGS optimizer (fit/models/lfm/problem.py ``fit_lfm``, optimizer lbfgs).

Beside the steepest-descent and conjugate-gradient kernels of :mod:`texstream.fit.kernels.lfm`: every
(vertex, channel) patch keeps its own history of the last m pairs (s, y) = (step, gradient change) of its
accepted iterations, in ring buffers over the whole parameter vector: hist_s_G / hist_y_G (m, 3 N, K) and
hist_s_H / hist_y_H (m, V K, M), with ``count`` (V,) vec3i pairs pushed per patch and channel: patch (v, c)'s
pair of age a (0 = newest) sits in ring slot (count[v][c] - 1 - a) mod m, valid while a < min(count, m).
``rho`` (m, V) holds 1 / s.y per slot and channel.
"""

from __future__ import annotations

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.func
def ring_slot(count: int, age: int, m: int):
    """The ring slot of the pair of ``age`` (0 = newest) with ``count`` pairs pushed; -1 if none."""
    if age >= count or age >= m:
        return -1
    return (count - 1 - age) % m


@wp.func
def push_history(x: wp.array2d(dtype=wp.vec3d), tx: wp.array2d(dtype=wp.vec3d), gx: wp.array2d(dtype=wp.vec3d),
                 tgx: wp.array2d(dtype=wp.vec3d), accepted: wp.vec3d, count: wp.vec3i, m: int, i: int, j: int,
                 hist_s: wp.array3d(dtype=wp.vec3d), hist_y: wp.array3d(dtype=wp.vec3d)):
    """Entry (i, j) of one L-BFGS pair, per channel c whose patch accepted its step: s = tx - x, y = tgx - gx
    into the patch channel's ring slot count mod m."""
    for c in range(3):
        if accepted[c] > wp.float64(0.0):
            q = count[c] % m
            a = hist_s[q, i, j]
            b = hist_y[q, i, j]
            a[c] = tx[i, j][c] - x[i, j][c]
            b[c] = tgx[i, j][c] - gx[i, j][c]
            hist_s[q, i, j] = a
            hist_y[q, i, j] = b


@wp.kernel
def lbfgs_push_G_kernel(G: wp.array2d(dtype=wp.vec3d), TG: wp.array2d(dtype=wp.vec3d),
                        gG: wp.array2d(dtype=wp.vec3d), tgG: wp.array2d(dtype=wp.vec3d),
                        accepted: wp.array(dtype=wp.vec3d), count: wp.array(dtype=wp.vec3i),
                        slot_vertex: wp.array(dtype=wp.int32), m: int,
                        hist_s: wp.array3d(dtype=wp.vec3d), hist_y: wp.array3d(dtype=wp.vec3d)):
    """Before adoption: write s = TG - G, y = tgG - gG into ring slot count mod m of every accepted
    patch channel (surface-map entries)."""
    s, k = wp.tid()
    push_history(G, TG, gG, tgG, accepted[slot_vertex[s]], count[slot_vertex[s]], m, s, k, hist_s, hist_y)


@wp.kernel
def lbfgs_push_H_kernel(H: wp.array2d(dtype=wp.vec3d), TH: wp.array2d(dtype=wp.vec3d),
                        gH: wp.array2d(dtype=wp.vec3d), tgH: wp.array2d(dtype=wp.vec3d),
                        accepted: wp.array(dtype=wp.vec3d), count: wp.array(dtype=wp.vec3i), n_terms: int, m: int,
                        hist_s: wp.array3d(dtype=wp.vec3d), hist_y: wp.array3d(dtype=wp.vec3d)):
    """The view-map entries of :func:`lbfgs_push_G_kernel`."""
    r, q2 = wp.tid()
    push_history(H, TH, gH, tgH, accepted[r / n_terms], count[r / n_terms], m, r, q2, hist_s, hist_y)


@wp.func
def history_dot(ring_start: wp.array(dtype=wp.int32), ring_slots: wp.array(dtype=wp.int32),
                aG: wp.array3d(dtype=wp.vec3d), aH: wp.array3d(dtype=wp.vec3d), qa: wp.vec3i,
                bG: wp.array2d(dtype=wp.vec3d), bH: wp.array2d(dtype=wp.vec3d), v: int, n_terms: int, n_view: int):
    """Per channel c, the patch dot product of history slot qa[c] of (aG, aH) with (bG, bH)
    (0 for a channel whose slot is -1)."""
    acc = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
    for e in range(ring_start[v], ring_start[v + 1]):
        slot = ring_slots[e]
        for k in range(n_terms):
            for c in range(3):
                if qa[c] >= 0:
                    acc[c] = acc[c] + aG[qa[c], slot, k][c] * bG[slot, k][c]
    for k in range(n_terms):
        row = v * n_terms + k
        for q in range(n_view):
            for c in range(3):
                if qa[c] >= 0:
                    acc[c] = acc[c] + aH[qa[c], row, q][c] * bH[row, q][c]
    return acc


@wp.kernel
def lbfgs_finish_push_kernel(ring_start: wp.array(dtype=wp.int32), ring_slots: wp.array(dtype=wp.int32),
                             hist_s_G: wp.array3d(dtype=wp.vec3d), hist_s_H: wp.array3d(dtype=wp.vec3d),
                             hist_y_G: wp.array3d(dtype=wp.vec3d), hist_y_H: wp.array3d(dtype=wp.vec3d),
                             accepted: wp.array(dtype=wp.vec3d), alpha: wp.array(dtype=wp.vec3d), n_terms: int,
                             n_view: int, m: int, count: wp.array(dtype=wp.vec3i), rho: wp.array2d(dtype=wp.vec3d),
                             gamma: wp.array(dtype=wp.vec3d)):
    """Per patch: keep the pair just written (count += 1, rho = 1 / s.y, initial scaling
    gamma = s.y / y.y) where the step was accepted and s.y > 0 (the curvature condition; a pair that
    fails it is overwritten by the next one). A rejected trial keeps the history: the same direction
    is tried again with the halved step (a backtracking line search). A channel that took no step
    (its direction did not descend) restarts from steepest descent (count = 0)."""
    v = wp.tid()
    slot = wp.vec3i(-1, -1, -1)
    cnt = count[v]
    for c in range(3):
        if accepted[v][c] > wp.float64(0.0):
            slot[c] = cnt[c] % m
    sy = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
    yy = sy
    for e in range(ring_start[v], ring_start[v + 1]):
        sl = ring_slots[e]
        for k in range(n_terms):
            for c in range(3):
                if slot[c] >= 0:
                    a = hist_s_G[slot[c], sl, k][c]
                    b = hist_y_G[slot[c], sl, k][c]
                    sy[c] = sy[c] + a * b
                    yy[c] = yy[c] + b * b
    for k in range(n_terms):
        row = v * n_terms + k
        for q in range(n_view):
            for c in range(3):
                if slot[c] >= 0:
                    a = hist_s_H[slot[c], row, q][c]
                    b = hist_y_H[slot[c], row, q][c]
                    sy[c] = sy[c] + a * b
                    yy[c] = yy[c] + b * b
    g = gamma[v]
    for c in range(3):
        if slot[c] >= 0:
            if sy[c] > wp.float64(0.0) and yy[c] > wp.float64(0.0):
                r = rho[slot[c], v]
                r[c] = wp.float64(1.0) / sy[c]
                rho[slot[c], v] = r
                g[c] = sy[c] / yy[c]
                cnt[c] = cnt[c] + 1
        elif alpha[v][c] == wp.float64(0.0):
            cnt[c] = 0
    count[v] = cnt
    gamma[v] = g


@wp.kernel
def lbfgs_coef_kernel(ring_start: wp.array(dtype=wp.int32), ring_slots: wp.array(dtype=wp.int32),
                      hist_G: wp.array3d(dtype=wp.vec3d), hist_H: wp.array3d(dtype=wp.vec3d),
                      qG: wp.array2d(dtype=wp.vec3d), qH: wp.array2d(dtype=wp.vec3d), count: wp.array(dtype=wp.vec3i),
                      rho: wp.array2d(dtype=wp.vec3d), age: int, m: int, n_terms: int, n_view: int, second: int,
                      alpha_hist: wp.array2d(dtype=wp.vec3d), coef: wp.array(dtype=wp.vec3d)):
    """One step of the two-loop recursion, per patch: the first loop (``second`` 0) sets
    a = rho (s . q) for the pair of ``age`` (kept in ``alpha_hist[age]``) and coef = -a (q -= a y);
    the second loop sets coef = a - rho (y . r) (r += coef s). coef is 0 where the patch has no
    pair of that age."""
    v = wp.tid()
    slot = wp.vec3i(-1, -1, -1)
    for c in range(3):
        slot[c] = ring_slot(count[v][c], age, m)
    d = history_dot(ring_start, ring_slots, hist_G, hist_H, slot, qG, qH, v, n_terms, n_view)
    out = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
    a = alpha_hist[age, v]
    for c in range(3):
        if slot[c] >= 0:
            rc = rho[slot[c], v][c]
            if second == 0:
                a[c] = rc * d[c]
                out[c] = -a[c]
            else:
                out[c] = a[c] - rc * d[c]
    if second == 0:
        alpha_hist[age, v] = a
    coef[v] = out


@wp.kernel
def lbfgs_axpy_G_kernel(hist: wp.array3d(dtype=wp.vec3d), count: wp.array(dtype=wp.vec3i), coef: wp.array(dtype=wp.vec3d),
                        age: int, m: int, slot_vertex: wp.array(dtype=wp.int32), q: wp.array2d(dtype=wp.vec3d)):
    """q += coef_v * (the patch's history pair of ``age``) on surface-map entries."""
    s, k = wp.tid()
    v = slot_vertex[s]
    out = q[s, k]
    for c in range(3):
        slot = ring_slot(count[v][c], age, m)
        if slot >= 0:
            out[c] = out[c] + coef[v][c] * hist[slot, s, k][c]
    q[s, k] = out


@wp.kernel
def lbfgs_axpy_H_kernel(hist: wp.array3d(dtype=wp.vec3d), count: wp.array(dtype=wp.vec3i), coef: wp.array(dtype=wp.vec3d),
                        age: int, m: int, n_terms: int, q: wp.array2d(dtype=wp.vec3d)):
    """q += coef_v * (the patch's history pair of ``age``) on view-map entries."""
    r, j = wp.tid()
    v = r / n_terms
    out = q[r, j]
    for c in range(3):
        slot = ring_slot(count[v][c], age, m)
        if slot >= 0:
            out[c] = out[c] + coef[v][c] * hist[slot, r, j][c]
    q[r, j] = out


@wp.kernel
def lbfgs_scale_G_kernel(gamma: wp.array(dtype=wp.vec3d),
                         slot_vertex: wp.array(dtype=wp.int32), q: wp.array2d(dtype=wp.vec3d)):
    """q = gamma_v q (the initial inverse Hessian gamma I) on surface-map entries."""
    s, k = wp.tid()
    q[s, k] = wp.cw_mul(gamma[slot_vertex[s]], q[s, k])


@wp.kernel
def lbfgs_scale_H_kernel(gamma: wp.array(dtype=wp.vec3d), n_terms: int, mask: wp.array(dtype=wp.int32),
                         q: wp.array2d(dtype=wp.vec3d)):
    """q = gamma_v q on view-map entries (0 outside the view-map mask)."""
    r, j = wp.tid()
    if mask[j] == 0:
        q[r, j] = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
        return
    q[r, j] = wp.cw_mul(gamma[r / n_terms], q[r, j])


@wp.kernel
def negate_kernel(a: wp.array2d(dtype=wp.vec3d)):
    """a = -a (the L-BFGS direction from the two-loop product)."""
    i, j = wp.tid()
    a[i, j] = -a[i, j]


@wp.kernel
def lbfgs_gamma_start_kernel(gg: wp.array(dtype=wp.vec3d), gamma: wp.array(dtype=wp.vec3d)):
    """gamma = 1 / |g| per patch channel (a first step of unit length; 0 where g = 0)."""
    v = wp.tid()
    out = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
    for c in range(3):
        if gg[v][c] > wp.float64(0.0):
            out[c] = wp.float64(1.0) / wp.sqrt(gg[v][c])
    gamma[v] = out
