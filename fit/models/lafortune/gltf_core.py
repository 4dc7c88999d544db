"""The core glTF metallic-roughness material that best reproduces a fitted Lafortune model under a point light.

A core glTF viewer (three.js's MeshStandardMaterial, Filament, most engines) shades a texel with baseColor b,
metallic m and roughness r (alpha = r^2) as

    f = b (1 - m) / pi + F D Vis,    F = F0 + (1 - F0) (1 - l.h)^5,    F0 = 0.04 (1 - m) + b m,

D the GGX distribution, Vis Smith's height-correlated visibility (G / (4 n.l n.v)); it ignores
KHR_materials_specular. The Lafortune model's lobe energy has no place there but the metallic part, so a
material with metallic 0 (the export before) loses every lobe in those viewers.

How the three maps are chosen: per texel, least squares over the light and view directions the photos saw
(:func:`capture_samples`: each fitted photo's camera and light seen from the texel's baked surface point and
frame) or, without a capture, a flash set (:func:`flash_samples`: a light beside the camera over the view
hemisphere). The residual is in radiance, ``(f_core - f_lafortune) E cos(theta_i)``, weighted by the texel's
pixel footprint in the photo (cos(theta_v) / depth^2), so it is the photos' squared error the choice minimises.
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
FLASH_SHARE = 0.5  # the flash set's share of a texel's weight beside the photos' directions (module doc)


@dataclasses.dataclass
class DirectionSamples:
    """Light and view directions per texel, in the texel's local frame (x tangent, y bitangent, z normal).

    Attributes:
        light, view: (T or 1, S, 3) unit vectors (1: the same set for every texel).
        weight: (T or 1, S) >= 0: (irradiance E cos(theta_i))^2 times the texel's pixel footprint in the photo
            (0: no sample). Per texel only ratios matter.
        source: what the directions are ("capture: N photos" or "flash set").
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
    (every 10) at azimuths 0, 45 and 90 degrees (the anisotropic lobes' axes and between), each with the light
    on the view direction and 8 and 16 degrees off it in four directions (a flash 0-30 cm from the lens at
    1 m). Weights cos(theta_v) sin(theta_v) (the texel's projected area times the solid angle of the view
    ring) times cos(theta_i)^2 (the radiance residual's scale); irradiance 1."""
    views, lights, weights = [], [], []
    for th in np.radians(np.arange(5.0, 80.0, 10.0)):
        for ph in np.radians([0.0, 45.0, 90.0]):
            v = np.array([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)])
            e1 = np.array([np.cos(th) * np.cos(ph), np.cos(th) * np.sin(ph), -np.sin(th)])
            e2 = np.cross(v, e1)
            offsets = [(0.0, 0.0)] + [(d, a) for d in np.radians([8.0, 16.0]) for a in np.radians([0, 90, 180, 270])]
            for d, a in offsets:
                ell = np.cos(d) * v + np.sin(d) * (np.cos(a) * e1 + np.sin(a) * e2)
                if ell[2] <= 0:
                    continue
                views.append(v)
                lights.append(ell)
                weights.append(np.cos(th) * np.sin(th) * ell[2] ** 2)
    return DirectionSamples(np.asarray(lights)[None], np.asarray(views)[None], np.asarray(weights)[None], "flash set")


def capture_samples(bake: dict, frames) -> DirectionSamples:
    """The directions the photos saw: for each frame (a capture.json ``Frame`` with a point or directional
    light) and each texel with a baked surface point (``bake``: bake.npz's ``position``, ``normal``,
    ``tangent``, ``bitangent``, (H, W, 3)), the camera and light as seen from the point, where the point is in
    front of the camera, inside the image and both directions are above its surface. Occlusion is not tested:
    a direction the texel was hidden from is still one the model was fitted for in its neighbours, and the
    target is the fitted model, not the photo. Returns (H * W, S) arrays, S = the number of frames."""
    p = np.asarray(bake["position"], np.float64).reshape(-1, 3)
    frame3 = np.stack([np.asarray(bake[k], np.float64).reshape(-1, 3) for k in ("tangent", "bitangent", "normal")],
                      axis=1)  # (T, 3, 3): rows t, b, n
    n = frame3[:, 2]
    lights, views, weights = [], [], []
    for f in frames:
        k = f.intrinsics
        cam = p @ np.asarray(f.R).T + np.asarray(f.t).reshape(1, 3)
        z = cam[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u, vv = k.fx * cam[:, 0] / z + k.cx, k.fy * cam[:, 1] / z + k.cy
        v = f.center[None] - p
        dist = np.linalg.norm(v, axis=1)
        v = v / np.maximum(dist, 1e-30)[:, None]
        if f.light.type == "point":
            ell = np.asarray(f.light.position, np.float64)[None] - p
            r2 = np.maximum(np.einsum("ij,ij->i", ell, ell), 1e-30)
            ell, irr = ell / np.sqrt(r2)[:, None], float(np.mean(f.light.intensity)) / r2
        else:
            ell = np.broadcast_to(-np.asarray(f.light.direction, np.float64), p.shape)
            irr = np.full(len(p), float(np.mean(f.light.intensity)))
        cos_v, cos_i = np.einsum("ij,ij->i", n, v), np.einsum("ij,ij->i", n, ell)
        ok = (z > 0) & (u >= 0) & (u < k.width) & (vv >= 0) & (vv < k.height) & (cos_v > 0) & (cos_i > 0)
        ok &= np.linalg.norm(n, axis=1) > 0.5
        lights.append(np.einsum("tij,tj->ti", frame3, ell))
        views.append(np.einsum("tij,tj->ti", frame3, v))
        weights.append(np.where(ok, (irr * cos_i) ** 2 * cos_v / np.maximum(z * z, 1e-30), 0.0))
    return DirectionSamples(np.stack(lights, 1), np.stack(views, 1), np.stack(weights, 1),
                            f"capture: {len(frames)} photos")


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


def _best_for_roughness(y, w, dv, x5, metal):
    """For one roughness per texel (``dv``, ``x5`` (T, S)): the best metallic on the grid ``metal`` (K,) and its
    base colour and squared error, from weighted moments (module doc). Returns (err (T,), m (T,), b (T, 3))."""
    a = dv * (1 - x5)
    p, q = 1.0 / np.pi, a - 1.0 / np.pi
    s, t = dv * x5 + DIELECTRIC_F0 * a, -DIELECTRIC_F0 * a  # g0 = s + m t, g1 = p + m q

    def mom(u, v):
        return np.einsum("ts,ts,ts->t", w, u, v)

    sw = w.sum(axis=1)
    pp, pq, qq = p * p * sw, p * (w * q).sum(1), mom(q, q)
    ps, pt, qs, qt = p * (w * s).sum(1), p * (w * t).sum(1), mom(q, s), mom(q, t)
    ss, st, tt = mom(s, s), mom(s, t), mom(t, t)
    py, qy = p * np.einsum("ts,tsc->tc", w, y), np.einsum("ts,ts,tsc->tc", w, q, y)
    sy, ty = np.einsum("ts,ts,tsc->tc", w, s, y), np.einsum("ts,ts,tsc->tc", w, t, y)
    yy = np.einsum("ts,tsc,tsc->tc", w, y, y)
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
    """Core (b, m, r) and the extension's F0_d for a chunk of texels (module doc)."""
    metal = np.linspace(0.0, 1.0, METALLIC_STEPS)
    best_err = np.full(len(y), np.inf)
    best_m, best_r, best_b = np.zeros(len(y)), np.ones(len(y)), np.zeros((len(y), 3))

    def consider(rough):
        nonlocal best_err, best_m, best_r, best_b
        dv, x5 = ggx_terms(light, view, (rough ** 2)[:, None])
        err, m, b = _best_for_roughness(y, w, np.broadcast_to(dv, w.shape), np.broadcast_to(x5, w.shape), metal)
        better = err < best_err
        best_err = np.where(better, err, best_err)
        best_m, best_r = np.where(better, m, best_m), np.where(better, rough, best_r)
        best_b = np.where(better[:, None], b, best_b)

    for r in np.geomspace(ROUGHNESS_MIN, 1.0, ROUGHNESS_STEPS):
        consider(np.full(len(y), r))
    coarse = best_r.copy()
    for f in ROUGHNESS_REFINE:
        consider(np.clip(coarse * f, ROUGHNESS_MIN, 1.0))
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
    source's material; None: every texel fitted itself). Texels without a sample (none of the photos saw
    their directions) take the flash set. ``old``: the export before (base = albedo, F0_d, roughness (H, W)),
    scored beside the fit in ``fit``."""
    h, w_, npar = grid.shape
    rows = np.asarray(grid, np.float64).reshape(-1, npar)
    own = np.arange(len(rows)) if fill_source is None else np.asarray(fill_source).reshape(-1)
    todo = np.unique(own)
    flash = flash_samples()
    base, metallic = np.zeros((len(rows), 3)), np.zeros(len(rows))
    rough, f0d = np.ones(len(rows)), np.full((len(rows), 3), DIELECTRIC_F0)
    rel = np.zeros((4, len(rows)))  # per texel relative RMS: core, core + extension, before (core, extension)
    old_b, old_f0, old_r = (np.asarray(a, np.float64).reshape(len(rows), -1) for a in old)
    for lo in range(0, len(todo), TEXEL_CHUNK):
        idx = todo[lo:lo + TEXEL_CHUNK]
        light, view, wt = _chunk_samples(samples, flash, idx)
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


def _chunk_samples(samples: DirectionSamples, flash: DirectionSamples, idx: np.ndarray):
    """(light, view, weight) of texels ``idx``: the capture's samples with weights summing to 1 - FLASH_SHARE and
    the flash set's to FLASH_SHARE (all of it for a texel the photos never saw); a set shared by every texel
    (the flash set) alone."""
    t = len(idx)

    def norm(w):
        s = w.sum(axis=1, keepdims=True)
        return np.where(s > 0, w / np.where(s > 0, s, 1.0), 0.0)

    if len(samples.weight) == 1:
        flash = samples
    fw = np.broadcast_to(norm(flash.weight), (t, flash.weight.shape[1]))
    fl, fv = (np.broadcast_to(a, (t,) + a.shape[1:]) for a in (flash.light, flash.view))
    if flash is samples:
        return fl, fv, fw
    cw = norm(samples.weight[idx])
    seen = cw.sum(axis=1, keepdims=True) > 0
    return (np.concatenate([samples.light[idx], fl], axis=1), np.concatenate([samples.view[idx], fv], axis=1),
            np.concatenate([cw * (1 - FLASH_SHARE), fw * np.where(seen, FLASH_SHARE, 1.0)], axis=1))
