"""Lafortune model value, Jacobian and second directional derivative, per texel sample.

Generic over float32/float64: ``p`` and ``d`` are fixed-length parameter vectors of the compute
type, exactly the layout's ``n_params`` long (:func:`param_types`),
``u``/``v`` are the local light/view directions and ``one`` is the scalar 1 of that type.

For channel c, m_c = rho_d,c + sum_j rho_s,j,c L_j with L_j = max(s_j, 0)^n_j and
s_j = C_j . w, w = (u_x v_x, u_y v_y, u_z v_z) (isotropic: C = (c_xy, c_xy, c_z)).
    dm_c/drho_d,c = 1
    dm_c/drho_s,j,c = L_j
    dm_c/dC_j,k = rho_s,j,c n_j s_j^(n_j-1) w_k          (isotropic c_xy: w_x + w_y)
    dm_c/dn_j = rho_s,j,c L_j ln s_j
Second directional derivative along d (da = d rho_s, ds = dC . w, dn):
    L' = L (n ds/s + dn ln s)
    L'' = L (n ds/s + dn ln s)^2 + L (2 dn ds/s - n ds^2/s^2)
    d^T (Hess m_c) d = sum_j 2 da_c L' + rho_s,c L''
For s <= 0 the lobe and all its derivatives are 0 (n >= 1 makes the objective C1 there).
"""

from __future__ import annotations

from typing import Any

import warp as wp

_PARAM_TYPES: dict = {}


def param_types(n_params: int, scalar) -> tuple:
    """(vector, matrix) Warp types of one texel's parameters: ``n_params`` long, ``scalar`` entries.

    Sized to the model layout rather than to the largest model, because a per-thread J^T J of
    17x17 floats spills registers on a GPU while one lobe's 9x9 stays in them; each size compiles
    its own kernel overloads (the kernels are generic over these types).
    """
    key = (int(n_params), scalar)
    if key not in _PARAM_TYPES:
        _PARAM_TYPES[key] = (wp.types.vector(length=int(n_params), dtype=scalar),
                             wp.types.matrix(shape=(int(n_params), int(n_params)), dtype=scalar))
    return _PARAM_TYPES[key]


@wp.func
def lobe_weights(u: Any, v: Any):
    return type(u)(u[0] * v[0], u[1] * v[1], u[2] * v[2])


@wp.func
def lobe_base(p: Any, o: int, aniso: int, w: Any):
    """s = C . w for the lobe whose columns start at ``o``."""
    if aniso != 0:
        return p[o + 3] * w[0] + p[o + 4] * w[1] + p[o + 5] * w[2]
    return p[o + 3] * (w[0] + w[1]) + p[o + 4] * w[2]


@wp.func
def lobe_features(p: Any, n_lobes: int, aniso: int, u: Any, v: Any, one: Any):
    """What the model and its Jacobian need from the directions, per lobe j at column offset o:
    f[o] = L_j, f[o + 3 + k] = dL_j/dC_j,k (isotropic: d/dc_xy, d/dc_z), f[o + stride - 1] = dL_j/dn_j;
    other entries 0. m and J are linear in f (:func:`model_from_features`), so a weighted mean of
    features over several directions gives the weighted mean model and Jacobian exactly (the
    filtered photo sampling of fit/kernels/stream.py)."""
    zero = one - one
    f = p * zero
    stride = 6 + aniso
    w = lobe_weights(u, v)
    for j in range(n_lobes):
        o = 3 + j * stride
        s = lobe_base(p, o, aniso, w)
        if s > zero:
            n = p[o + stride - 1]
            ls = wp.log(s)
            # cap the lobe at e^30 (~1e13; its square stays finite in fp32): reachable only when
            # C pushes s above 1 with a huge exponent, where the model is meaningless anyway
            nls = n * ls
            capped = nls > type(one)(30.0)
            lobe = wp.exp(wp.min(nls, type(one)(30.0)))
            dlds = n * lobe / s
            if capped:
                dlds = zero
                ls = zero  # d lobe / dn = lobe ln s becomes 0 on the flat cap
            f[o] = lobe
            if aniso != 0:
                for k in range(3):
                    f[o + 3 + k] = dlds * w[k]
            else:
                f[o + 3] = dlds * (w[0] + w[1])
                f[o + 4] = dlds * w[2]
            f[o + stride - 1] = lobe * ls
    return f


@wp.func
def model_from_features(p: Any, f: Any, n_lobes: int, aniso: int, one: Any):
    """Model value m (RGB) and the Jacobian rows dm_r/dp, dm_g/dp, dm_b/dp from lobe features."""
    zero = one - one
    jr = p * zero
    jg = p * zero
    jb = p * zero
    m = wp.vector(p[0], p[1], p[2])
    jr[0] = one
    jg[1] = one
    jb[2] = one
    stride = 6 + aniso
    for j in range(n_lobes):
        o = 3 + j * stride
        lobe = f[o]
        m = m + wp.vector(p[o], p[o + 1], p[o + 2]) * lobe
        jr[o] = lobe
        jg[o + 1] = lobe
        jb[o + 2] = lobe
        for k in range(3, stride):
            jr[o + k] = p[o] * f[o + k]
            jg[o + k] = p[o + 1] * f[o + k]
            jb[o + k] = p[o + 2] * f[o + k]
    return m, jr, jg, jb


@wp.func
def lafortune_eval(p: Any, n_lobes: int, aniso: int, u: Any, v: Any, one: Any):
    """Model value m (RGB) and the Jacobian rows dm_r/dp, dm_g/dp, dm_b/dp."""
    return model_from_features(p, lobe_features(p, n_lobes, aniso, u, v, one), n_lobes, aniso, one)


@wp.func
def lafortune_dhd(p: Any, d: Any, n_lobes: int, aniso: int, u: Any, v: Any, one: Any):
    """d^T (Hess m_c) d for c = r, g, b (the part the Gauss-Newton approximation drops)."""
    zero = one - one
    out = type(u)(zero, zero, zero)
    stride = 6 + aniso
    w = lobe_weights(u, v)
    for j in range(n_lobes):
        o = 3 + j * stride
        s = lobe_base(p, o, aniso, w)
        if s > zero:
            n = p[o + stride - 1]
            dnj = d[o + stride - 1]
            ds = lobe_base(d, o, aniso, w)
            ls = wp.log(s)
            if n * ls > type(one)(30.0):
                continue  # flat cap: no curvature
            lobe = wp.exp(n * ls)
            q = n * ds / s + dnj * ls
            l1 = lobe * q
            l2 = lobe * q * q + lobe * ((one + one) * dnj * ds / s - n * ds * ds / (s * s))
            da = type(u)(d[o], d[o + 1], d[o + 2])
            a = type(u)(p[o], p[o + 1], p[o + 2])
            out = out + (one + one) * l1 * da + l2 * a
    return out
