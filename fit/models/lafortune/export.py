"""The Lafortune (and diffuse) model's material for glTF and OBJ (fit/stages/export.py writes it).

texstream fits per-texel Lafortune parameters (BRDF values in 1/sr, capture/conventions.py). Viewers
and DCC tools read a PBR metallic-roughness glTF or a Phong-style OBJ/MTL instead, so the export
converts (docs/export.md has the same text with the numbers). The glTF material is the core
metallic-roughness material fitted to the model by least squares (gltf_core.py; ``ExportMaterial.pbr``),
with KHR_materials_specular's F0 fitted on top; what follows is the OBJ's material and the analytic
conversions the fit is compared with (the export before it: base colour = albedo, metallic 0, the lobes'
energy in KHR_materials_specular alone, which core viewers ignore):

base colour
    Diffuse albedo ``pi * rho_d`` (the Lambertian BRDF rho_d in 1/sr reflects ``pi * rho_d``),
    clipped to [0, 1] and stored as an 8-bit sRGB PNG (glTF's baseColorTexture and OBJ's map_Kd are
    sRGB). metallic = 0 (every texstream model is a dielectric-style diffuse + specular mix).

specular colour (KHR_materials_specular, OBJ Ks / map_Ks)
    Lobe j reflects ``a_j = rho_s,j * 2 pi / (n_j + 2)`` of light arriving along the normal (the
    integral of ``rho_s max(s, 0)^n cos`` over the hemisphere with c_z = 1; the same quantity the
    fit's energy bound caps, render/layout.py). ``F0 = min(sum_j a_j, 1)`` per channel is the glTF
    dielectric F0 (energy matched, not peak matched: see :func:`lobe_conversion_table`). glTF makes
    ``F0 = min(0.04 * specularColorFactor * specularColorTexture, 1) * specularFactor``, so the
    texture holds ``F0 / s`` (s = the largest F0 over covered texels and channels: the texture uses
    the whole 8-bit range), ``specularColorFactor = s / 0.04`` (may exceed 1, the extension allows it)
    and ``specularFactor = 1``. A diffuse-only model writes ``specularFactor = 0``, which removes the
    specular layer (a pure Lambertian material). OBJ: ``Ks = s`` and ``map_Ks`` = the same texture.

roughness (glTF metallicRoughnessTexture G channel, OBJ Ns)
    A Lafortune lobe with c_z = 1 is a Phong lobe ``cos^n`` about the mirror direction. GGX takes
    ``alpha = roughness^2``. The default ("fitted") conversion is ``alpha = sqrt(0.72 / (n + 3))``:
    0.72 is the minimax fit of GGX's peak-normalised in-plane lobe to ``cos^n`` for large n, the +3
    keeps small exponents close to their own best fit. "blinn4" is the textbook chain, for reference:
    Phong exponent n ~ Blinn-Phong 4n about the half vector, Walter et al. 2007's Beckmann
    ``alpha = sqrt(2 / (n_bp + 2))``, GGX alpha taken equal to Beckmann alpha: ``alpha =
    sqrt(2 / (4 n + 2))`` (treating n itself as a Blinn-Phong exponent, sqrt(2 / (n + 2)), makes
    GGX's lobe 55% too wide at half maximum for n >= 100). With two lobes the texel's roughness
    comes from the lobe with the larger albedo. OBJ has one Ns per material: the median dominant
    exponent over covered texels, clipped to [1, 1000].

    Errors, measured by :func:`lobe_conversion_table` (light along the normal; widths are full
    widths at half maximum in the plane of incidence; "shape" is the largest difference of the
    peak-normalised lobes; "albedo" is GGX's directional albedo with F0 = 1 (Lafortune's is 1 by
    construction); "peak" is GGX's peak over Lafortune's with F0 = the lobe albedo):

    ====== ====== ========= ========= ========= ====== ====== ====== =====
    n      alpha  roughness FWHM Laf. FWHM GGX  width  shape  albedo peak
    ====== ====== ========= ========= ========= ====== ====== ====== =====
    fitted (the default)
    1      0.424  0.651     120.0 deg 87.4 deg  -27%   0.44   0.76   0.93
    10     0.235  0.485     42.2 deg  37.5 deg  -11%   0.094  0.93   0.75
    100    0.0836 0.289     13.5 deg  12.4 deg  -7.6%  0.061  0.99   0.70
    1000   0.0268 0.164     4.28 deg  3.95 deg  -7.6%  0.058  1.00   0.70
    10000  0.0085 0.092     1.34 deg  1.25 deg  -6.7%  0.058  1.00   0.69
    blinn4
    10     0.218  0.467     42.2 deg  34.4 deg  -19%   0.13   0.94   0.88
    100    0.0705 0.266     13.5 deg  10.5 deg  -22%   0.16   0.99   0.99
    1000   0.0224 0.150     4.28 deg  3.30 deg  -23%   0.16   1.00   1.00
    ====== ====== ========= ========= ========= ====== ====== ====== =====

    With the light 45 degrees off the normal (fitted): shape 0.45 / 0.11 / 0.075 and width +5.8% /
    -6.7% / -7.4% for n = 10 / 100 / 1000 (GGX's lobe leans and stretches towards grazing, the
    Phong lobe stays round about the mirror direction). The fitted alpha is within 1% of the alpha
    that minimises the shape difference for n >= 10 (n = 1: 0.424 against 0.377). Energy matching
    leaves sharp GGX highlights 30% lower at their peak and wider in the tails than the Lafortune
    lobe; matching the peak instead would add 45% to the reflected energy (environment-lit viewers
    show energy, so the export matches it).

    Not representable in glTF and dropped: c_z < 1 (off-specular shape: the lobe keeps its height
    and width), the anisotropic c_y (the lobe is exported as if isotropic), a second lobe's own width, and the
    missing Fresnel rise (glTF's dielectric reflects more towards grazing, f90 = specularFactor = 1;
    it also darkens the diffuse layer by ``1 - max(F)``, i.e. by max(F0) along the normal).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from texstream.core.errors import ConfigError
from texstream.fit.models.lafortune.gltf_core import DirectionSamples, fit_core_material, flash_samples
from texstream.fit.models.registry import ExportMaterial

ROUGHNESS_CONVERSIONS = ("fitted", "blinn4")
MTL_NS_MAX = 1000.0


def albedo_from_rho_d(rho_d: np.ndarray) -> np.ndarray:
    """Diffuse albedo of a Lambertian BRDF value rho_d (1/sr): ``pi * rho_d``."""
    return np.pi * np.asarray(rho_d, dtype=np.float64)


def lobe_albedo(rho_s: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Albedo of a Phong lobe ``rho_s max(s, 0)^n`` lit along the normal: ``rho_s * 2 pi / (n + 2)``.

    ``rho_s`` (..., 3) and ``n`` (...) broadcast; returns (..., 3)."""
    n = np.asarray(n, dtype=np.float64)
    return np.asarray(rho_s, dtype=np.float64) * (2.0 * np.pi / (n + 2.0))[..., None]


def ggx_alpha_from_exponent(n: np.ndarray, conversion: str = "fitted") -> np.ndarray:
    """GGX alpha of a Lafortune / Phong exponent n (module doc): fitted ``sqrt(0.72 / (n + 3))``,
    blinn4 ``sqrt(2 / (4 n + 2))``."""
    n = np.maximum(np.asarray(n, dtype=np.float64), 0.0)
    if conversion == "fitted":
        return np.sqrt(0.72 / (n + 3.0))
    if conversion == "blinn4":
        return np.sqrt(2.0 / (4.0 * n + 2.0))
    raise ConfigError(f"unknown roughness conversion {conversion!r}",
                      fix=f"use one of {ROUGHNESS_CONVERSIONS}")


def roughness_from_exponent(n: np.ndarray, conversion: str = "fitted") -> np.ndarray:
    """glTF perceptual roughness (``alpha = roughness^2``) of a Lafortune exponent n."""
    return np.sqrt(ggx_alpha_from_exponent(n, conversion))


def ggx_lobe_inplane(alpha: float, incidence: float, view: np.ndarray) -> np.ndarray:
    """GGX specular BRDF with F = 1 and Smith's separable G, light at polar angle ``incidence`` and
    view at signed polar angles ``view`` (radians, > 0 on the mirror side) in the plane of incidence."""
    view = np.asarray(view, dtype=np.float64)
    lx, lz = -math.sin(incidence), math.cos(incidence)
    vx, vz = np.sin(view), np.cos(view)
    hx, hz = lx + vx, lz + vz
    ch2 = hz * hz / (hx * hx + hz * hz)
    a2 = alpha * alpha
    d = a2 / (np.pi * ch2 * ch2 * (a2 + (1.0 - ch2) / ch2) ** 2)

    def g1(c):
        c2 = np.maximum(np.asarray(c, dtype=np.float64) ** 2, 1e-300)
        return 2.0 / (1.0 + np.sqrt(1.0 + a2 * (1.0 - c2) / c2))

    return d * g1(lz) * g1(vz) / (4.0 * lz * np.maximum(vz, 1e-300))


def _trapezoid(y: np.ndarray, x: np.ndarray) -> float:
    return float(np.sum(0.5 * (y[1:] + y[:-1]) * np.diff(x)))


def lobe_conversion_table(exponents=(1, 10, 100, 1000, 10000), conversion: str = "fitted",
                          incidence_deg: float = 0.0, samples: int = 20001) -> list[dict]:
    """How well the GGX lobe of the exported roughness matches the Lafortune lobe (c_z = 1).

    Both lobes are sampled in the plane of incidence for a light at ``incidence_deg`` from the
    normal (view angles -90..90 degrees, ``samples`` points) and normalised to their peaks.

    Returns one dict per exponent: ``n``, ``alpha``, ``roughness``, ``fwhm_lafortune_deg`` and
    ``fwhm_ggx_deg`` (full width at half maximum: the measure of the view angles where the
    peak-normalised lobe is >= 1/2), ``fwhm_error`` (GGX / Lafortune - 1), ``max_shape_diff`` (largest
    difference of the peak-normalised lobes), and for a light along the normal ``ggx_albedo``
    (GGX's directional albedo with F0 = 1; the Lafortune lobe scaled to albedo 1 has 1) and
    ``peak_ratio`` (GGX peak / Lafortune peak when F0 is the lobe albedo, as exported).
    """
    ti = math.radians(incidence_deg)
    phi = np.linspace(-np.pi / 2, np.pi / 2, samples)[1:-1]
    step = math.degrees(float(phi[1] - phi[0]))
    th = np.linspace(0.0, np.pi / 2, samples)[:-1]
    rows = []
    for n in exponents:
        n = float(n)
        alpha = float(ggx_alpha_from_exponent(n, conversion))
        laf = np.maximum(np.cos(phi - ti), 0.0) ** n
        ggx = ggx_lobe_inplane(alpha, ti, phi)
        ggx = ggx / ggx.max()
        fw_l, fw_g = step * float((laf >= 0.5).sum()), step * float((ggx >= 0.5).sum())
        g0 = ggx_lobe_inplane(alpha, 0.0, th)
        albedo = 2.0 * np.pi * _trapezoid(g0 * np.cos(th) * np.sin(th), th)
        rows.append({"n": n, "alpha": alpha, "roughness": math.sqrt(alpha),
                     "fwhm_lafortune_deg": fw_l, "fwhm_ggx_deg": fw_g, "fwhm_error": fw_g / fw_l - 1.0,
                     "max_shape_diff": float(np.abs(ggx - laf).max()), "ggx_albedo": albedo,
                     "peak_ratio": 1.0 / (2.0 * alpha * alpha * (n + 2.0))})
    return rows


def bake_fill_source(model_dir: Path) -> np.ndarray | None:
    """bake.npz's ``fill_source`` (the covered texel each padding texel copies), or None without one."""
    path = Path(model_dir) / "bake.npz"
    if not path.is_file():
        return None
    with np.load(path) as bake:
        return bake["fill_source"] if "fill_source" in bake.files else None


def lafortune_material(grid: np.ndarray, layout, covered: np.ndarray, roughness: str,
                       samples: DirectionSamples | None = None, fill_source: np.ndarray | None = None,
                       device: str = "cpu") -> ExportMaterial:
    """The exported material of a Lafortune parameter grid (H, W, P).

    OBJ (and the fields ``base``, ``specular``, ``roughness``): base colour the clipped albedo; with lobes, F0 the
    summed lobe albedos (normalised by their largest value over ``covered`` texels), the roughness of the
    dominant lobe's exponent (``roughness``: the conversion) and Ns their median; without, no specular layer.
    glTF (``pbr``): the core metallic-roughness material fitted to the model over ``samples`` (None: the flash
    set; gltf_core.py, on Warp ``device``), padding texels taking their ``fill_source``'s, and KHR_materials_specular's F0
    on top."""
    g = grid.astype(np.float64)
    lay = layout
    albedo = albedo_from_rho_d(g[..., 0:3])
    clipped = int((albedo.max(axis=-1)[covered] > 1.0).sum())
    base = np.clip(albedo, 0.0, 1.0)
    samples = samples or flash_samples()
    if lay.n_lobes == 0:
        before = (base, np.zeros_like(base), np.ones(base.shape[:2]))
        return ExportMaterial(base, clipped=clipped, name="diffuse",
                              pbr=fit_core_material(g, lay, samples, fill_source, before, device))
    albedos, exps = [], []
    for j in range(lay.n_lobes):
        o = lay.lobe_offset(j)
        n = np.maximum(g[..., o + lay.lobe_stride - 1], 0.0)
        albedos.append(lobe_albedo(np.maximum(g[..., o:o + 3], 0.0), n))
        exps.append(n)
    f0 = np.clip(np.sum(albedos, axis=0), 0.0, 1.0)
    dom = np.argmax(np.stack([a.mean(axis=-1) for a in albedos]), axis=0)
    n_dom = np.take_along_axis(np.stack(exps), dom[None], axis=0)[0]
    scale = float(f0[covered].max())
    spec = f0 / scale if scale > 0 else np.zeros_like(f0)
    rough = roughness_from_exponent(n_dom, roughness)
    shiny = covered & (f0.max(axis=-1) > 0)
    ns = float(np.median(n_dom[shiny if shiny.any() else covered]))
    pbr = fit_core_material(g, lay, samples, fill_source, (base, np.maximum(f0, 0.0), np.maximum(rough, 0.04)),
                            device)
    return ExportMaterial(base, specular=spec, specular_scale=scale, roughness=rough,
                          ns=float(np.clip(ns, 1.0, MTL_NS_MAX)), clipped=clipped, name="lafortune", pbr=pbr)
