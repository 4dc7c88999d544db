"""The core glTF metallic-roughness material that best reproduces a fitted Lafortune model under a point light.

A core glTF viewer (three.js's MeshStandardMaterial, Filament, most engines) shades a texel with baseColor b,
metallic m and roughness r (alpha = r^2) as

    f = b (1 - m) / pi + F D Vis,    F = F0 + (1 - F0) (1 - l.h)^5,    F0 = 0.04 (1 - m) + b m,

D the GGX distribution, Vis Smith's height-correlated visibility (G / (4 n.l n.v)); it ignores
KHR_materials_specular. The Lafortune model's lobe energy has no place there but the metallic part, so a
material with metallic 0 (the export before) loses every lobe in those viewers.

How the three maps are chosen: per texel, least squares over a flash set (:func:`flash_samples`: a light
beside the camera, on it and 8 and 16 degrees off it, over the view hemisphere: the geometry of a flash capture,
whose photos the model was fitted to). The residual is in radiance, ``(f_core - f_lafortune) cos(theta_i)``,
weighted by the texel's projected area (cos(theta_v) sin(theta_v) per view ring), so it is an image's squared
error the choice minimises. Why not the photos' own directions: a texel is seen by a few dozen photos, and its
highlight peak (a Lafortune lobe of exponent 60 is 17 degrees wide) falls between them; fitted to them alone the
GGX lobe shrank to a needle that no photo saw (the README demo's held-out view: 19.9 dB in three.js against
38.4 dB with the flash set); mixed with the flash set (10 / 25 / 50% of the weight on the flash set: 31.5 /
38.1 / 38.4 dB) they added nothing, so the export uses the flash set alone and needs no capture.
For fixed (m, r) the core BRDF is affine in b, channel by channel (the diffuse term b (1 - m) / pi and
F0's b m both are), so b is the least-squares value clipped to [0, 1] (exact for a 1-D quadratic), and its
error needs only a few weighted moments over the samples; m runs over a grid of 101 values (step 0.01, from the
moments alone) and r over 24 geometric values in [0.04, 1] (three.js clamps roughness at 0.04), refined
around the best by +-2.5% and +-5%. Why least squares and not an analytic map (exponent -> roughness, lobe
energy -> metallic): GGX's lobe is not a Phong lobe (its core is sharper and its tails heavier, docs/export.md)
and F0 = mix(0.04, b, m) ties the specular colour to the diffuse one, so the best compromise depends on the
angles the texel is seen at; the fit finds it and reports what is left (``relative_rms``).

KHR_materials_specular on top (viewers that read it): it changes only the dielectric part's F0, ``F0 =
(1 - m) F0_d + m b`` with ``F0_d = min(0.04 specularColorFactor specularColorTexture, 1) specularFactor`` (and
F90 = 1 for specularFactor 1). With (b, m, r) fixed by the core fit, F0_d is the per-channel least-squares
value in [0, 1] (affine again); F0_d = 0.04 gives the core material back, so a viewer that reads the extension
renders the model at least as well as one that does not (in this BRDF), and both agree where the core alone
was exact.

Not modelled: the glTF specification's reference implementation also dims the dielectric's diffuse term by
(1 - F) (three.js and Filament do not, for punctual lights): 4% along the normal. Cast shadows and
interreflections are the renderer's, not the material's.
"""

from __future__ import annotations

import dataclasses

import numpy as np

DIELECTRIC_F0 = 0.04
ROUGHNESS_MIN = 0.04  # three.js clamps roughness to [0.04, 1]
METALLIC_STEPS = 101
ROUGHNESS_STEPS = 24
ROUGHNESS_REFINE = (0.95, 0.975, 1.025, 1.05)
TEXEL_CHUNK = 1024
FLASH_OFFSETS_DEG = (0.0, 8.0, 16.0)  # the light's angles off the view direction (flash_samples)


@dataclasses.dataclass
class DirectionSamples:
    """Light and view directions, the same for every texel, in the texel's local frame (x tangent, y bitangent,
    z normal).

    Attributes:
        light, view: (1, S, 3) unit vectors.
        weight: (1, S) >= 0: cos(theta_i)^2 (the radiance residual's scale) times the texel's projected area.
        source: what the directions are, for export.json.
    """

    light: np.ndarray
    view: np.ndarray
    weight: np.ndarray
    source: str


@dataclasses.dataclass
class CoreMaterial:
    """The fitted glTF material per texel: base_color (H, W, 3) linear in [0, 1], metallic (H, W), roughness
    (H, W) in [0.04, 1], specular_f0 (H, W, 3): KHR_materials_specular's dielectric F0 in [0, 1]; ``fit``: the
    directions' source and the median over texels of the relative RMS radiance error over the samples: core,
    core + extension, and the export before (b = albedo, metallic 0, roughness from the exponent, the lobe energy
    in the extension alone) without and with the extension."""

    base_color: np.ndarray
    metallic: np.ndarray
    roughness: np.ndarray
    specular_f0: np.ndarray
    fit: dict


def flash_samples() -> DirectionSamples:
    """A light beside the camera over the view hemisphere, for every texel: view polar angles 5..75 degrees
    (every 10) at azimuths 0, 45 and 90 degrees (an anisotropic lobe's axes and between), each with the light
    on the view direction and 8 and 16 degrees off it in four directions (a flash 0-30 cm from the lens at 1 m;
    the README demo's is 15 degrees off: a set with the light 15 degrees off at 8 azimuths and views every 5
    degrees gave the same 38.41 dB). Weights cos(theta_v) sin(theta_v) (the texel's projected area times the
    solid angle of the view ring) times cos(theta_i)^2 (the radiance residual's scale)."""
    views, lights, weights = [], [], []
    offsets = [(0.0, 0.0)] + [(d, a) for d in np.radians(FLASH_OFFSETS_DEG[1:]) for a in np.radians([0, 90, 180, 270])]
    for th in np.radians(np.arange(5.0, 80.0, 10.0)):
        for ph in np.radians([0.0, 45.0, 90.0]):
            v = np.array([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)])
            e1 = np.array([np.cos(th) * np.cos(ph), np.cos(th) * np.sin(ph), -np.sin(th)])
            e2 = np.cross(v, e1)
            for d, a in offsets:
                ell = np.cos(d) * v + np.sin(d) * (np.cos(a) * e1 + np.sin(a) * e2)
                if ell[2] <= 0:
                    continue
                views.append(v)
                lights.append(ell)
                weights.append(np.cos(th) * np.sin(th) * ell[2] ** 2)
    return DirectionSamples(np.asarray(lights)[None], np.asarray(views)[None], np.asarray(weights)[None],
                            "flash set: light 0, 8 and 16 degrees off the view")


def lafortune_brdf(grid_rows: np.ndarray, layout, light: np.ndarray, view: np.ndarray) -> np.ndarray:
    """The Lafortune BRDF (render/shading.py ``lafortune_brdf``, in numpy): rows (T, P), local directions
    (T or 1, S, 3) -> (T, S, 3)."""
    g = np.asarray(grid_rows, np.float64)
    out = np.broadcast_to(g[:, None, 0:3], (len(g), light.shape[1], 3)).copy()
    for j in range(layout.n_lobes):
        o = layout.lobe_offset(j)
        cs = g[:, o + 3:o + layout.lobe_stride - 1]
        cx, cy, cz = (cs[:, 0], cs[:, 0], cs[:, 1]) if not layout.anisotropic else (cs[:, 0], cs[:, 1], cs[:, 2])
        s = (cx[:, None] * light[..., 0] * view[..., 0] + cy[:, None] * light[..., 1] * view[..., 1]
             + cz[:, None] * light[..., 2] * view[..., 2])
        with np.errstate(divide="ignore"):
            lobe = np.where(s > 0, np.exp(np.minimum(g[:, o + layout.lobe_stride - 1, None] * np.log(np.maximum(s, 1e-300)),
                                                     30.0)), 0.0)
        out += lobe[..., None] * g[:, None, o:o + 3]
    return out


def ggx_terms(light: np.ndarray, view: np.ndarray, alpha: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """D * Vis (GGX, Smith height-correlated) and Schlick's (1 - l.h)^5 for local directions (..., 3) and
    alpha broadcasting against (...)."""
    h = light + view
    h = h / np.maximum(np.linalg.norm(h, axis=-1, keepdims=True), 1e-30)
    nl, nv, nh = np.clip(light[..., 2], 0, 1), np.clip(view[..., 2], 0, 1), np.clip(h[..., 2], 0, 1)
    lh = np.clip(np.sum(light * h, axis=-1), 0, 1)
    a2 = alpha * alpha
    d = a2 / (np.pi * (nh * nh * (a2 - 1.0) + 1.0) ** 2)
    vis = 0.5 / np.maximum(nl * np.sqrt(a2 + (1 - a2) * nv * nv) + nv * np.sqrt(a2 + (1 - a2) * nl * nl), 1e-12)
    return d * vis, (1.0 - lh) ** 5


def core_brdf(base: np.ndarray, metallic: np.ndarray, roughness: np.ndarray, light: np.ndarray, view: np.ndarray,
              specular_f0: np.ndarray | None = None) -> np.ndarray:
    """The core glTF BRDF as three.js shades a punctual light (module doc): per texel base (T, 3), metallic and
    roughness (T,), directions (T or 1, S, 3) -> (T, S, 3); ``specular_f0`` (T, 3): KHR_materials_specular's
    dielectric F0 (None: 0.04, the core material)."""
    dv, x5 = ggx_terms(light, view, (np.asarray(roughness, np.float64) ** 2)[:, None])
    m = np.asarray(metallic, np.float64)[:, None, None]
    f0d = DIELECTRIC_F0 if specular_f0 is None else np.asarray(specular_f0, np.float64)[:, None]
    f0 = (1 - m) * f0d + m * np.asarray(base, np.float64)[:, None]
    return np.asarray(base)[:, None] * (1 - m) / np.pi + (dv * (1 - x5))[..., None] * f0 + (dv * x5)[..., None]


def _wsum(wu: np.ndarray, y: np.ndarray) -> np.ndarray:
    """sum over samples of wu * y: ``wu`` (S,) shared by the texels or (T, S), ``y`` (T, S, 3) -> (T, 3)."""
    return np.einsum("s,tsc->tc" if wu.ndim == 1 else "ts,tsc->tc", wu, y)


def _best_for_roughness(y, w, dv, x5, metal, yy):
    """For one roughness per texel (``dv``, ``x5``: (S,) when every texel has the same roughness, else (T, S);
    ``w`` likewise): the best metallic on the grid ``metal`` (K,) and its base colour and squared error, from
    weighted moments (module doc); ``yy`` (T, 3) the weighted sum of y^2. Returns (err (T,), m (T,), b (T, 3))."""
    a = dv * (1 - x5)
    p, q = 1.0 / np.pi, a - 1.0 / np.pi
    s, t = dv * x5 + DIELECTRIC_F0 * a, -DIELECTRIC_F0 * a  # g0 = s + m t, g1 = p + m q

    def mom(u, v):  # (T,), or (1,) for directions and weights shared by the texels
        return np.atleast_1d((w * u * v).sum(axis=-1))

    pp, pq, qq = p * p * np.atleast_1d(w.sum(axis=-1)), p * mom(q, 1.0), mom(q, q)
    ps, pt, qs, qt = p * mom(s, 1.0), p * mom(t, 1.0), mom(q, s), mom(q, t)
    ss, st, tt = mom(s, s), mom(s, t), mom(t, t)
    py, qy, sy, ty = p * _wsum(w, y), _wsum(w * q, y), _wsum(w * s, y), _wsum(w * t, y)
    m = metal[None, :, None]  # (1, K, 1)
    g2 = (pp[:, None] + 2 * metal[None] * pq[:, None] + metal[None] ** 2 * qq[:, None])[..., None]
    gy = (py[:, None] + m * qy[:, None] - (ps[:, None, None] + m * (qs + pt)[:, None, None]
                                           + m * m * qt[:, None, None]))
    r2 = (yy[:, None] - 2 * (sy[:, None] + m * ty[:, None]) + ss[:, None, None] + 2 * m * st[:, None, None]
          + m * m * tt[:, None, None])
    b = np.clip(gy / np.maximum(g2, 1e-300), 0.0, 1.0)
    err = (r2 - 2 * b * gy + b * b * g2).sum(axis=2)  # (T, K)
    k = np.argmin(err, axis=1)
    rows = np.arange(len(k))
    return err[rows, k], metal[k], b[rows, k]


def _fit_chunk(y, w, light, view) -> tuple[np.ndarray, ...]:
    """Core (b, m, r) and the extension's F0_d for a chunk of texels (module doc). The coarse roughness grid
    gives every texel the same roughness, so its GGX terms and moments are computed once for the chunk (the
    directions and weights are every texel's): only the refinement works per texel."""
    metal = np.linspace(0.0, 1.0, METALLIC_STEPS)
    best_err = np.full(len(y), np.inf)
    best_m, best_r, best_b = np.zeros(len(y)), np.ones(len(y)), np.zeros((len(y), 3))
    yy = _wsum(w[0], y * y)

    def consider(rough, dv, x5, wt):
        nonlocal best_err, best_m, best_r, best_b
        err, m, b = _best_for_roughness(y, wt, dv, x5, metal, yy)
        better = err < best_err
        best_err = np.where(better, err, best_err)
        best_m, best_r = np.where(better, m, best_m), np.where(better, rough, best_r)
        best_b = np.where(better[:, None], b, best_b)

    for r in np.geomspace(ROUGHNESS_MIN, 1.0, ROUGHNESS_STEPS):
        dv, x5 = ggx_terms(light[0], view[0], r * r)
        consider(np.full(len(y), r), dv, x5, w[0])
    coarse = best_r.copy()
    for f in ROUGHNESS_REFINE:
        rough = np.clip(coarse * f, ROUGHNESS_MIN, 1.0)
        dv, x5 = ggx_terms(light, view, (rough ** 2)[:, None])
        consider(rough, dv, x5, w)
    dv, x5 = ggx_terms(light, view, (best_r ** 2)[:, None])
    kk = ((1 - best_m)[:, None] * dv * (1 - x5))[..., None]  # d f / d F0_d
    g = core_brdf(best_b, best_m, best_r, light, view) - DIELECTRIC_F0 * kk
    num, den = np.einsum("ts,tsc->tc", w, kk * (y - g)), np.einsum("ts,tsc->tc", w, kk * kk)
    f0d = np.where(den > 0, np.clip(num / np.where(den > 0, den, 1.0), 0.0, 1.0), DIELECTRIC_F0)
    return best_b, best_m, best_r, f0d


def fit_core_material(grid: np.ndarray, layout, samples: DirectionSamples, fill_source: np.ndarray | None,
                      old: tuple[np.ndarray, np.ndarray, np.ndarray]) -> CoreMaterial:
    """The core material of a Lafortune parameter grid (H, W, P) under ``samples`` (module doc).

    ``fill_source``: bake.npz's (H, W) flat index of the covered texel each texel copies (padding takes its
    source's material; None: every texel fitted itself). ``old``: the export before (base = albedo, F0_d,
    roughness (H, W)), scored beside the fit in ``fit``."""
    h, w_, npar = grid.shape
    rows = np.asarray(grid, np.float64).reshape(-1, npar)
    own = np.arange(len(rows)) if fill_source is None else np.asarray(fill_source).reshape(-1)
    todo = np.unique(own)
    base, metallic = np.zeros((len(rows), 3)), np.zeros(len(rows))
    rough, f0d = np.ones(len(rows)), np.full((len(rows), 3), DIELECTRIC_F0)
    rel = np.zeros((4, len(rows)))  # per texel relative RMS: core, core + extension, before (core, extension)
    old_b, old_f0, old_r = (np.asarray(a, np.float64).reshape(len(rows), -1) for a in old)
    for lo in range(0, len(todo), TEXEL_CHUNK):
        idx = todo[lo:lo + TEXEL_CHUNK]
        light, view = (np.broadcast_to(a, (len(idx),) + a.shape[1:]) for a in (samples.light, samples.view))
        wt = np.broadcast_to(samples.weight / samples.weight.sum(), (len(idx), samples.weight.shape[1]))
        y = lafortune_brdf(rows[idx], layout, light, view)
        b, m, r, f = _fit_chunk(y, wt, light, view)
        base[idx], metallic[idx], rough[idx], f0d[idx] = b, m, r, f
        zero = np.zeros(len(idx))
        yy = np.maximum(np.einsum("ts,tsc->t", wt, y * y), 1e-300)
        for k, pred in enumerate((core_brdf(b, m, r, light, view), core_brdf(b, m, r, light, view, f),
                                  core_brdf(old_b[idx], zero, old_r[idx, 0], light, view),
                                  core_brdf(old_b[idx], zero, old_r[idx, 0], light, view, old_f0[idx]))):
            rel[k, idx] = np.sqrt(np.einsum("ts,tsc->t", wt, (pred - y) ** 2) / yy)
    med = np.median(rel[:, todo], axis=1)
    fit = {"directions": samples.source, "relative_rms_core": float(med[0]),
           "relative_rms_with_specular_extension": float(med[1]), "relative_rms_before_core": float(med[2]),
           "relative_rms_before_with_specular_extension": float(med[3]),
           "metallic_median": float(np.median(metallic[todo])), "roughness_median": float(np.median(rough[todo]))}
    return CoreMaterial(base[own].reshape(h, w_, 3), metallic[own].reshape(h, w_), rough[own].reshape(h, w_),
                        f0d[own].reshape(h, w_, 3), fit)
