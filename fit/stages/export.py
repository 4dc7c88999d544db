"""Export a fitted model folder to files other tools open: glTF 2.0 binary and OBJ + MTL.

``texstream fit`` writes per-texel Lafortune parameters as float EXR maps (BRDF values in 1/sr,
capture/conventions.py). Viewers and DCC tools read a PBR metallic-roughness glTF or a Phong-style
OBJ/MTL instead, so this module converts (docs/export.md has the same text with the numbers):

base colour
    Diffuse albedo ``pi * rho_d`` (the Lambertian BRDF rho_d in 1/sr reflects ``pi * rho_d``),
    clipped to [0, 1] and stored as an 8-bit sRGB PNG (glTF's baseColorTexture and OBJ's map_Kd are
    sRGB). metallic = 0 (every texstream model is a dielectric-style diffuse + specular mix).

specular colour (KHR_materials_specular, OBJ Ks / map_Ks)
    Lobe j reflects ``a_j = rho_s,j * 2 pi / (n_j + 2)`` of light arriving along the normal (the
    integral of ``rho_s max(s, 0)^n cos`` over the hemisphere with c_z = 1; the same quantity the
    fit's energy bound caps, fit/models.py). ``F0 = min(sum_j a_j, 1)`` per channel is the glTF
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

radiance models (``layout.kind == "radiance"``, grid columns 0:3: view-independent exitant
radiance in photo units; ``"view_radiance"``: its radiance seen along the normal, columns 0:3, since
neither glTF nor OBJ has a view-dependent colour; the view terms stay in the EXR maps)
    ``radiance * radiance_scale`` clipped to [0, 1], 8-bit sRGB, as the baseColor of an unlit
    material (``KHR_materials_unlit``, fallback metallic 0, roughness 0.9 as the extension suggests);
    OBJ: map_Kd with ``illum 0``.

light field mapping models (``layout.kind == "lfm"``, fit/lfm_stage.py: lfm.npz)
    Exported unlit like the radiance models. Base colour per texel: the view-independent term d(s)
    plus, for each of the texel's three vertex light fields and each term k, its surface map value
    times the mean of the vertex's view map over view directions, cosine-weighted over the vertex's
    hemisphere (``lfm_view_mean = "cosine"``: seen from viewpoints all around, a surface element
    covers pixels in proportion to cos(theta_v), so this is the pixel-weighted average colour of the
    element); ``"none"`` keeps d(s) alone. The mean uses the renderer's own view-map lookups
    (``view_taps`` of fit/kernels/lfm.py at a 128 x 128 grid of disk-uniform directions). The exact
    surface and view maps stay in ``maps/*.exr`` (diffuse, surface_k{k}_v{j}, view_k{k}).

Geometry
    Positions, unit vertex normals, UVs. texstream UVs have v up (capture/conventions.py), glTF's
    origin is the top-left of the image: TEXCOORD_0 = (u, 1 - v); OBJ keeps v up. Texture images
    are written as stored (row 0 = top). The glTF scene turns the model's up axis to glTF's +y with
    a node rotation (``up_axis="z"``: -90 degrees about x; the vertex data stay in texstream's
    world frame, readers apply the node); OBJ has no node, so its vertices are rotated. The float
    EXR maps are copied into ``maps/`` beside the export.

Like the rest of ``texstream.fit`` this module imports only numpy (and texstream.core) at module
level; pygltflib and OpenImageIO (through capture.imageio) are imported inside the functions.
"""

from __future__ import annotations

import dataclasses
import math
import tempfile
from pathlib import Path

import numpy as np

from texstream.core.config import option, save_config
from texstream.core.errors import ConfigError, InputError
from texstream.core.outputs import StageResult, atomic_output_dir, read_json, write_json_atomic

FORMATS = ("glb", "obj")
ROUGHNESS_CONVERSIONS = ("fitted", "blinn4")
UP_AXES = ("z", "y")
LFM_VIEW_MEANS = ("cosine", "none")
VIEW_MEAN_GRID = 128
"""disk-uniform directions per side of the grid the LFM view-map means average over (12,868 in the disk)"""
DIELECTRIC_F0 = 0.04  # ((ior - 1) / (ior + 1))^2 at glTF's default ior 1.5
MTL_NS_MAX = 1000.0
_MODEL_FIX = "give the folder `texstream fit` wrote (model.json, mesh.obj, bake.npz and the EXR maps)"

# glTF enums
_FLOAT, _UINT = 5126, 5125
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963
_LINEAR, _LINEAR_MIPMAP_LINEAR, _CLAMP = 9729, 9987, 33071


@dataclasses.dataclass
class ExportConfig:
    """Options of the export stage (``texstream export``)."""

    formats: tuple[str, ...] = option(("glb", "obj"), "files to write: glb (glTF 2.0 binary, PBR metallic-"
                                      "roughness + KHR_materials_specular) and/or obj (OBJ + MTL + PNG)")
    name: str = option("model", "file stem: NAME.glb, NAME.obj, NAME.mtl, NAME_*.png")
    up_axis: str = option("z", "the model's world up axis, turned to +y (glTF's up; OBJ importers assume "
                          "it too): z for texstream's synthetic scenes, y to keep the coordinates",
                          choices=UP_AXES)
    roughness: str = option("fitted", "Lafortune exponent n -> GGX alpha: fitted sqrt(0.72/(n+3)) or "
                            "blinn4 sqrt(2/(4n+2)) (docs/export.md)", choices=ROUGHNESS_CONVERSIONS)
    radiance_scale: float = option(1.0, "radiance models: multiply the radiance by this before clipping "
                                   "to [0, 1] (1 = photo units, where 1 is the photo's white)")
    copy_maps: bool = option(True, "copy the float EXR parameter maps into maps/ (the exact fitted values)")
    lfm_view_mean: str = option("cosine", "light field mapping models: unlit base colour = the view-"
                                "independent term plus each view-dependent term's mean over view "
                                "directions, cosine-weighted over the hemisphere (cosine), or the "
                                "view-independent term alone (none)", choices=("cosine", "none"))


# ---------------------------------------------------------------------------------------------
# conversions (numpy only)


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


# ---------------------------------------------------------------------------------------------
# light field mapping: the unlit approximation


def cosine_directions(n: int = VIEW_MEAN_GRID) -> np.ndarray:
    """(D, 3) unit local directions (z = the normal) cosine-distributed over the hemisphere: the
    centres of an n x n grid on [-1, 1]^2 inside the unit disk, lifted to z = sqrt(1 - x^2 - y^2)
    (equal disk areas are equal projected solid angles, Nusselt's analog)."""
    c = (np.arange(n) + 0.5) / n * 2.0 - 1.0
    x, y = (a.reshape(-1) for a in np.meshgrid(c, c))
    r2 = x * x + y * y
    keep = r2 < 1.0
    return np.stack([x[keep], y[keep], np.sqrt(1.0 - r2[keep])], 1)


def view_mean_weights(res: int, mapping: str, lookup: str, device: str | None = None,
                      n: int = VIEW_MEAN_GRID) -> np.ndarray:
    """(R * R,) weights w (summing to 1) such that ``sum_q w[q] h[q]`` is the cosine-weighted mean over
    view directions of a view map h looked up as the renderer does (mapping "disk" | "hemioct",
    lookup "nearest" | "bilinear"): the average of ``view_taps`` over :func:`cosine_directions`, on
    ``device`` (None: the CPU where Warp can compile for it, else Warp's preferred device)."""
    import warp as wp

    from texstream.fit.kernels import lfm as LK
    from texstream.fit.kernels.lfm_lookup import direction_taps_kernel

    if device is None:
        device = "cpu" if wp.is_cpu_available() else str(wp.get_preferred_device())
    dirs = cosine_directions(n)
    d = wp.array(dirs, dtype=wp.vec3d, device=device)
    idx = wp.zeros(len(dirs), dtype=wp.vec4i, device=device)
    wt = wp.zeros(len(dirs), dtype=wp.vec4d, device=device)
    code_map = int(LK.MAP_DISK if mapping == "disk" else LK.MAP_HEMIOCT)
    code_lookup = int(LK.LOOKUP_NEAREST if lookup == "nearest" else LK.LOOKUP_BILINEAR)
    wp.launch(direction_taps_kernel, dim=len(dirs), device=device,
              inputs=[d, code_map, int(res), code_lookup], outputs=[idx, wt])
    out = np.zeros(res * res)
    np.add.at(out, idx.numpy().reshape(-1), wt.numpy().reshape(-1))
    return out / out.sum()


def lfm_unlit_radiance(model, view_mean: str = "cosine", device: str | None = None) -> np.ndarray:
    """(N, 3) the unlit radiance of each compact texel of an LFM model (fit/lfm_stage.py
    ``LFMModelFolder``): d(s) plus, with ``view_mean = "cosine"``, sum over the texel's slots j and terms
    k of g_k(slot) times the cosine-weighted mean of h_k over the slot vertex's view directions."""
    p = model.params
    d = np.asarray(p.diffuse, np.float64)
    if view_mean == "none":
        return d.copy()
    if view_mean != "cosine":
        raise ConfigError(f"unknown lfm_view_mean {view_mean!r}", fix=f"use one of {LFM_VIEW_MEANS}")
    w = view_mean_weights(model.view_res, model.cfg.view_map, model.cfg.lookup, device)
    h_mean = np.einsum("vkmc,m->vkc", np.asarray(p.H, np.float64), w)     # (V, K, 3)
    terms = (np.asarray(p.G, np.float64) * h_mean[model.geom.slot_vertex]).sum(axis=1)   # (3N, 3)
    return d + terms.reshape(-1, 3, 3).sum(axis=1)


def lfm_atlas(model, values: np.ndarray) -> np.ndarray:
    """(H, W, C) float32 atlas of per-compact-texel ``values`` (N, C): each texel holds its own value or,
    for padding, the value of the texel it copies (what the LFM renderer reads); 0 elsewhere."""
    from texstream.fit.stages.lfm_stage import grid_source

    b = model.bake
    src = grid_source(b, model.grid_index)
    v = np.asarray(values)
    out = np.zeros((b.height * b.width, v.shape[1]), np.float32)
    out[src >= 0] = v[src[src >= 0]]
    return out.reshape(b.height, b.width, v.shape[1])


def lfm_unlit_renderer(model, view_mean: str = "cosine", device: str = "cpu"):
    """frame -> (image, coverage): the exported unlit approximation of an LFM model rendered by
    texstream's radiance renderer (fit/render.py, bilinear atlas lookup, times the frame's exposure),
    to score it against the full model or the photos."""
    from texstream.fit.kernels.layout import ModelLayout
    from texstream.fit.stages.stage import render_model

    grid = lfm_atlas(model, lfm_unlit_radiance(model, view_mean, device))
    layout = ModelLayout(kind="radiance")
    mesh = model.mesh

    def render(frame):
        return render_model(mesh, grid, layout, frame, device)
    return render


# ---------------------------------------------------------------------------------------------
# reading the model folder


@dataclasses.dataclass
class _Model:
    folder: Path
    mesh: object  # SurfaceMesh with normals and UVs
    grid: np.ndarray  # (H, W, P)
    layout: object  # ModelLayout (or anything with kind / n_lobes / lobe_offset / lobe_stride)
    manifest: dict
    covered: np.ndarray  # (H, W) bool: texels on the surface (all True without a usable bake.npz)


def _read_model(model_dir, cfg: ExportConfig | None = None) -> _Model:
    """Load and check a model folder; every problem is an InputError naming the file and the fix.
    An LFM folder's grid is its unlit radiance (:func:`lfm_unlit_radiance`, ``cfg.lfm_view_mean``)."""
    from texstream.fit.stages import stage

    d = Path(model_dir)
    if not d.is_dir():
        raise InputError("model folder not found" if not d.exists() else "not a folder", d, _MODEL_FIX)
    if not (d / "model.json").is_file():
        raise InputError("not a model folder (no model.json)", d / "model.json", _MODEL_FIX)
    man = read_json(d / "model.json", what="model manifest")
    if not isinstance(man, dict) or not isinstance(man.get("layout"), dict) or "kind" not in man["layout"]:
        raise InputError("model.json has no layout (kind, n_lobes, ...)", d / "model.json",
                         "re-run `texstream fit`, which writes the layout")
    if man["layout"]["kind"] == "lfm":
        return _read_lfm_model(d, cfg or ExportConfig())
    try:
        mesh, grid, layout, man = stage.load_model(d)
    except InputError as e:
        if e.path and e.path.lower().endswith(".exr"):  # read_image's fix speaks of capture.json
            raise InputError(f"parameter map: {e.message}", e.path, "restore the map, or re-run "
                             "`texstream fit` to rewrite the model folder") from None
        raise
    except ConfigError as e:
        raise InputError(f"model.json describes a model this texstream cannot read ({e.message})",
                         d / "model.json", "re-run `texstream fit`, or update texstream") from None
    except (KeyError, TypeError, ValueError) as e:
        raise InputError(f"model.json or the parameter maps are inconsistent ({type(e).__name__}: {e})",
                         d / "model.json", "re-run `texstream fit` to rewrite the model folder") from None
    if mesh.uvs is None:
        raise InputError("mesh has no texture coordinates", d / "mesh.obj",
                         "export the mesh.obj the fit wrote (it carries the atlas UVs)")
    need = 3 if layout.kind == "radiance" else layout.n_params
    if grid.ndim != 3 or grid.shape[2] < need:
        raise InputError(f"parameter maps hold {grid.shape[-1]} channels, the {layout.kind} layout "
                         f"needs {need}", d, "re-run `texstream fit` to rewrite the maps")
    covered = np.ones(grid.shape[:2], bool)
    if (d / "bake.npz").is_file():
        try:
            with np.load(d / "bake.npz") as z:
                if "covered" in z.files and z["covered"].shape == grid.shape[:2]:
                    covered = z["covered"].astype(bool)
        except (OSError, ValueError):
            pass  # the bake only narrows the statistics (Ns, specular scale); all texels will do
    if not covered.any():
        covered[:] = True
    return _Model(d, mesh, grid, layout, man, covered)


@dataclasses.dataclass
class _LFMLayout:
    """What the export reads of an LFM model's layout (it has no per-texel parameter table)."""

    kind: str = "lfm"
    n_lobes: int = 0
    view_mean: str = "cosine"


def _read_lfm_model(d: Path, cfg: ExportConfig) -> _Model:
    from texstream.fit.stages.lfm_stage import load_lfm_model

    try:
        model = load_lfm_model(d)
    except (KeyError, TypeError, ValueError) as e:
        why = f"model.json or lfm.npz are inconsistent ({type(e).__name__}: {e})"
        raise InputError(why, d / "model.json",
                         "re-run `texstream fit --model lfm` to rewrite the folder") from None
    if model.mesh.uvs is None:
        raise InputError("mesh has no texture coordinates", d / "mesh.obj",
                         "export the mesh.obj the fit wrote (it carries the atlas UVs)")
    grid = lfm_atlas(model, lfm_unlit_radiance(model, cfg.lfm_view_mean))
    covered = np.asarray(model.bake.covered, bool)
    return _Model(d, model.mesh, grid, _LFMLayout(view_mean=cfg.lfm_view_mean), model.manifest,
                  covered if covered.any() else np.ones(grid.shape[:2], bool))


def _map_files(m: _Model) -> list[Path]:
    names = m.manifest.get("maps")
    files = [m.folder / str(v) for v in names.values()] if isinstance(names, dict) else []
    files = [f for f in files if f.is_file()]
    return files or sorted(m.folder.glob("*.exr"))


# ---------------------------------------------------------------------------------------------
# the material as images


@dataclasses.dataclass
class _Material:
    kind: str  # "radiance", "diffuse" or "lafortune"
    base: np.ndarray  # (H, W, 3) linear in [0, 1]: albedo, or clipped radiance
    specular: np.ndarray | None  # (H, W, 3) F0 / specular_scale in [0, 1]
    specular_scale: float  # largest F0 over covered texels (0: no specular layer)
    roughness: np.ndarray | None  # (H, W) glTF roughness in [0, 1]
    ns: float  # OBJ exponent
    clipped: int  # covered texels whose base colour was clipped at 1


def _material(m: _Model, cfg: ExportConfig) -> _Material:
    g = m.grid.astype(np.float64)
    lay = m.layout
    if lay.kind in ("radiance", "view_radiance", "lfm"):
        # glTF and OBJ have no view-dependent colour: the radiance seen along the normal (view_radiance),
        # or the view-independent term plus the view terms' mean over directions (lfm, _read_lfm_model)
        rad = g[..., 0:3] * float(cfg.radiance_scale)
        clipped = int((rad.max(axis=-1)[m.covered] > 1.0).sum())
        return _Material("radiance", np.clip(rad, 0.0, 1.0), None, 0.0, None, 1.0, clipped)
    albedo = albedo_from_rho_d(g[..., 0:3])
    clipped = int((albedo.max(axis=-1)[m.covered] > 1.0).sum())
    base = np.clip(albedo, 0.0, 1.0)
    if lay.n_lobes == 0:
        return _Material("diffuse", base, None, 0.0, None, 1.0, clipped)
    albedos, exps = [], []
    for j in range(lay.n_lobes):
        o = lay.lobe_offset(j)
        n = np.maximum(g[..., o + lay.lobe_stride - 1], 0.0)
        albedos.append(lobe_albedo(np.maximum(g[..., o:o + 3], 0.0), n))
        exps.append(n)
    f0 = np.clip(np.sum(albedos, axis=0), 0.0, 1.0)
    dom = np.argmax(np.stack([a.mean(axis=-1) for a in albedos]), axis=0)
    n_dom = np.take_along_axis(np.stack(exps), dom[None], axis=0)[0]
    scale = float(f0[m.covered].max())
    spec = f0 / scale if scale > 0 else np.zeros_like(f0)
    rough = roughness_from_exponent(n_dom, cfg.roughness)
    shiny = m.covered & (f0.max(axis=-1) > 0)
    ns = float(np.median(n_dom[shiny if shiny.any() else m.covered]))
    return _Material("lafortune", base, spec, scale, rough, float(np.clip(ns, 1.0, MTL_NS_MAX)), clipped)


def _png_bytes(img: np.ndarray) -> bytes:
    """8-bit PNG of a linear image (sRGB-encoded by capture.imageio) or of uint8 codes (stored as is)."""
    from texstream.capture.imageio import write_image

    with tempfile.TemporaryDirectory(prefix="texstream_export_") as t:
        p = write_image(Path(t) / "tex.png", img, bits=8)
        return p.read_bytes()


def _roughness_codes(rough: np.ndarray) -> np.ndarray:
    """glTF metallicRoughnessTexture (linear, not sRGB): R unused (255), G roughness, B metalness 0."""
    out = np.zeros((*rough.shape, 3), np.uint8)
    out[..., 0] = 255
    out[..., 1] = np.floor(np.clip(rough, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    return out


def _up_rotation(up_axis: str) -> np.ndarray:
    if up_axis == "z":
        return np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # (x, y, z) -> (x, z, -y)
    if up_axis == "y":
        return np.eye(3)
    raise ConfigError(f"unknown up axis {up_axis!r}", fix=f"use one of {UP_AXES}")


def _unit_normals(mesh) -> np.ndarray:
    n = np.asarray(mesh.vertex_normals(), dtype=np.float64)
    ln = np.linalg.norm(n, axis=1, keepdims=True)
    return np.divide(n, ln, out=np.tile([0.0, 0.0, 1.0], (len(n), 1)), where=ln > 0)


def _copy_maps(m: _Model, folder: Path) -> list[str]:
    from texstream.core.outputs import write_atomic_with

    out = []
    for f in _map_files(m):
        data = f.read_bytes()
        write_atomic_with(folder / f.name, lambda fh, data=data: fh.write(data))
        out.append(f"maps/{f.name}")
    return out


def _info(m: _Model, mat: _Material, cfg: ExportConfig) -> dict:
    h, w = m.grid.shape[:2]
    info = {"kind": mat.kind, "vertices": m.mesh.n_vertices, "faces": m.mesh.n_faces, "texture": [w, h],
            "up_axis": cfg.up_axis, "base_colour_clipped_texels": mat.clipped}
    if mat.kind == "lafortune":
        info.update({"specular_scale": mat.specular_scale,
                     "specular_color_factor": mat.specular_scale / DIELECTRIC_F0,
                     "roughness_conversion": cfg.roughness, "mtl_ns": mat.ns})
    if mat.kind == "radiance":
        info["radiance_scale"] = cfg.radiance_scale
    info["model_kind"] = m.layout.kind
    if m.layout.kind == "lfm":
        info["lfm_view_mean"] = cfg.lfm_view_mean
    return info


def _check_config(cfg: ExportConfig) -> None:
    bad = [f for f in cfg.formats if f not in FORMATS]
    if bad or not cfg.formats:
        raise ConfigError(f"unknown export format(s) {bad or '(none)'}", fix=f"use some of {FORMATS}")
    _up_rotation(cfg.up_axis)
    ggx_alpha_from_exponent(1.0, cfg.roughness)
    if not (math.isfinite(cfg.radiance_scale) and cfg.radiance_scale > 0):
        raise ConfigError(f"radiance_scale must be > 0, got {cfg.radiance_scale}",
                          fix="pass a positive scale")
    if cfg.lfm_view_mean not in LFM_VIEW_MEANS:
        raise ConfigError(f"unknown lfm_view_mean {cfg.lfm_view_mean!r}", fix=f"use one of {LFM_VIEW_MEANS}")
    if not cfg.name or "/" in cfg.name or cfg.name.startswith("."):
        raise ConfigError(f"bad file stem {cfg.name!r}", fix="pass a plain file name without folders")


# ---------------------------------------------------------------------------------------------
# glTF 2.0 binary


def export_gltf(model_dir, out_path, config: ExportConfig | None = None) -> dict:
    """Write a model folder as one glTF 2.0 binary (``.glb``) with embedded PNG textures.

    Lafortune / diffuse models get a PBR metallic-roughness material (base colour = albedo, metallic
    0, roughness from the lobe exponent) with ``KHR_materials_specular`` (the lobe albedo as F0);
    radiance models an unlit base colour (``KHR_materials_unlit``). The module doc gives the
    conversions. With ``config.copy_maps`` the EXR maps are copied into ``maps/`` beside the file.

    Args:
        model_dir: a model folder (``texstream fit`` output).
        out_path: the ``.glb`` to write (atomically; its folder is created).
        config: export options (defaults: ExportConfig()).

    Returns:
        A summary dict (vertices, faces, texture size, conversion factors).

    Raises:
        InputError: missing or invalid model folder (naming the file and the fix).
        ConfigError: bad options.
    """
    cfg = config or ExportConfig()
    _check_config(cfg)
    return _export_gltf(_read_model(model_dir, cfg), cfg, Path(out_path))


def _export_gltf(m: _Model, cfg: ExportConfig, out: Path) -> dict:
    mat = _material(m, cfg)
    _write_glb(m, mat, cfg, out)
    info = _info(m, mat, cfg)
    info["path"] = str(out)
    if cfg.copy_maps:
        info["maps"] = _copy_maps(m, out.parent / "maps")
    return info


def _write_glb(m: _Model, mat: _Material, cfg: ExportConfig, out: Path) -> None:
    import pygltflib as G

    from texstream.core.outputs import write_atomic_with

    mesh = m.mesh
    pos = np.ascontiguousarray(mesh.vertices, dtype="<f4")
    nrm = np.ascontiguousarray(_unit_normals(mesh), dtype="<f4")
    uv = np.asarray(mesh.uvs, dtype=np.float64)
    tex = np.ascontiguousarray(np.stack([uv[:, 0], 1.0 - uv[:, 1]], axis=1), dtype="<f4")  # v up -> glTF
    idx = np.ascontiguousarray(mesh.faces, dtype="<u4").reshape(-1)

    blob = bytearray()
    views: list = []

    def view(data: bytes, target: int | None = None) -> int:
        blob.extend(b"\0" * (-len(blob) % 4))
        views.append(G.BufferView(buffer=0, byteOffset=len(blob), byteLength=len(data), target=target))
        blob.extend(data)
        return len(views) - 1

    accessors = [
        G.Accessor(bufferView=view(pos.tobytes(), _ARRAY_BUFFER), componentType=_FLOAT, count=len(pos),
                   type="VEC3", min=pos.min(axis=0).tolist(), max=pos.max(axis=0).tolist()),
        G.Accessor(bufferView=view(nrm.tobytes(), _ARRAY_BUFFER), componentType=_FLOAT, count=len(nrm),
                   type="VEC3"),
        G.Accessor(bufferView=view(tex.tobytes(), _ARRAY_BUFFER), componentType=_FLOAT, count=len(tex),
                   type="VEC2"),
        G.Accessor(bufferView=view(idx.tobytes(), _ELEMENT_ARRAY_BUFFER), componentType=_UINT,
                   count=int(idx.size), type="SCALAR", min=[int(idx.min())], max=[int(idx.max())]),
    ]
    images, textures = [], []

    def texture(name: str, img: np.ndarray) -> int:
        images.append(G.Image(bufferView=view(_png_bytes(img)), mimeType="image/png", name=name))
        textures.append(G.Texture(sampler=0, source=len(images) - 1, name=name))
        return len(textures) - 1

    units = "base colour = albedo (pi * rho_d) or clipped radiance; see docs/export.md"
    extras = {"texstream": {"kind": mat.kind, "model_kind": m.layout.kind, "units": units}}
    if m.layout.kind == "lfm":  # the unlit approximation of a light field (module doc)
        extras["texstream"]["lfm_view_mean"] = cfg.lfm_view_mean
    pbr = G.PbrMetallicRoughness(baseColorFactor=[1.0, 1.0, 1.0, 1.0],
                                 baseColorTexture=G.TextureInfo(index=texture("base_color", mat.base)),
                                 metallicFactor=0.0)
    if mat.kind == "radiance":
        pbr.roughnessFactor = 0.9
        extensions = {"KHR_materials_unlit": {}}
        extras["texstream"]["radiance_scale"] = cfg.radiance_scale
    elif mat.kind == "diffuse":
        pbr.roughnessFactor = 1.0
        extensions = {"KHR_materials_specular": {"specularFactor": 0.0}}  # no specular layer: Lambertian
    else:
        pbr.roughnessFactor = 1.0
        pbr.metallicRoughnessTexture = G.TextureInfo(index=texture("metallic_roughness",
                                                                    _roughness_codes(mat.roughness)))
        spec = {"specularFactor": 1.0, "specularColorFactor": [mat.specular_scale / DIELECTRIC_F0] * 3}
        if mat.specular_scale > 0:
            spec["specularColorTexture"] = {"index": texture("specular_color", mat.specular)}
        extensions = {"KHR_materials_specular": spec}
        extras["texstream"].update({"roughness_conversion": cfg.roughness,
                                    "specular_scale": mat.specular_scale})
    material = G.Material(name=f"texstream_{mat.kind}", pbrMetallicRoughness=pbr, extensions=extensions,
                          extras=extras, doubleSided=False)
    up = _up_rotation(cfg.up_axis)
    node = G.Node(mesh=0, name=cfg.name)
    if not np.allclose(up, np.eye(3)):
        node.rotation = [-math.sqrt(0.5), 0.0, 0.0, math.sqrt(0.5)]  # -90 deg about x: +z up -> +y up
    prim = G.Primitive(attributes=G.Attributes(POSITION=0, NORMAL=1, TEXCOORD_0=2), indices=3, material=0,
                       mode=4)
    gltf = G.GLTF2(asset=G.Asset(version="2.0", generator="texstream export"), scene=0,
                   scenes=[G.Scene(nodes=[0])], nodes=[node],
                   meshes=[G.Mesh(name=cfg.name, primitives=[prim])],
                   accessors=accessors, bufferViews=views, buffers=[G.Buffer(byteLength=len(blob))],
                   images=images, textures=textures,
                   samplers=[G.Sampler(magFilter=_LINEAR, minFilter=_LINEAR_MIPMAP_LINEAR, wrapS=_CLAMP,
                                       wrapT=_CLAMP)],
                   materials=[material], extensionsUsed=sorted(extensions))
    gltf.set_binary_blob(bytes(blob))
    data = b"".join(gltf.save_to_bytes())
    write_atomic_with(out, lambda fh: fh.write(data))


# ---------------------------------------------------------------------------------------------
# OBJ + MTL


def export_obj(model_dir, out_dir, config: ExportConfig | None = None) -> dict:
    """Write a model folder as ``NAME.obj`` + ``NAME.mtl`` + PNG textures into ``out_dir``.

    MTL: ``map_Kd`` = base colour (albedo, sRGB PNG), ``Ks`` / ``map_Ks`` = the lobe albedo (F0, as
    in the glTF: ``Ks`` is its largest value, the texture the normalised map), ``Ns`` = the median
    exponent, ``illum 2``; diffuse models ``Ks 0`` and ``illum 1``; radiance models ``map_Kd`` =
    radiance and ``illum 0``. Vertices and normals are turned so the model's up axis is +y. With
    ``config.copy_maps`` the EXR maps are copied into ``out_dir/maps/``. Every file is written
    atomically (a temporary file, then a rename).

    Returns:
        A summary dict. Raises InputError / ConfigError as :func:`export_gltf`.
    """
    cfg = config or ExportConfig()
    _check_config(cfg)
    return _export_obj(_read_model(model_dir, cfg), cfg, Path(out_dir))


def _export_obj(m: _Model, cfg: ExportConfig, out: Path) -> dict:
    from texstream.capture.imageio import write_image
    from texstream.core.outputs import write_atomic_with

    mat = _material(m, cfg)
    if out.exists() and not out.is_dir():
        raise InputError("output path exists and is not a folder", out, "choose another output folder")
    out.mkdir(parents=True, exist_ok=True)
    stem = cfg.name
    kd = f"{stem}_{'radiance' if mat.kind == 'radiance' else 'basecolor'}.png"
    write_image(out / kd, mat.base, bits=8)
    lines = [f"# texstream export: {mat.kind} model (conversions: docs/export.md)", "newmtl texstream",
             "Ka 0 0 0", "Kd 1 1 1", f"map_Kd {kd}"]
    if mat.kind == "lafortune":
        ks = f"{stem}_specular.png"
        write_image(out / ks, mat.specular, bits=8)
        s = mat.specular_scale
        lines += [f"Ks {s:.6g} {s:.6g} {s:.6g}", f"map_Ks {ks}", f"Ns {mat.ns:.6g}", "illum 2"]
    elif mat.kind == "diffuse":
        lines += ["Ks 0 0 0", "illum 1"]
    else:
        lines += ["Ks 0 0 0", "illum 0"]
    lines += ["d 1", ""]
    mtl = "\n".join(lines).encode()
    write_atomic_with(out / f"{stem}.mtl", lambda fh: fh.write(mtl))

    up = _up_rotation(cfg.up_axis)
    v = np.asarray(m.mesh.vertices, dtype=np.float64) @ up.T
    n = _unit_normals(m.mesh) @ up.T
    f = np.asarray(m.mesh.faces, dtype=np.int64) + 1
    header = (f"# texstream export: {m.mesh.n_vertices} vertices, {m.mesh.n_faces} faces, "
              f"up {cfg.up_axis} -> +y\n")
    parts = [header, f"mtllib {stem}.mtl\n", f"o {stem}\n",
             _rows(v, "v", "%.9g"), _rows(np.asarray(m.mesh.uvs, np.float64), "vt", "%.9g"),
             _rows(n, "vn", "%.7g"), "usemtl texstream\n", _rows(np.repeat(f, 3, axis=1), "f", "%d/%d/%d")]
    obj = "".join(parts).encode()
    write_atomic_with(out / f"{stem}.obj", lambda fh: fh.write(obj))
    info = _info(m, mat, cfg)
    info["path"] = str(out / f"{stem}.obj")
    if cfg.copy_maps:
        info["maps"] = _copy_maps(m, out / "maps")
    return info


def _rows(a: np.ndarray, prefix: str, fmt: str) -> str:
    if len(a) == 0:
        return ""
    row = prefix + " " + " ".join([fmt] * (a.shape[1] // fmt.count("%"))) + "\n"
    return (row * len(a)) % tuple(a.reshape(-1).tolist())


# ---------------------------------------------------------------------------------------------
# the stage


def export_stage(model_dir, out_dir, config: ExportConfig | None = None) -> StageResult:
    """Export a model folder to ``out_dir`` (written atomically: complete, or untouched on error).

    ``out_dir`` gets ``NAME.glb`` and/or ``NAME.obj`` + ``NAME.mtl`` + ``NAME_*.png``, ``maps/`` (the
    EXR maps), ``export.json`` (what was written and the conversion factors) and
    ``export_config.json`` (the resolved options).
    """
    from texstream.core.progress import phase

    cfg = config or ExportConfig()
    _check_config(cfg)
    m = _read_model(model_dir, cfg)  # fail before touching out_dir
    one = dataclasses.replace(cfg, copy_maps=False)
    with atomic_output_dir(out_dir) as tmp:
        written: dict = {}
        if "glb" in cfg.formats:
            with phase("export", f"glTF binary {cfg.name}.glb"):
                written["glb"] = _export_gltf(m, one, tmp / f"{cfg.name}.glb")
        if "obj" in cfg.formats:
            with phase("export", f"OBJ + MTL + PNG textures {cfg.name}.obj"):
                written["obj"] = _export_obj(m, one, tmp)
        maps = _copy_maps(m, tmp / "maps") if cfg.copy_maps else []
        for w in written.values():
            w["path"] = Path(w["path"]).name
        summary = {**next(iter(written.values())), "files": {k: w["path"] for k, w in written.items()},
                   "maps": maps, "model": str(m.folder.resolve())}
        summary.pop("path", None)
        write_json_atomic(tmp / "export.json", summary)
        save_config(cfg, tmp / "export_config.json")
    return StageResult(Path(out_dir), summary)
