"""Per-texel optimizer kernels: trial points, acceptance (Alg. 11), directions (Alg. 10),
L-BFGS two-loop recursion, damped Gauss-Newton solves, penalties and deterministic reductions.

State is batched: one thread per texel works on its own fixed-length parameter vectors
(sized to the layout, ``lafortune_grad.param_types``), so there is never a Python loop over texels. Column masks (``free``)
keep frozen parameters (the Lafortune scale gauge) fixed.
"""

from __future__ import annotations

from typing import Any

import warp as wp

from texstream.fit.kernels.overloads import STORAGE_SCALAR, at_every_count, declare, param_overload

# no kernel here is differentiated (the fit writes its own derivatives): skipping Warp's adjoint
# code generation roughly halves compile time
wp.set_module_options({"enable_backward": False})


@wp.func
def masked(v: Any, free: Any):
    return wp.cw_mul(v, free)


@wp.func
def energy_bound(t: Any, n_lobes: int, lobe_stride: int, albedo_max: float):
    """Cap each lobe's rho_s,c at albedo_max (n + 2) / (2 pi) (see models.energy_bound_numpy)."""
    out = t
    if albedo_max > 0.0:
        for j in range(n_lobes):
            o = 3 + j * lobe_stride
            cap = type(t[0])(albedo_max) * (t[o + lobe_stride - 1] + type(t[0])(2.0)) / type(t[0])(2.0 * wp.pi)
            for c in range(3):
                out[o + c] = wp.min(out[o + c], cap)
    return out


@wp.kernel(enable_backward=False, module="unique")
def trial_kernel(p: wp.array(dtype=Any), d: wp.array(dtype=Any), alpha: wp.array(dtype=Any),
                 lower: Any, upper: Any, free: Any, active: wp.array(dtype=wp.int32), n_params: int,
                 n_lobes: int, lobe_stride: int, albedo_max: float,
                 trial: wp.array(dtype=Any), storage: wp.array2d(dtype=Any)):
    """trial = project(p + alpha d): clamped to the hard bounds, then each lobe's rho_s capped by
    the energy bound (a feasible point, not the Euclidean projection; acceptance still compares
    objectives, so steps stay monotone). Also written in the storage precision; the trial vector
    holds exactly what the storage holds. Inactive texels copy ``p`` unchanged."""
    i = wp.tid()
    t = p[i]
    if active[i] != 0:
        t = wp.max(wp.min(p[i] + alpha[i] * masked(d[i], free), upper), lower)
        t = energy_bound(t, n_lobes, lobe_stride, albedo_max)
    for k in range(n_params):
        storage[i, k] = type(storage[i, k])(t[k])
        t[k] = type(t[k])(storage[i, k])
    trial[i] = t


@wp.kernel
def guess_from_samples_kernel(low: wp.array(dtype=wp.vec3), high: wp.array(dtype=wp.vec3),
                              count: wp.array(dtype=wp.int32), defaults: wp.array(dtype=wp.float64),
                              lower: wp.array(dtype=wp.float64), upper: wp.array(dtype=wp.float64),
                              percentile: int, n_lobes: int, lobe_stride: int, min_excess: wp.float64,
                              guess: wp.array2d(dtype=wp.float64)):
    """The starting parameters from the initial guess's pass (fitter.fit_start), in float64: the defaults,
    and for seen texels with ``percentile`` the low sample clipped to its bounds as the diffuse term (or
    radiance) and each lobe j's rho_s at max(high - low, ``min_excess``) / (j + 1), the excess of the
    brightest sample (a lobe peaks at rho_s). ``min_excess`` comes from the host: a literal here would be
    a float32 constant."""
    i = wp.tid()
    for k in range(guess.shape[1]):
        guess[i, k] = defaults[k]
    if percentile != 0 and count[i] > 0:
        lo = low[i]
        hi = high[i]
        for c in range(3):
            sample_low = wp.float64(lo[c])
            guess[i, c] = wp.min(wp.max(sample_low, lower[c]), upper[c])
            excess = wp.max(wp.float64(hi[c]) - sample_low, min_excess)
            for j in range(n_lobes):
                guess[i, 3 + j * lobe_stride + c] = excess / wp.float64(j + 1)


@wp.kernel(enable_backward=False, module="unique")
def start_point_kernel(guess: wp.array2d(dtype=wp.float64), lower: wp.array(dtype=wp.float64),
                       upper: wp.array(dtype=wp.float64), n_lobes: int, lobe_stride: int,
                       albedo_max: wp.float64, two_pi: wp.float64, count: wp.array(dtype=wp.int32),
                       p: wp.array(dtype=Any), storage: wp.array2d(dtype=Any), valid: wp.array(dtype=wp.int32)):
    """A fit's first point from its (N, n_params) float64 start: clipped to the bounds, then each lobe's
    rho_s capped by the energy bound, in float64 (models.energy_bound_numpy's operations, in its order),
    then rounded to the compute precision ``p`` and to the storage precision (half floats through float32,
    as Warp converts). ``valid``: 1 where the texel has samples."""
    i = wp.tid()
    t = p[i]
    lobes_end = 3 + n_lobes * lobe_stride
    for k in range(guess.shape[1]):
        v = wp.min(wp.max(guess[i, k], lower[k]), upper[k])
        if albedo_max > wp.float64(0.0) and k >= 3 and k < lobes_end and (k - 3) % lobe_stride < 3:
            last = k - (k - 3) % lobe_stride + lobe_stride - 1  # the lobe's exponent n
            exponent = wp.min(wp.max(guess[i, last], lower[last]), upper[last])
            v = wp.min(v, albedo_max * (exponent + wp.float64(2.0)) / two_pi)
        t[k] = type(t[k])(v)
        storage[i, k] = type(storage[i, k])(v)
    p[i] = t
    valid[i] = wp.where(count[i] > 0, 1, 0)


@wp.kernel(enable_backward=False, module="unique")
def accept_kernel(p: wp.array(dtype=Any), f: wp.array(dtype=Any), g: wp.array(dtype=Any),
                  d: wp.array(dtype=Any), trial: wp.array(dtype=Any), f_trial: wp.array(dtype=Any),
                  g_trial: wp.array(dtype=Any), alpha: wp.array(dtype=Any), active: wp.array(dtype=wp.int32),
                  sigma1: Any, sigma2: Any, use_wolfe: int, shrink: Any, quadratic: int, free: Any,
                  stats: wp.array(dtype=wp.vec4d), stats_trial: wp.array(dtype=wp.vec4d),
                  accepted: wp.array(dtype=wp.int32), want_diag: int, diag: wp.array(dtype=Any),
                  diag_trial: wp.array(dtype=Any)):
    """Armijo (3.11), optionally curvature (3.12), per texel; accepted texels take the trial
    point, objective and gradient by conditional assignment (Alg. 11) and leave the line search.
    Rejected texels get a smaller alpha: backtracking (alpha *= shrink) or the two-sided quadratic
    minimiser (3.15) when it lies in (0.1 alpha, alpha) (Alg. 3). With ``want_diag`` the
    trial's Gauss-Newton diagonal is adopted too (the Jacobi preconditioner at the new point)."""
    i = wp.tid()
    if active[i] == 0:
        return
    step = trial[i] - p[i]
    slope = wp.dot(g[i], masked(step, free))
    ft = f_trial[i]
    ok = ft <= f[i] + sigma1 * slope and ft == ft  # ft == ft rejects NaN
    if ok and use_wolfe != 0:
        ok = wp.dot(g_trial[i], masked(d[i], free)) >= sigma2 * wp.dot(g[i], masked(d[i], free))
    if wp.length_sq(step) == type(ft)(0.0):
        ok = True  # the projection pinned every free parameter: nothing left to search
    if ok:
        p[i] = trial[i]
        f[i] = ft
        g[i] = g_trial[i]
        stats[i] = stats_trial[i]
        if want_diag != 0:
            diag[i] = diag_trial[i]
        accepted[i] = 1
        active[i] = 0
    else:
        a = alpha[i]
        new_a = a * shrink
        if quadratic != 0:
            phi0d = wp.dot(g[i], masked(d[i], free))
            den = type(a)(2.0) * (ft - phi0d * a - f[i])
            if den > type(a)(0.0) and ft == ft:
                amin = -phi0d * a * a / den
                if amin > type(a)(0.1) * a and amin < a:
                    new_a = amin
        alpha[i] = new_a


@wp.func
def jacobi_inverse(diag: Any, free: Any, n_params: int, rel_floor: Any):
    """M^-1 of the Jacobi preconditioner M = D + floor on the free columns, 0 on frozen ones.

    D is the Gauss-Newton diagonal diag(J^T J) of the texel; floor = rel_floor * mean of D over
    the free columns + the smallest normal-ish value, so a column the photos do not constrain
    (D_k = 0, hence g_k = 0 from the data term) cannot divide by zero. The floor is relative and
    tiny (default 1e-10) because a genuinely weak column (the exponent n ~ 1e3 has D_n ~ 1e-7 of
    the albedos' D) is exactly the one the preconditioner must scale up. An all-zero D (never
    accumulated) gives M = I, the unpreconditioned method."""
    zero = rel_floor - rel_floor
    cnt = wp.dot(free, free)
    total = wp.dot(diag, free)
    mean = zero
    if cnt > zero:
        mean = total / cnt
    if not (mean > zero):
        return free  # no diagonal yet (not accumulated, or a texel no sample constrains): M = I
    floor = rel_floor * mean + type(rel_floor)(1.0e-30)
    out = diag * zero
    for k in range(n_params):
        if free[k] != zero:
            dk = diag[k]
            if not (dk >= zero):  # NaN or negative (cannot happen for sums of squares): ignore
                dk = zero
            out[k] = type(rel_floor)(1.0) / (dk + floor)
    return out


@wp.kernel(enable_backward=False, module="unique")
def steepest_direction_kernel(g: wp.array(dtype=Any), free: Any, precondition: int, diag: wp.array(dtype=Any),
                              n_params: int, rel_floor: Any, d: wp.array(dtype=Any)):
    """d = -g, or the scaled gradient d = -M^-1 g with M from the current point's diagonal."""
    i = wp.tid()
    if precondition != 0:
        d[i] = -wp.cw_mul(jacobi_inverse(diag[i], free, n_params, rel_floor), masked(g[i], free))
    else:
        d[i] = -masked(g[i], free)


@wp.kernel(enable_backward=False, module="unique")
def cg_direction_kernel(g: wp.array(dtype=Any), g_prev: wp.array(dtype=Any), d_prev: wp.array(dtype=Any),
                        restart: wp.array(dtype=wp.int32), polak_ribiere: int, eps: Any, free: Any,
                        precondition: int, diag: wp.array(dtype=Any), minv: wp.array(dtype=Any),
                        n_params: int, rel_floor: Any, refresh_always: int, d: wp.array(dtype=Any)):
    """Nonlinear CG (3.3) with Fletcher-Reeves (3.4) or Polak-Ribiere+ (3.5, beta >= 0 restart),
    restart on request, and the descent-direction safeguard of Alg. 10.

    Preconditioned (N&W 5.2, Shewchuk's preconditioned PR), z = M^-1 g:
        d = -z + beta d_prev, beta_PR+ = max(0, z.(g - g_prev) / z_prev.g_prev),
        beta_FR = z.g / z_prev.g_prev.
    M (``minv`` = M^-1, per texel) is held fixed between restarts, as the CG recurrences assume,
    and refreshed from the current point's Gauss-Newton diagonal ``diag`` whenever the texel
    restarts: on request (first iteration, rejected step, periodic restart), when PR+ clips beta
    to 0, or when the descent safeguard fires. At those points d = -z carries no conjugacy to
    break, so changing the metric is free. ``refresh_always`` takes M from every iteration's point
    instead (beta then mixes metrics, which did not pay on the ornament: docs/accuracy.md).
    Unpreconditioned, M = I (z = g) exactly.
    """
    i = wp.tid()
    gi = masked(g[i], free)
    gp = masked(g_prev[i], free)
    mi = free
    if precondition != 0:
        mi = minv[i]
    refresh = restart[i] != 0
    if precondition != 0 and refresh_always != 0:
        mi = jacobi_inverse(diag[i], free, n_params, rel_floor)  # M_k from every iteration's point
    zi = wp.cw_mul(mi, gi)
    den = wp.dot(wp.cw_mul(mi, gp), gp)
    zero = den - den
    beta = zero
    if not refresh and den > zero:
        if polak_ribiere != 0:
            beta = wp.dot(zi, gi - gp) / den
            if not (beta > zero):
                beta = zero
                refresh = True
        else:
            beta = wp.dot(zi, gi) / den
    if precondition != 0 and refresh:
        mi = jacobi_inverse(diag[i], free, n_params, rel_floor)
        zi = wp.cw_mul(mi, gi)
    di = -zi + beta * masked(d_prev[i], free)
    ng = wp.length(gi)
    if not (wp.dot(gi, di) < -eps * ng * wp.length(di)):
        if precondition != 0 and not refresh:
            mi = jacobi_inverse(diag[i], free, n_params, rel_floor)
            zi = wp.cw_mul(mi, gi)
        di = -zi
        if not (wp.dot(gi, di) < -eps * ng * wp.length(di)):
            di = -gi  # M^-1 so badly conditioned that -z is nearly orthogonal to g
    if precondition != 0:
        minv[i] = mi
    d[i] = di
    restart[i] = 0


@wp.func
def unbound(p: Any, g: Any, lower: Any, upper: Any, free: Any, n_params: int):
    """The free mask less the binding bounds: columns at a bound whose gradient pushes outward
    (at the upper bound with g < 0, at the lower with g > 0). A step along them is clamped away
    by the projection, so a direction that relies on them (L-BFGS mixes columns through its pairs)
    can lose descent once projected; Bertsekas' projected quasi-Newton drops them the same way."""
    out = free
    zero = g[0] - g[0]
    for k in range(n_params):
        if (p[k] >= upper[k] and g[k] < zero) or (p[k] <= lower[k] and g[k] > zero):
            out[k] = zero
    return out


@wp.kernel(enable_backward=False, module="unique")
def lbfgs_direction_kernel(g: wp.array(dtype=Any), s_hist: wp.array2d(dtype=Any), y_hist: wp.array2d(dtype=Any),
                           rho: wp.array2d(dtype=Any), count: wp.array(dtype=wp.int32), head: wp.array(dtype=wp.int32),
                           m: int, eps: Any, free: Any, precondition: int, diag: wp.array(dtype=Any),
                           n_params: int, rel_floor: Any, gamma_scaled: int, alpha_buf: wp.array2d(dtype=Any),
                           p: wp.array(dtype=Any), lower: Any, upper: Any, d: wp.array(dtype=Any)):
    """L-BFGS two-loop recursion (Nocedal & Wright Alg. 7.4), per texel, with
    H0 = gamma_k I, gamma_k = s^T y / y^T y of the newest pair. (The seed's Alg. 1 has the
    second loop's update written as d <- d + s (eta - beta); N&W's r <- r + s (alpha - beta) is used.)

    Preconditioned: H0 = gamma_k M^-1, M = D + floor with D the Gauss-Newton diagonal at the
    current point, gamma_k = s^T y / y^T M^-1 y of the newest pair (``gamma_scaled``; 1 before
    any pair: D already carries the Hessian's units, so the first step is a diagonal Gauss-Newton
    step of natural length 1), or H0 = M^-1 unscaled. N&W allow H0 to change every iteration, so
    M is refreshed each iteration from the accepted point's pass.

    Bounds: the recursion runs on the columns that are free and not held by a binding bound
    (:func:`unbound`), so the projected trial point keeps the direction's descent."""
    i = wp.tid()
    free = unbound(p[i], g[i], lower, upper, free, n_params)
    q = masked(g[i], free)
    n = count[i]
    zero = rho[0, i] - rho[0, i]
    for j in range(n):
        slot = (head[i] - 1 - j + m) % m
        a = rho[slot, i] * wp.dot(s_hist[slot, i], q)
        alpha_buf[slot, i] = a
        q = q - a * y_hist[slot, i]
    r = q
    h0 = free
    if precondition != 0:
        h0 = jacobi_inverse(diag[i], free, n_params, rel_floor)
        if gamma_scaled != 0 and n > 0:
            # H0 = gamma M^-1, gamma = s^T y / y^T M^-1 y of the newest pair (N&W 7.20, M-metric)
            newest = (head[i] - 1 + m) % m
            yn = y_hist[newest, i]
            ymy = wp.dot(yn, wp.cw_mul(h0, yn))
            if ymy > zero:
                h0 = (wp.dot(s_hist[newest, i], yn) / ymy) * h0
        r = wp.cw_mul(h0, q)
    else:
        gamma = zero + type(zero)(1.0)
        if n > 0:
            newest = (head[i] - 1 + m) % m
            yy = wp.dot(y_hist[newest, i], y_hist[newest, i])
            if yy > zero:
                gamma = wp.dot(s_hist[newest, i], y_hist[newest, i]) / yy
        r = gamma * q
    for j in range(n):
        slot = (head[i] - n + j + m) % m
        b = rho[slot, i] * wp.dot(y_hist[slot, i], r)
        r = r + (alpha_buf[slot, i] - b) * s_hist[slot, i]
    di = -masked(r, free)
    gi = masked(g[i], free)
    if not (wp.dot(gi, di) < -eps * wp.length(gi) * wp.length(di)):
        di = -wp.cw_mul(h0, gi)
        count[i] = 0
        if not (wp.dot(gi, di) < -eps * wp.length(gi) * wp.length(di)):
            di = -gi
    d[i] = di


@wp.kernel(enable_backward=False, module="unique")
def lbfgs_update_kernel(p_old: wp.array(dtype=Any), g_old: wp.array(dtype=Any), p: wp.array(dtype=Any),
                        g: wp.array(dtype=Any), accepted: wp.array(dtype=wp.int32), m: int, free: Any,
                        s_hist: wp.array2d(dtype=Any), y_hist: wp.array2d(dtype=Any), rho: wp.array2d(dtype=Any),
                        count: wp.array(dtype=wp.int32), head: wp.array(dtype=wp.int32)):
    """Store s = p_{k+1} - p_k, y = g_{k+1} - g_k when the texel moved and y^T s > 0 (keeps H positive definite).

    A texel whose line search accepted no trial forgets its pairs (as CG restarts on a rejected
    step): otherwise the next iteration rebuilds the same rejected direction and the texel stalls
    (seen with the Jacobi preconditioner: on the full ornament the objective froze from iteration
    ~25 at 29% above steepest descent's after 250, about half the texels rejecting every step)."""
    i = wp.tid()
    if accepted[i] == 0:
        count[i] = 0
        return
    s = masked(p[i] - p_old[i], free)
    y = masked(g[i] - g_old[i], free)
    ys = wp.dot(y, s)
    zero = ys - ys
    if ys > type(ys)(1.0e-12) * wp.length(y) * wp.length(s) and ys > zero:
        h = head[i]
        s_hist[h, i] = s
        y_hist[h, i] = y
        rho[h, i] = type(ys)(1.0) / ys
        head[i] = (h + 1) % m
        count[i] = wp.min(count[i] + 1, m)


@wp.kernel(enable_backward=False, module="unique")
def hessian_alpha_kernel(g: wp.array(dtype=Any), d: wp.array(dtype=Any), dhd: wp.array(dtype=Any),
                         fallback: wp.array(dtype=Any), free: Any, alpha: wp.array(dtype=Any)):
    """One-sided quadratic step (3.13) alpha = -g.d / d^T H d, guarded: a non-positive or
    non-finite denominator falls back to the backtracking start."""
    i = wp.tid()
    num = -wp.dot(masked(g[i], free), masked(d[i], free))
    den = dhd[i]
    zero = den - den
    a = fallback[i]
    if den > zero and num > zero:
        q = num / den
        if q == q and q < type(q)(1.0e30):
            a = q
    alpha[i] = a


@wp.kernel(enable_backward=False, module="unique")
def initial_alpha_kernel(g: wp.array(dtype=Any), d: wp.array(dtype=Any), prev_alpha: wp.array(dtype=Any),
                         prev_slope: wp.array(dtype=Any), first: int, alpha0: Any, free: Any,
                         alpha: wp.array(dtype=Any), slope: wp.array(dtype=Any)):
    """Backtracking start: alpha0 on the first iteration (or after a restart), else
    N&W (3.60): alpha = alpha_prev * (g_prev.d_prev) / (g.d), capped at 1e6 * alpha0."""
    i = wp.tid()
    sl = wp.dot(masked(g[i], free), masked(d[i], free))
    a = alpha0
    if first == 0 and sl < sl - sl and prev_slope[i] < sl - sl:
        a = wp.min(prev_alpha[i] * prev_slope[i] / sl * type(sl)(1.01), alpha0 * type(sl)(1.0e6))
    if not (a > sl - sl):
        a = alpha0
    alpha[i] = a
    slope[i] = sl


@wp.kernel(enable_backward=False, module="unique")
def lm_solve_kernel(jtj: wp.array(dtype=Any), jtr: wp.array(dtype=Any), lam: wp.array(dtype=Any),
                    n_params: int, free: Any, like: Any, p: wp.array(dtype=Any), lower: Any, upper: Any,
                    step: wp.array(dtype=Any), pred: wp.array(dtype=Any)):
    """Solve (J^T J + lambda diag(J^T J) + tiny I) delta = -J^T r per texel by Cholesky;
    frozen rows are identity. pred = predicted decrease -(g.delta + 0.5 delta^T JtJ delta).

    Columns held by a binding bound (:func:`unbound`) are frozen for this solve: the step the
    other columns take would otherwise assume the held one moves, and the clamped trial misses
    the predicted decrease."""
    i = wp.tid()
    free = unbound(p[i], jtr[i], lower, upper, free, n_params)
    a = jtj[i]
    b = -masked(jtr[i], free)
    zero = lam[i] - lam[i]
    one = zero + type(zero)(1.0)
    for k in range(n_params):
        dk = a[k, k]
        if free[k] == zero:
            for j in range(n_params):
                a[k, j] = zero
                a[j, k] = zero
            a[k, k] = one
            b[k] = zero
        else:
            a[k, k] = dk + lam[i] * dk + type(zero)(1.0e-9) * (one + dk)
    # in-place Cholesky: a = L L^T (lower triangle)
    ok = int(1)
    for k in range(n_params):
        s = a[k, k]
        for j in range(k):
            s = s - a[k, j] * a[k, j]
        if s <= zero:
            ok = 0
            s = one
        lkk = wp.sqrt(s)
        a[k, k] = lkk
        for r in range(k + 1, n_params):
            t = a[r, k]
            for j in range(k):
                t = t - a[r, j] * a[k, j]
            a[r, k] = t / lkk
    x = like * zero
    for k in range(n_params):
        t = b[k]
        for j in range(k):
            t = t - a[k, j] * x[j]
        x[k] = t / a[k, k]
    for kk in range(n_params):
        k = n_params - 1 - kk
        t = x[k]
        for j in range(k + 1, n_params):
            t = t - a[j, k] * x[j]
        x[k] = t / a[k, k]
    if ok == 0:
        x = b * (one / (one + lam[i]))
    step[i] = x
    gx = wp.dot(masked(jtr[i], free), x)
    pred[i] = -(gx + type(zero)(0.5) * wp.dot(x, jtj[i] * x))


@wp.kernel(enable_backward=False, module="unique")
def lm_accept_kernel(p: wp.array(dtype=Any), f: wp.array(dtype=Any), g: wp.array(dtype=Any),
                     jtj: wp.array(dtype=Any), trial: wp.array(dtype=Any), f_trial: wp.array(dtype=Any),
                     g_trial: wp.array(dtype=Any), jtj_trial: wp.array(dtype=Any), f_cmp: wp.array(dtype=Any),
                     f_trial_cmp: wp.array(dtype=Any), pred: wp.array(dtype=Any),
                     lam: wp.array(dtype=Any), active: wp.array(dtype=wp.int32), stats: wp.array(dtype=wp.vec4d),
                     stats_trial: wp.array(dtype=wp.vec4d), accepted: wp.array(dtype=wp.int32)):
    """Gain-ratio test on the texel's objective (``f_cmp`` now, ``f_trial_cmp`` at the trial; the
    data term plus the smoothness with the neighbours held): accept when the actual decrease is
    positive and a fair share of the predicted one, then lambda /= 3 and the trial's data terms
    (f, g, J^T J, stats) are adopted; else lambda *= 4 and the point is kept (Alg. 11 style)."""
    i = wp.tid()
    if active[i] == 0:
        return
    ft = f_trial_cmp[i]
    zero = ft - ft
    actual = f_cmp[i] - ft
    ok = ft == ft and actual >= zero and (actual >= type(ft)(1.0e-3) * pred[i] or actual == zero)
    if ok:
        p[i] = trial[i]
        f[i] = f_trial[i]
        g[i] = g_trial[i]
        jtj[i] = jtj_trial[i]
        stats[i] = stats_trial[i]
        accepted[i] = 1
        lam[i] = wp.max(lam[i] / type(ft)(3.0), type(ft)(1.0e-9))
    else:
        accepted[i] = 0
        lam[i] = wp.min(lam[i] * type(ft)(4.0), type(ft)(1.0e12))


@wp.kernel(enable_backward=False, module="unique")
def smooth_local_kernel(p: wp.array(dtype=Any), p_nb: wp.array(dtype=Any), neighbors: wp.array(dtype=wp.vec4i),
                        edge_w: wp.array(dtype=wp.vec4), weights: Any, lam: Any, f_scale: Any,
                        f_in: wp.array(dtype=Any), g_in: wp.array(dtype=Any), h_in: wp.array(dtype=Any),
                        n_params: int, want_derivatives: int, f_out: wp.array(dtype=Any),
                        g_out: wp.array(dtype=Any), h_out: wp.array(dtype=Any)):
    """Texel i's share of the membrane smoothness with its neighbours held at ``p_nb``:
    S_i = lam sum_j e_ij sum_k w_k (p_ik - p_jk)^2 over the masked 4-neighbourhood.

    f_out = f_in + f_scale S_i (f_scale 1: the local objective of a block-Jacobi / red-black step;
    1/2: the texel's share of the global penalty, each pair being counted from both ends).
    g_out = g_in + dS_i/dp_i (= the global penalty's gradient) and h_out = h_in + its (diagonal)
    Hessian 2 lam deg_i diag(w), exact for the block; the coupling blocks are left out, which is
    why LM updates texels in red-black order (neighbours never move together)."""
    i = wp.tid()
    pi = p[i]
    zero = lam - lam
    pen = zero
    gr = pi * zero
    deg = zero
    nb = neighbors[i]
    ew = edge_w[i]
    for k in range(4):
        j = nb[k]
        if j >= 0:
            e = type(lam)(ew[k])
            diff = pi - p_nb[j]
            wd = wp.cw_mul(diff, weights)
            pen = pen + e * wp.dot(wd, diff)
            gr = gr + e * wd
            deg = deg + e
    two = type(lam)(2.0)
    f_out[i] = f_in[i] + f_scale * lam * pen
    if want_derivatives != 0:
        g_out[i] = g_in[i] + two * lam * gr
        h = h_in[i]
        for k in range(n_params):
            h[k, k] = h[k, k] + two * lam * deg * weights[k]
        h_out[i] = h


@wp.kernel
def parity_active_kernel(valid: wp.array(dtype=wp.int32), parity: wp.array(dtype=wp.int32), which: int,
                         active: wp.array(dtype=wp.int32)):
    """Red-black ordering on the texel grid: only texels of one colour move in a step."""
    i = wp.tid()
    active[i] = 0
    if valid[i] != 0 and parity[i] == which:
        active[i] = 1


@wp.kernel(enable_backward=False, module="unique")
def bounds_penalty_kernel(p: wp.array(dtype=Any), d: wp.array(dtype=Any), lower: Any, upper: Any,
                          mu: Any, free: Any, want_dhd: int, n_params: int, f: wp.array(dtype=Any),
                          g: wp.array(dtype=Any), dhd: wp.array(dtype=Any)):
    """Quadratic bounds penalty (3.19): mu sum max(l - p, 0)^2 + max(p - u, 0)^2, its gradient
    2 mu (max(p - u, 0) - max(l - p, 0)) and d^T H d = 2 mu sum_{violated} d_k^2
    (the text's Eqs. 4.8-4.11 carry sign slips; these are the derivatives of 3.19)."""
    i = wp.tid()
    pi = p[i]
    zero = mu - mu
    two = type(mu)(2.0)
    pen = zero
    gr = pi * zero
    h = zero
    for k in range(n_params):
        if free[k] != zero:
            lo = wp.max(lower[k] - pi[k], zero)
            hi = wp.max(pi[k] - upper[k], zero)
            pen = pen + lo * lo + hi * hi
            gr[k] = two * (hi - lo)
            if want_dhd != 0 and (lo > zero or hi > zero):
                h = h + two * d[i][k] * d[i][k]
    f[i] = f[i] + mu * pen
    g[i] = g[i] + mu * gr
    if want_dhd != 0:
        dhd[i] = dhd[i] + mu * h


@wp.kernel(enable_backward=False, module="unique")
def laplacian_kernel(x: wp.array(dtype=Any), neighbors: wp.array(dtype=wp.vec4i), out: wp.array(dtype=Any)):
    """(L x)_i with the masked 5-point stencil of Alg. 7: centre weight = number of valid neighbours."""
    i = wp.tid()
    nb = neighbors[i]
    acc = x[i] * (x[i][0] - x[i][0])
    w = int(0)
    for k in range(4):
        j = nb[k]
        if j >= 0:
            acc = acc - x[j]
            w = w + 1
    out[i] = acc + type(x[i][0])(float(w)) * x[i]


@wp.kernel(enable_backward=False, module="unique")
def laplacian_penalty_kernel(lp: wp.array(dtype=Any), llp: wp.array(dtype=Any), ld: wp.array(dtype=Any),
                             weights: Any, lam: Any, want_dhd: int, f: wp.array(dtype=Any),
                             g: wp.array(dtype=Any), dhd: wp.array(dtype=Any)):
    """P = lam (Lp)^T W (Lp) (4.12) split per texel; grad 2 lam L^T W L p (4.13; L is symmetric);
    d^T H d = 2 lam (Ld)^T W (Ld) (4.14). ``weights`` selects which columns are regularised."""
    i = wp.tid()
    a = wp.cw_mul(lp[i], weights)
    two = type(lam)(2.0)
    f[i] = f[i] + lam * wp.dot(a, lp[i])
    g[i] = g[i] + two * lam * wp.cw_mul(llp[i], weights)
    if want_dhd != 0:
        b = wp.cw_mul(ld[i], weights)
        dhd[i] = dhd[i] + two * lam * wp.dot(b, ld[i])


@wp.kernel(enable_backward=False, module="unique")
def chunk_sums_kernel(f: wp.array(dtype=Any), g: wp.array(dtype=Any), st: wp.array(dtype=wp.vec4d),
                      accepted: wp.array(dtype=wp.int32), valid: wp.array(dtype=wp.int32), n: int, chunk: int,
                      out: wp.array2d(dtype=wp.float64)):
    """Deterministic first reduction level: thread c sums texels [c*chunk, (c+1)*chunk) in order.
    Columns: objective, |grad|^2, samples, SSE, sum|r|, sum|y|, accepted, valid texels."""
    c = wp.tid()
    acc = wp.vector(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0), wp.float64(0.0),
                    wp.float64(0.0), wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
    for i in range(c * chunk, wp.min((c + 1) * chunk, n)):
        if valid[i] != 0:
            s = st[i]
            gi = g[i]
            acc = acc + wp.vector(wp.float64(f[i]), wp.float64(wp.dot(gi, gi)), s[0], s[1], s[2], s[3],
                                  wp.float64(accepted[i]), wp.float64(1.0))
    for k in range(8):
        out[c, k] = acc[k]


@wp.kernel
def final_sums_kernel(partial: wp.array2d(dtype=wp.float64), n_chunks: int, row: int,
                      trace: wp.array2d(dtype=wp.float64)):
    """Second reduction level into row ``row`` of the trace buffer: thread k sums column k over the chunks,
    in order."""
    k = wp.tid()
    s = wp.float64(0.0)
    for c in range(n_chunks):
        s = s + partial[c, k]
    trace[row, k] = s


@wp.kernel(enable_backward=False, module="unique")
def centred_prior_kernel(params: wp.array2d(dtype=Any), direction: wp.array2d(dtype=Any), centre: wp.array(dtype=Any),
                         weights: wp.array(dtype=Any), active: wp.array(dtype=wp.int32), n_params: int, want_dhd: int,
                         want_diag: int, f: wp.array(dtype=Any), g: wp.array(dtype=Any), dhd: wp.array(dtype=Any),
                         diag: wp.array(dtype=Any)):
    """Adds the prior P_i = 1/2 sum_k w_ik (p_ik - c_ik)^2 to texel i's objective, w_i (p_i - c_i) to its
    gradient, (``want_dhd``) sum_k w_ik d_k^2 to its d^T H d and (``want_diag``) w_i to its Gauss-Newton
    diagonal (the Jacobi preconditioner); inactive texels are left as they are. ``centre`` and ``weights``
    hold a row per texel (the shared materials' prior, fit/models/materials.py) or one row for every texel (the
    view terms' ridge prior, centre 0)."""
    i = wp.tid()
    if active[i] == 0:
        return
    c = centre[wp.min(i, centre.shape[0] - 1)]
    w = weights[wp.min(i, weights.shape[0] - 1)]
    zero = w[0] - w[0]
    pen = zero
    curv = zero
    gi = g[i]
    for k in range(n_params):
        e = type(zero)(params[i, k]) - c[k]
        pen = pen + w[k] * e * e
        gi[k] = gi[k] + w[k] * e
        if want_dhd != 0:
            dk = type(zero)(direction[i, k])
            curv = curv + w[k] * dk * dk
    f[i] = f[i] + type(zero)(0.5) * pen
    g[i] = gi
    if want_dhd != 0:
        dhd[i] = dhd[i] + curv
    if want_diag != 0:
        diag[i] = diag[i] + w


@wp.kernel(enable_backward=False, module="unique")
def centred_prior_diag_kernel(weights: wp.array(dtype=Any), active: wp.array(dtype=wp.int32), n_params: int,
                              jtj: wp.array(dtype=Any)):
    """Adds the centred prior's Hessian diag(w_i) to texel i's Gauss-Newton matrix (:func:`centred_prior_kernel`;
    one row of ``weights`` serves every texel)."""
    i = wp.tid()
    if active[i] == 0:
        return
    h = jtj[i]
    w = weights[wp.min(i, weights.shape[0] - 1)]
    for k in range(n_params):
        h[k, k] = h[k, k] + w[k]
    jtj[i] = h


def _declare_optimizer_overloads(scalar, n_params: int) -> None:
    """The optimizer kernels' overloads of the compute scalar ``scalar`` for one declared parameter count, in
    every module before its first launch (fit/kernels/overloads.py)."""
    _s, _v, _m = param_overload(n_params, scalar)
    declare(start_point_kernel, p=_v, storage=STORAGE_SCALAR)
    declare(trial_kernel, p=_v, d=_v, alpha=_s, lower=_v, upper=_v, free=_v, trial=_v, storage=STORAGE_SCALAR)
    declare(lm_solve_kernel, jtj=_m, jtr=_v, lam=_s, free=_v, like=_v, p=_v, lower=_v, upper=_v, step=_v,
            pred=_s)
    declare(lm_accept_kernel, p=_v, f=_s, g=_v, jtj=_m, trial=_v, f_trial=_s, g_trial=_v, jtj_trial=_m,
            f_cmp=_s, f_trial_cmp=_s, pred=_s, lam=_s)
    declare(chunk_sums_kernel, f=_s, g=_v)
    declare(centred_prior_kernel, params=STORAGE_SCALAR, direction=STORAGE_SCALAR, centre=_v, weights=_v, f=_s,
            g=_v, dhd=_s, diag=_v)
    declare(centred_prior_diag_kernel, weights=_v, jtj=_m)


at_every_count(_declare_optimizer_overloads)
