"""A synthetic scene's per-texel material parameters: its materials (BRDF values, smooth gradients, value-noise
albedo) laid on the texels by its assignment rule, and the room's light they reflect (the ``materials``,
``assignment`` and ``room_light`` keys of :mod:`texstream.capture.synthetic.synth`'s module doc)."""

from __future__ import annotations

import math

import numpy as np

from texstream.core.errors import ConfigError


def _axis_coord(axis: str, bake, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(H, W) coordinate s in [0, 1] of every texel along a named axis."""
    h, w = bake.height, bake.width
    if axis in ("x", "y", "z"):
        k = "xyz".index(axis)
        ext = max(hi[k] - lo[k], 1e-12)
        return np.clip((bake.position[..., k] - lo[k]) / ext, 0.0, 1.0)
    if axis == "u":
        return np.broadcast_to((np.arange(w) + 0.5) / w, (h, w))
    if axis == "v":
        return np.broadcast_to(1.0 - (np.arange(h)[:, None] + 0.5) / h, (h, w))
    raise ConfigError(f"unknown axis {axis!r}", fix="use x, y, z, u or v")


def value_noise(u: np.ndarray, v: np.ndarray, cells, octaves: int = 3, seed: int = 0) -> np.ndarray:
    """Multi-octave value noise in [-1, 1] at UV points (periodic in u; smoothstep interpolation).

    Args:
        u, v: (N,) coordinates in [0, 1].
        cells: int or (cu, cv), grid cells of the coarsest octave.
        octaves: octave count; octave o has 2**o times the cells and half the previous amplitude.
        seed: random seed of the lattice values.

    Returns:
        (N,) float64 noise values.
    """
    cu0, cv0 = (cells, cells) if isinstance(cells, (int, float)) else cells
    rng = np.random.default_rng([int(seed), 11])
    total, norm = np.zeros(np.shape(u)), 0.0
    for o in range(max(1, int(octaves))):
        cu, cv = max(1, int(cu0) << o), max(1, int(cv0) << o)
        lat = rng.uniform(-1.0, 1.0, size=(cv + 1, cu))
        x, y = np.clip(u, 0.0, 1.0) * cu, np.clip(v, 0.0, 1.0) * cv
        i0, j0 = np.minimum(np.floor(x).astype(int), cu), np.minimum(np.floor(y).astype(int), cv - 1)
        fx, fy = x - i0, y - j0
        fx, fy = fx * fx * (3 - 2 * fx), fy * fy * (3 - 2 * fy)  # smoothstep: no visible lattice creases
        ia, ib = i0 % cu, (i0 + 1) % cu  # periodic in u
        val = ((lat[j0, ia] * (1 - fx) + lat[j0, ib] * fx) * (1 - fy)
               + (lat[j0 + 1, ia] * (1 - fx) + lat[j0 + 1, ib] * fx) * fy)
        amp = 0.5 ** o
        total += amp * val
        norm += amp
    return total / norm


def material_params(scene: dict, layout, mesh, bake) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Per-texel parameters from the scene's materials and assignment rule.

    Returns:
        params (H, W, P) float32 (padding filled from chart neighbours; texels off the surface
        and beyond the padding hold rho = 0 and the default lobe shape), material id (H, W)
        int32 (-1 off the surface) and the material names.
    """
    names = list(scene["materials"])
    lo, hi = mesh.bbox()
    h, w = bake.height, bake.width
    a = scene["assignment"]
    if a["rule"] == "uniform":
        mid = np.full((h, w), names.index(a["material"]), dtype=np.int32)
    elif a["rule"] == "bands":
        s = _axis_coord(a.get("axis", "z"), bake, lo, hi)
        mid = np.full((h, w), names.index(a["bands"][-1][1]), dtype=np.int32)
        for upper, name in reversed(a["bands"]):
            mid[s < float(upper)] = names.index(name)
    else:  # checker
        cells = a.get("cells", [4, 4])
        cu, cv = (cells, cells) if isinstance(cells, (int, float)) else cells
        su = _axis_coord("u", bake, lo, hi) if a.get("space", "uv") == "uv" else _axis_coord("x", bake, lo, hi)
        sv = _axis_coord("v", bake, lo, hi) if a.get("space", "uv") == "uv" else _axis_coord("y", bake, lo, hi)
        parity = (np.floor(su * cu).astype(int) + np.floor(sv * cv).astype(int)) % 2
        mats = [names.index(x) for x in a["materials"]]
        mid = np.where(parity == 0, mats[0], mats[1]).astype(np.int32)
    mid[~bake.covered] = -1

    out = np.zeros((h, w, layout.n_params), dtype=np.float64)
    base = layout.pack(np.zeros(3), [{"rho_s": np.zeros(3), "n": layout.defaults()[layout.lobe_offset(j) + layout.lobe_stride - 1]}
                                     for j in range(layout.n_lobes)])
    out[:] = base
    for k, name in enumerate(names):
        mat = scene["materials"][name]
        sel = mid == k
        if not sel.any():
            continue
        g = mat.get("gradient")
        f_rho = np.ones(int(sel.sum()))
        f_n = np.ones(int(sel.sum()))
        if g:
            s = _axis_coord(g.get("axis", "x"), bake, lo, hi)[sel]
            f_rho = 1.0 + float(g.get("amount", 0.0)) * (2 * s - 1)
            f_n = 1.0 + float(g.get("n_amount", 0.0)) * (2 * s - 1)
        out[sel, 0:3] = np.asarray(mat["rho_d"], dtype=np.float64)[None] * f_rho[:, None]
        if mat.get("noise"):
            nz = mat["noise"]
            su, sv = _axis_coord("u", bake, lo, hi)[sel], _axis_coord("v", bake, lo, hi)[sel]
            val = value_noise(su, sv, nz.get("cells", 16), int(nz.get("octaves", 3)), int(nz.get("seed", 0)))
            k = float(nz.get("sharpness", 0.0))
            if k > 0:  # tanh contrast: blotches with sharp edges (corners and blobs at many scales)
                val = np.tanh(k * val) / math.tanh(k)
            f_tex = np.maximum(0.0, 1.0 + float(nz.get("amount", 0.5)) * val)
            out[sel, 0:3] *= f_tex[:, None]
        lobes = mat.get("lobes", [])
        if len(lobes) > layout.n_lobes:
            raise ConfigError(f"material {name!r} has {len(lobes)} lobes, the model {layout.n_lobes}",
                              fix="raise model.n_lobes or drop lobes")
        for j, lobe in enumerate(lobes):
            o = layout.lobe_offset(j)
            out[sel, o:o + 3] = np.asarray(lobe["rho_s"], dtype=np.float64)[None] * f_rho[:, None]
            if layout.anisotropic:
                out[sel, o + 3:o + 6] = [-1.0, float(lobe.get("c_y", -1.0)), float(lobe.get("c_z", 1.0))]
            else:
                out[sel, o + 3:o + 5] = [-1.0, float(lobe.get("c_z", 1.0))]
            out[sel, o + layout.lobe_stride - 1] = float(lobe["n"]) * f_n
    out = bake.fill_padding(out)
    return out.astype(np.float32), mid, names


def room_irradiance(room: dict, mesh, bake) -> np.ndarray:
    """(H, W, 3) irradiance the room's light casts on every texel: ``irradiance`` (a number or RGB) times
    1 + a (2 s - 1) along ``gradient``'s axis (s in [0, 1], as the materials' gradient; a = 0: uniform)."""
    e = np.broadcast_to(np.asarray(room.get("irradiance", 0.0), np.float64), (3,))
    g = room.get("gradient") or {}
    lo, hi = mesh.bbox()
    s = _axis_coord(g.get("axis", "z"), bake, lo, hi) if g else np.full((bake.height, bake.width), 0.5)
    factor = 1.0 + float(g.get("amount", 0.0)) * (2 * s - 1)
    if np.any(e < 0) or np.any(factor < 0):
        raise ConfigError(f"room_light {room} makes a negative irradiance", fix="use irradiance >= 0 and |amount| <= 1")
    return e[None, None, :] * factor[..., None]


def add_room_light(params: np.ndarray, layout, room: dict, mesh, bake) -> np.ndarray:
    """``params`` with the ambient columns (render/layout.py ``ambient_offset``) holding what a Lambertian texel
    sends back of the room's light: A = rho_d E_room (rho_d in 1/sr is the BRDF, so radiance = BRDF x irradiance;
    the lobes' share of a diffuse room light is left out: the term is the diffuse one)."""
    out = np.array(params, np.float32, copy=True)
    o = layout.ambient_offset
    out[..., o:o + 3] = (params[..., 0:3] * room_irradiance(room, mesh, bake)).astype(np.float32)
    return out
