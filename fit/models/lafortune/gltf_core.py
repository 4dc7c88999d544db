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

from texstream.fit.models.lafortune.gltf_core_kernel import fit_rows

DIELECTRIC_F0 = 0.04
ROUGHNESS_MIN = 0.04  # three.js clamps roughness to [0.04, 1]
METALLIC_STEPS = 101
ROUGHNESS_STEPS = 24
ROUGHNESS_REFINE = (0.95, 0.975, 1.025, 1.05)
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


def fit_core_material(grid: np.ndarray, layout, samples: DirectionSamples, fill_source: np.ndarray | None,
                      old: tuple[np.ndarray, np.ndarray, np.ndarray], device: str = "cpu") -> CoreMaterial:
    """The core material of a Lafortune parameter grid (H, W, P) under ``samples`` (module doc), fitted by
    gltf_core_kernel.py on Warp ``device``.

    ``fill_source``: bake.npz's (H, W) flat index of the covered texel each texel copies (padding takes its
    source's material; None: every texel fitted itself). ``old``: the export before (base = albedo, F0_d,
    roughness (H, W)), scored beside the fit in ``fit``."""
    h, w_, npar = grid.shape
    rows = np.asarray(grid, np.float64).reshape(-1, npar)
    own = np.arange(len(rows)) if fill_source is None else np.asarray(fill_source).reshape(-1)
    todo = np.unique(own)
    old_b, old_f0, old_r = (np.asarray(a, np.float64).reshape(len(rows), -1) for a in old)
    weight = samples.weight[0] / samples.weight.sum()
    fitted = fit_rows(rows[todo], layout, samples.light[0], samples.view[0], weight,
                      (old_b[todo], old_f0[todo], old_r[todo, 0]), np.geomspace(ROUGHNESS_MIN, 1.0, ROUGHNESS_STEPS),
                      ROUGHNESS_REFINE, ROUGHNESS_MIN, METALLIC_STEPS, device)
    base, metallic = np.zeros((len(rows), 3)), np.zeros(len(rows))
    rough, f0d = np.ones(len(rows)), np.full((len(rows), 3), DIELECTRIC_F0)
    base[todo], metallic[todo], rough[todo], f0d[todo], rel = fitted
    med = np.median(rel, axis=1)
    fit = {"directions": samples.source, "relative_rms_core": float(med[0]),
           "relative_rms_with_specular_extension": float(med[1]), "relative_rms_before_core": float(med[2]),
           "relative_rms_before_with_specular_extension": float(med[3]),
           "metallic_median": float(np.median(metallic[todo])), "roughness_median": float(np.median(rough[todo]))}
    return CoreMaterial(base[own].reshape(h, w_, 3), metallic[own].reshape(h, w_), rough[own].reshape(h, w_),
                        f0d[own].reshape(h, w_, 3), fit)
