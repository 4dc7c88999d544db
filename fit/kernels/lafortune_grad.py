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

With an ambient radiance A (render/layout.py ``ModelLayout.ambient``, its columns last) a sample predicts
W m_c with m_c = (the above) + A_c a_c, a_c = exposure / W_c (the sample's flash weight W_c = exposure E_c cos
per unit BRDF, so W m_c = W (rho_d + lobes) + exposure A_c). a_c is a property of the sample, not of a direction,
so it is not a per-direction feature: the sample sets it once its weight is known (``set_ambient``).
    dm_c/dA_c = a_c, and m is linear in A: no second-derivative term.
With the room light (``ModelLayout.room``, the same columns holding the texel's known room irradiance factor S)
the room's radiance rho_d S takes the ambient's place: m_c = (the above) + rho_d,c S_c a_c, so
    dm_c/drho_d,c = 1 + S_c a_c,   dm_c/dS_c = rho_d,c a_c
(S is frozen in the per-texel fit; its column's J^T r and J^T J are what the global light's solve reduces,
fit/models/per_texel/room_light.py). The only second derivative, d^2 m_c / drho_d,c dS_c = a_c, meets a direction
whose S entries are 0 (frozen), so ``dhd`` is unchanged.
A channel whose light is exactly 0 (a photo taken with the flash off) has no flash term: its sample predicts the
ambient alone, exposure A_c share (the room's: rho_d,c S_c share), so the sample takes the share itself as a_c and
the weight 1 (fit/kernels/accumulate.py): m_c = A_c a_c, dm_c/dA_c = a_c and every other entry 0 (the room's:
m_c = rho_d,c S_c a_c, dm_c/drho_d,c = S_c a_c, dm_c/dS_c = rho_d,c a_c); ``set_ambient`` marks such a channel by
f[c] = 1 (the features leave the diffuse columns' f[0:3] at 0) and :func:`unlit_funcs` reads the mark.
"""

from __future__ import annotations

import functools
from typing import Any, NamedTuple

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


class LafortuneFuncs(NamedTuple):
    """The model functions of one layout (:func:`lafortune_funcs`)."""

    features: Any
    """``features(p, u, v, one)``: per lobe j at column offset o, f[o] = L_j, f[o + 3 + k] =
    dL_j/dC_j,k (isotropic: d/dc_xy, d/dc_z), f[o + stride - 1] = dL_j/dn_j; other entries 0.
    m and J are linear in f (:func:`model_value`, ``jacobian_row``), so a weighted mean of
    features over several directions gives the weighted mean model and Jacobian exactly (the
    filtered photo sampling of fit/kernels/accumulate.py)."""
    dhd: Any
    """``dhd(p, d, u, v, one)``: d^T (Hess m_c) d for c = r, g, b (the part the Gauss-Newton
    approximation drops)."""
    model_value: Any
    """``model_value(p, f, c)``: m_c from the features."""
    jacobian_row: Any
    """``jacobian_row(p, f, c)``: dm_c/dp, an n_params vector (zero outside channel c's columns
    and the lobes' shape columns)."""
    row_entry: Any
    """``row_entry(p, f, c, t)``: (column, value) of the t-th structurally non-zero entry of
    dm_c/dp, t < ``row_nonzeros``: t = 0 rho_d,c; 1..K rho_s,j,c; then the lobes' C and n; last the ambient's A_c
    (a layout with it)."""
    row_nonzeros: int
    set_ambient: Any
    """``set_ambient(f, share, weight)``: the features ``f`` with the ambient ones f[A_c] = share / W_c (share: the
    sample's exposure times texel i's share of its taps, W: the sample's weight, see the module doc); ``f``
    unchanged for a layout without ambient."""


@wp.func
def no_ambient(f: Any, share: Any, weight: Any):
    return f


def set_ambient_func(amb: int):
    """``set_ambient`` (:class:`LafortuneFuncs`) of a layout whose ambient (or room) columns start at ``amb``.

    A channel whose weight W_c is 0 (its light is exactly 0: a photo taken with the flash off) sees the ambient
    alone: its feature is the share itself (the residual's weight taken as 1, :func:`unlit_funcs`, no division by
    W) and f[c] = 1 marks the channel unlit (the features leave f[0:3], the diffuse columns, at 0)."""

    @wp.func
    def set_ambient(f: Any, share: Any, weight: Any):
        zero = share - share
        tiny = zero + type(share)(1.0e-30)
        out = f
        for c in range(3):
            if weight[c] > zero:
                out[wp.static(amb) + c] = share / wp.max(weight[c], tiny)
            else:
                out[c] = zero + type(share)(1.0)
                out[wp.static(amb) + c] = share
        return out

    return set_ambient


def unlit_funcs(model_value: Any, row_entry: Any, amb: int, room: bool, ambient_entry: int):
    """(model_value, row_entry) of a layout with the ambient (``room``: the room light's S) whose columns start at
    ``amb``: a lit channel's as the layout's own (the same arithmetic), an unlit one's (f[c] = 1, ``set_ambient``)
    the ambient's alone, m_c = A_c a_c (the room's: rho_d,c S_c a_c) with a_c the share and every other entry of the
    row 0 but ``ambient_entry`` (A's; the room's: S's and rho_d's, S_c a_c)."""

    @wp.func
    def unlit_model_value(p: Any, f: Any, c: int):
        if f[c] != p[0] - p[0]:
            if wp.static(room):
                return p[c] * p[wp.static(amb) + c] * f[wp.static(amb) + c]
            return p[wp.static(amb) + c] * f[wp.static(amb) + c]
        return model_value(p, f, c)

    @wp.func
    def unlit_row_entry(p: Any, f: Any, c: int, t: int):
        col, val = row_entry(p, f, c, t)
        zero = p[0] - p[0]
        if f[c] != zero:
            if t != wp.static(ambient_entry):
                val = zero
                if wp.static(room):
                    if t == 0:
                        val = p[wp.static(amb) + c] * f[wp.static(amb) + c]
        return col, val

    return unlit_model_value, unlit_row_entry


def jacobian_row_func(row_entry: Any, row_nonzeros: int):
    """``jacobian_row(p, f, c)`` of a model from its ``row_entry``: dm_c/dp as an n_params vector, its
    ``row_nonzeros`` structurally non-zero entries set with literal trip counts (kept in registers)."""

    @wp.func
    def jacobian_row(p: Any, f: Any, c: int):
        jc = p * (p[0] - p[0])
        for t in range(wp.static(row_nonzeros)):
            col, val = row_entry(p, f, c, t)
            jc[col] = val
        return jc

    return jacobian_row


@functools.cache
def lafortune_funcs(n_lobes: int, anisotropic: int, ambient: int = 0) -> LafortuneFuncs:
    """The model functions specialised to one layout (K = ``n_lobes``, isotropic or not, with or without the
    ambient radiance (``ambient`` 1) or the room light's S (2), whose columns follow the lobes).

    Every loop over lobes and columns has a compile-time trip count, so Warp unrolls it and
    every vector index is a literal: the parameter, feature and Jacobian vectors stay in
    registers instead of the thread's local memory, where run-time indices put them (Nsight
    Compute and ``benchmarks/kernel_resources.py`` show 336-472 bytes of local memory per GPU
    thread with run-time loops). One layout compiles its own functions and kernels.
    """
    n_lobes = int(n_lobes)
    aniso = int(anisotropic)
    stride = 6 + aniso
    n_shape = stride - 3  # C columns and n
    lobe_nonzeros = 1 + n_lobes + n_lobes * n_shape
    with_ambient = bool(ambient)
    with_room = int(ambient) == 2
    amb = 3 + n_lobes * stride  # the ambient columns (when the layout has them)
    row_nonzeros = lobe_nonzeros + int(with_ambient)

    @wp.func
    def lobe_base(p: Any, o: int, w: Any):
        """s = C . w for the lobe whose columns start at ``o``."""
        if wp.static(aniso != 0):
            return p[o + 3] * w[0] + p[o + 4] * w[1] + p[o + 5] * w[2]
        return p[o + 3] * (w[0] + w[1]) + p[o + 4] * w[2]

    @wp.func
    def features(p: Any, u: Any, v: Any, one: Any):
        zero = one - one
        f = p * zero
        w = lobe_weights(u, v)
        for j in range(wp.static(n_lobes)):
            o = 3 + j * wp.static(stride)
            s = lobe_base(p, o, w)
            if s > zero:
                n = p[o + wp.static(stride - 1)]
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
                if wp.static(aniso != 0):
                    f[o + 3] = dlds * w[0]
                    f[o + 4] = dlds * w[1]
                    f[o + 5] = dlds * w[2]
                else:
                    f[o + 3] = dlds * (w[0] + w[1])
                    f[o + 4] = dlds * w[2]
                f[o + wp.static(stride - 1)] = lobe * ls
        return f

    @wp.func
    def model_value(p: Any, f: Any, c: int):
        m = p[c]
        for j in range(wp.static(n_lobes)):
            o = 3 + j * wp.static(stride)
            m = m + p[o + c] * f[o]
        if wp.static(with_room):
            m = m + p[c] * p[wp.static(amb) + c] * f[wp.static(amb) + c]
        elif wp.static(with_ambient):
            m = m + p[wp.static(amb) + c] * f[wp.static(amb) + c]
        return m

    @wp.func
    def row_entry(p: Any, f: Any, c: int, t: int):
        if t == 0:
            if wp.static(with_room):
                return c, type(p[0])(1.0) + p[wp.static(amb) + c] * f[wp.static(amb) + c]
            return c, p[0] - p[0] + type(p[0])(1.0)
        if wp.static(with_room):
            if t == wp.static(lobe_nonzeros):
                return wp.static(amb) + c, p[c] * f[wp.static(amb) + c]
        elif wp.static(with_ambient):
            if t == wp.static(lobe_nonzeros):
                return wp.static(amb) + c, f[wp.static(amb) + c]
        if t <= wp.static(n_lobes):
            o = 3 + (t - 1) * wp.static(stride)
            return o + c, f[o]
        j = (t - 1 - wp.static(n_lobes)) // wp.static(n_shape)
        k = (t - 1 - wp.static(n_lobes)) % wp.static(n_shape)
        o = 3 + j * wp.static(stride)
        return o + 3 + k, p[o + c] * f[o + 3 + k]

    if with_ambient:  # wrapped for samples whose light is 0 (unlit_funcs); the other layouts compile as they did
        model_value, row_entry = unlit_funcs(model_value, row_entry, amb, with_room, lobe_nonzeros)
    jacobian_row = jacobian_row_func(row_entry, row_nonzeros)

    @wp.func
    def dhd(p: Any, d: Any, u: Any, v: Any, one: Any):
        zero = one - one
        out = type(u)(zero, zero, zero)
        w = lobe_weights(u, v)
        for j in range(wp.static(n_lobes)):
            o = 3 + j * wp.static(stride)
            s = lobe_base(p, o, w)
            if s > zero:
                n = p[o + wp.static(stride - 1)]
                dnj = d[o + wp.static(stride - 1)]
                ds = lobe_base(d, o, w)
                ls = wp.log(s)
                if n * ls <= type(one)(30.0):  # above: the flat cap, no curvature
                    lobe = wp.exp(n * ls)
                    q = n * ds / s + dnj * ls
                    l1 = lobe * q
                    l2 = lobe * q * q + lobe * ((one + one) * dnj * ds / s - n * ds * ds / (s * s))
                    da = type(u)(d[o], d[o + 1], d[o + 2])
                    a = type(u)(p[o], p[o + 1], p[o + 2])
                    out = out + (one + one) * l1 * da + l2 * a
        return out

    return LafortuneFuncs(features, dhd, model_value, jacobian_row, row_entry, row_nonzeros,
                          set_ambient_func(amb) if with_ambient else no_ambient)


@functools.cache
def view_radiance_funcs() -> LafortuneFuncs:
    """The model functions of the view-dependent radiance (render/layout.py, kind "view_radiance").

    m_c = p_c + sum_k p_(3 + 3k + c) phi_k(v), phi = (v_x, v_y, v_x^2, v_x v_y, v_y^2) of the local
    view direction v (``u``, the light, is unused). Features: f[3 + 3k + c] = phi_k(v) for every
    channel c (the same value three times, so ``model_value`` and ``row_entry`` index f at the
    parameter's own column); f[0:3] = 1. Linear in p: the Jacobian row of channel c has 6
    non-zeros (1, then phi_k) and d^T (Hess m_c) d = 0.
    """
    n_terms = 5
    row_nonzeros = 1 + n_terms

    @wp.func
    def features(p: Any, u: Any, v: Any, one: Any):
        f = p * (one - one)
        phi = wp.vector(v[0], v[1], v[0] * v[0], v[0] * v[1], v[1] * v[1])
        for c in range(3):
            f[c] = one
        for k in range(wp.static(n_terms)):
            for c in range(3):
                f[3 + 3 * k + c] = phi[k]
        return f

    @wp.func
    def model_value(p: Any, f: Any, c: int):
        m = p[c]
        for k in range(wp.static(n_terms)):
            m = m + p[3 + 3 * k + c] * f[3 + 3 * k + c]
        return m

    @wp.func
    def row_entry(p: Any, f: Any, c: int, t: int):
        if t == 0:
            return c, p[0] - p[0] + type(p[0])(1.0)
        col = 3 + 3 * (t - 1) + c
        return col, f[col]

    jacobian_row = jacobian_row_func(row_entry, row_nonzeros)

    @wp.func
    def dhd(p: Any, d: Any, u: Any, v: Any, one: Any):
        zero = one - one
        return type(u)(zero, zero, zero)

    return LafortuneFuncs(features, dhd, model_value, jacobian_row, row_entry, row_nonzeros, no_ambient)
