"""UV atlas for fitting: xatlas charts, packed to a texel budget, in texstream's UV convention.

:func:`build_atlas` returns the mesh split along chart seams with per-vertex UVs (``source_vertex``
maps each split vertex back to the input vertex) and an :class:`AtlasInfo`.

How it works
    1. Charting (xatlas ``add_mesh`` + ``generate``): xatlas segments the surface into charts and
       flattens each one. Its packing in this pass is thrown away; only the charts and their
       flattening (rescaled to scene units) are kept. xatlas ignores faces whose area is below
       float32 epsilon in absolute units (small faces of an object measured in metres), so it
       charts a copy scaled to a bounding-box diagonal of 100; faces it still ignores get a chart
       of their own.
    2. Per-face importance (``face_weights``, optional; :func:`_density_charts`): xatlas has no
       per-face density, so charts are scaled before packing. A face asks for the linear scale
       sqrt(w / stretch), stretch being its flattened-to-surface area ratio (xatlas' charts are
       near-conformal, not area-preserving), and at least ``min_face_texels`` texels. With
       ``density_bands`` > 0 (default 0.5 octave) charts are split into connected pieces whose
       (smoothed) log2 asks fall in one band, pieces under ``min_piece_texels`` merge into a
       neighbour less than a band away, and each piece is scaled by the area-weighted geometric
       mean of its faces' asks. After packing, charts that xatlas' packer enlarged (it snaps
       charts to whole texels, at least about one) are shrunk by the ratio and packed again.
       Figures (texel size in the photos, p90/p10; tests/test_geometry_density.py): icosphere
       with cameras crowding one side 7.9 uniform, 1.5 banded; ornament capture 1.13 uniform,
       1.07 banded (one camera distance: little to gain), with close-up cameras added 2.9
       uniform, 1.09 banded.
    3. Packing (xatlas ``add_uv_mesh`` + ``generate``, one UV island per chart, in texel units:
       xatlas welds UV vertices closer than ~1e-4): with ``texels_per_unit`` given, the charts
       are packed at that density (an error if the atlas would exceed ``resolution``); otherwise
       the density is searched so that the larger atlas side comes as close to ``resolution`` as
       possible without exceeding it. Repacking is cheap (tens of ms), charting is not, which is
       why the two passes are separate.
    4. Every face gets a texel: faces owning no texel centre after the bake's orphan rule
       (slivers, pole fans, faces crowded into one texel) are laid flat in a chart of their own
       of at least 2 texels and the atlas is packed again (a few rounds, at one density a little
       under the first). ``faces_without_texels`` counts any left (only when the atlas is far too
       small for the face count).

UV convention
    xatlas returns UVs normalised by the atlas size with v pointing down the image (row y of its
    chart image is v * height). texstream's UVs have v up (capture/conventions.py), so
    v = 1 - v_xatlas; texel centres then sit at u = (x + 0.5) / W, v = 1 - (y + 0.5) / H, exactly
    where xatlas rasterised the charts (tests/test_geometry_atlas.py checks against xatlas' image).

A mesh that already has usable UVs (inside [0, 1], not degenerate, not overlapping) keeps them when
``keep_existing_uvs`` is set: the design's "a mesh with good UVs: no atlas".
"""

from __future__ import annotations

import dataclasses
import math
import time

import numpy as np

from texstream.capture.capture_json import read_capture
from texstream.capture.imageio import write_image
from texstream.core.errors import ConfigError, InputError
from texstream.core.config import config_to_dict, option, save_config
from texstream.core.outputs import StageResult, atomic_output_dir, read_json, write_json_atomic
from texstream.core.progress import phase

from .atlas_density import _density_charts, _scale_charts, _uv_areas
from texstream.render.mesh import SurfaceMesh
from .bake import _claim_orphans, _texel_vertex_coords, bake_texels, claim_texels
from .density import density_face_weights, pixel_footprints, texel_size_spread
from .mesh_io import load_mesh, save_mesh, validate_mesh
from .seams import SEAMS_FILE, find_seams
from .visibility import depth_maps


@dataclasses.dataclass
class AtlasConfig:
    """How the texture atlas is made (xatlas charting and packing)."""

    resolution: int = option(1024, help="largest atlas side in texels; with texels_per_unit 0 the "
                                        "density is chosen to fill this size", min=8, max=16384)
    texels_per_unit: float = option(0.0, help="texel density in texels per scene unit (at face weight 1); "
                                              "0 derives it from resolution", min=0.0)
    min_texel_pixels: float = option(1.0, help="with photos given (texstream run: its posed capture; texstream atlas "
                                               "--capture): when texels at resolution would be narrower than this "
                                               "many pixels in the tenth of the photos that see the mesh largest, "
                                               "the charts are packed at the density of texels this wide instead: "
                                               "a smaller atlas, no detail that a photo shows lost, fewer texels to "
                                               "fit (the Middlebury temple's 640x480 photos: 0.81 px texels at "
                                               "1024; 0: off)", min=0.0)
    padding: int = option(2, help="empty texels between charts (also the padding fill radius of the bake)",
                          min=0, max=64)
    bilinear: bool = option(True, help="reserve a one-texel border around charts so bilinear lookups "
                                       "inside a chart never read another chart")
    max_chart_area: float = option(0.0, help="largest chart surface area in scene units^2 (0: no limit); "
                                             "smaller charts let face weights vary more finely", min=0.0)
    max_boundary_length: float = option(0.0, help="largest chart boundary length in scene units "
                                                  "(0: no limit)", min=0.0)
    max_cost: float = option(2.0, help="xatlas chart growth cost threshold: lower gives more, flatter charts "
                                       "with less stretch", min=0.0)
    max_iterations: int = option(1, help="xatlas chart growing iterations (more: better charts, slower)",
                                 min=1, max=100)
    normal_deviation_weight: float = option(2.0, help="xatlas cost weight of normal deviation from "
                                                      "the chart's average normal", min=0.0)
    roundness_weight: float = option(0.01, help="xatlas cost weight favouring round charts", min=0.0)
    straightness_weight: float = option(6.0, help="xatlas cost weight favouring straight chart boundaries",
                                        min=0.0)
    normal_seam_weight: float = option(4.0, help="xatlas cost weight keeping hard normal edges on chart "
                                                 "boundaries", min=0.0)
    texture_seam_weight: float = option(0.5, help="xatlas cost weight keeping existing UV seams on chart "
                                                  "boundaries", min=0.0)
    rotate_charts: bool = option(True, help="let the packer rotate charts for a tighter fit")
    brute_force: bool = option(False, help="slower, tighter packing (xatlas bruteForce)")
    block_align: bool = option(False, help="align charts to 4x4 texel blocks (for block-compressed textures)")
    density_bands: float = option(0.5, help="with face weights: split charts where the weight changes by more "
                                             "than this many octaves (0: one weight per xatlas chart)",
                                             min=0.0, max=16.0)
    density_smoothing: int = option(1, help="with density bands: smoothing steps of the log face weights over "
                                            "neighbouring faces before banding (noisy weights shatter charts)",
                                            min=0, max=100)
    min_face_texels: float = option(1.0, help="with face weights: raise the weight of faces that would get fewer "
                                              "texels than this (faces still without one get a chart of their own)",
                                              min=0.0)
    min_piece_texels: float = option(64.0, help="with density bands: pieces smaller than about this many texels "
                                                "are merged into a neighbouring piece of their chart",
                                                min=0.0)
    keep_existing_uvs: bool = option(True, help="use the mesh's own UVs when they are usable (in [0, 1], "
                                                "not degenerate, not overlapping) instead of a new atlas")


@dataclasses.dataclass
class AtlasInfo:
    """What :func:`build_atlas` made.

    Attributes:
        width: atlas width in texels.
        height: atlas height in texels.
        n_charts: number of charts (UV islands).
        utilization: fraction of the atlas covered by charts (xatlas' measure; for kept UVs the
            fraction of texel centres on the surface).
        faces_without_texels: number of faces whose UV triangle owns no texel centre (see the bake).
        source: "xatlas" (new atlas) or "input" (the mesh's own UVs were kept).
        texels_per_unit: texel density used, texels per scene unit at face weight 1 (for kept UVs,
            the mean density sqrt(W H uv_area / surface_area)).
        n_covered: texels whose centre lies on the surface.
        orphan_faces: faces whose UV triangle contains no texel centre; each was given the
            nearest texel (see :mod:`texstream.geometry.bake`), those that could not be are
            counted in ``faces_without_texels``.
        reason: why the mesh's UVs were kept or replaced.
    """

    width: int
    height: int
    n_charts: int
    utilization: float
    faces_without_texels: int
    source: str = "xatlas"
    texels_per_unit: float = 0.0
    n_covered: int = 0
    orphan_faces: int = 0
    reason: str = ""

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def from_xatlas_uv(uv: np.ndarray) -> np.ndarray:
    """xatlas' normalised UVs (v down the image) -> texstream UVs (v up), float64."""
    uv = np.asarray(uv, dtype=np.float64)
    return np.stack([uv[:, 0], 1.0 - uv[:, 1]], axis=1)


def build_atlas(mesh: SurfaceMesh, config: AtlasConfig, face_weights: np.ndarray | None = None,
                device: str = "cpu") -> tuple[SurfaceMesh, AtlasInfo]:
    """Give a mesh a UV atlas for texel fitting.

    Args:
        mesh: the triangle mesh (scene units).
        config: charting and packing options.
        face_weights: (F,) non-negative relative importance per face; a chart's texel count scales
            with the area-weighted mean weight of its faces (module doc). None: uniform.
        device: Warp device of the texel coverage checks (the run's, as every stage's).

    Returns:
        (mesh with per-vertex ``uvs`` in [0, 1]^2 (v up), split at chart seams, ``source_vertex``
        indexing the input's vertices (or the input's own ``source_vertex`` when it has one), and
        ``normals`` carried over when the input had them; :class:`AtlasInfo`).

    Raises:
        InputError: the mesh is invalid, or ``face_weights`` has the wrong shape or bad values.
        ConfigError: bad options, or ``texels_per_unit`` needs an atlas larger than ``resolution``.
    """
    validate_mesh(mesh)
    _check_config(config)
    weights = _check_weights(face_weights, mesh.n_faces)
    reason = ""
    if mesh.uvs is not None:
        if not config.keep_existing_uvs:
            reason = "mesh UVs replaced: keep_existing_uvs is off"
        else:
            usable, why = _uvs_usable(mesh, config)
            if usable:
                return _keep_uvs(mesh, config, weights, device)
            reason = f"mesh UVs replaced: {why}"
    out, info = _xatlas_atlas(mesh, config, weights, device)
    info.reason = reason or "mesh had no UVs"
    return out, info


# ----------------------------------------------------------------------------------------------


def _check_config(c: AtlasConfig) -> None:
    if int(c.resolution) < 8:
        raise ConfigError(f"resolution must be at least 8 texels, got {c.resolution}",
                          fix="pass --resolution 1024")
    if not (c.texels_per_unit >= 0 and math.isfinite(c.texels_per_unit)):
        raise ConfigError(f"texels_per_unit must be >= 0, got {c.texels_per_unit}",
                          fix="pass 0 to derive it from --resolution")
    if int(c.padding) < 0:
        raise ConfigError(f"padding must be >= 0, got {c.padding}", fix="pass --padding 2")


def _check_weights(w: np.ndarray | None, n_faces: int) -> np.ndarray | None:
    if w is None:
        return None
    w = np.asarray(w, dtype=np.float64)
    if w.shape != (n_faces,):
        raise InputError(f"face_weights must have shape ({n_faces},), got {w.shape}", None,
                         "pass one weight per face")
    if not np.all(np.isfinite(w)) or w.min() < 0 or w.max() <= 0:
        raise InputError("face_weights must be finite, >= 0 and not all zero", None,
                         "clip the weights to [0, inf) (e.g. np.clip(w, 0, None))")
    return w


def _uvs_usable(mesh: SurfaceMesh, config: AtlasConfig) -> tuple[bool, str]:
    """Whether the mesh's own UVs can serve as the fitting atlas, and why not."""
    uv = np.asarray(mesh.uvs, dtype=np.float64)
    if uv.min() < -1e-6 or uv.max() > 1 + 1e-6:
        return False, "UVs leave [0, 1] (tiled or wrapped textures)"
    a_uv = np.abs(_uv_areas(uv, mesh.faces))
    a3 = mesh.face_areas()
    degenerate = (a_uv <= 1e-14) & (a3 > 1e-12 * max(a3.max(), 1e-30))
    if degenerate.mean() > 0.01:
        return False, f"{100 * degenerate.mean():.1f}% of faces have degenerate UVs"
    side = _kept_side(mesh, config)
    owner = claim_texels(mesh, side, side)
    covered = float(np.count_nonzero(owner >= 0))
    # Overlapping islands (mirrored or stacked UVs) share texels: the summed UV area then clearly
    # exceeds the covered area. The slack allows for edge texels lost to rasterisation.
    summed = float(a_uv.sum()) * side * side
    if summed > 1.1 * covered + 4.0 * math.sqrt(max(summed, 1.0)) + 16.0:
        return False, f"UV islands overlap (summed UV area {summed:.0f} texels, covered {covered:.0f})"
    return True, "mesh UVs kept: inside [0, 1], not degenerate, not overlapping"


def _kept_side(mesh: SurfaceMesh, config: AtlasConfig) -> int:
    if config.texels_per_unit <= 0:
        return int(config.resolution)
    a_uv = float(np.abs(_uv_areas(mesh.uvs, mesh.faces)).sum())
    a3 = float(mesh.face_areas().sum())
    side = int(math.ceil(config.texels_per_unit * math.sqrt(a3 / max(a_uv, 1e-30))))
    if side > config.resolution:
        raise ConfigError(f"texels_per_unit {config.texels_per_unit:g} needs a {side}x{side} atlas for the "
                          f"mesh's UVs, larger than resolution {config.resolution}",
                          fix="lower --texels-per-unit or raise --resolution")
    return max(side, 8)


def _keep_uvs(mesh: SurfaceMesh, config: AtlasConfig, weights: np.ndarray | None,
              device: str) -> tuple[SurfaceMesh, AtlasInfo]:
    side = _kept_side(mesh, config)
    n_cov, n_orphan, n_without = _coverage(mesh, side, side, device)
    a_uv = float(np.abs(_uv_areas(mesh.uvs, mesh.faces)).sum())
    tpu = side * math.sqrt(a_uv / max(float(mesh.face_areas().sum()), 1e-30))
    reason = "mesh UVs kept: inside [0, 1], not degenerate, not overlapping"
    if weights is not None:
        reason += (" (face_weights ignored: they only shape new atlases;"
                   " set keep_existing_uvs off to use them)")
    out = mesh if mesh.source_vertex is not None else dataclasses.replace(
        mesh, source_vertex=np.arange(mesh.n_vertices, dtype=np.int32))
    info = AtlasInfo(width=side, height=side, n_charts=_count_islands(out), utilization=n_cov / side ** 2,
                     faces_without_texels=n_without, source="input", texels_per_unit=tpu,
                     n_covered=n_cov, orphan_faces=n_orphan, reason=reason)
    return out, info


def _coverage(mesh: SurfaceMesh, width: int, height: int, device: str, return_owned: bool = False):
    """(covered texels, faces with no texel centre inside, faces still without a texel after
    the orphan rule), as the bake will find them; with ``return_owned`` also (F,) texels per face."""
    face = claim_texels(mesh, width, height, device, claim_orphans=False).reshape(-1)
    n_orphan = mesh.n_faces - len(np.unique(face[face >= 0]))
    tx, ty = _texel_vertex_coords(mesh, width, height)
    _claim_orphans(face, tx, ty, np.asarray(mesh.faces), width, height)
    owned = np.bincount(face[face >= 0], minlength=mesh.n_faces)
    n_without = int(np.count_nonzero(owned == 0))
    res = (int(np.count_nonzero(face >= 0)), int(n_orphan), n_without)
    return (*res, owned) if return_owned else res


def _count_islands(mesh: SurfaceMesh) -> int:
    """Connected components of faces through shared (split) vertices: the UV islands.

    Union-find by hooking roots to the smaller root and pointer jumping, vectorised.
    """
    f = np.asarray(mesh.faces, dtype=np.int64)
    a = np.concatenate([f[:, 0], f[:, 1]])
    b = np.concatenate([f[:, 1], f[:, 2]])
    parent = np.arange(mesh.n_vertices)
    while True:
        ra, rb = parent[a], parent[b]
        if np.array_equal(ra, rb):
            break
        np.minimum.at(parent, np.maximum(ra, rb), np.minimum(ra, rb))
        while True:
            pp = parent[parent]
            if np.array_equal(pp, parent):
                break
            parent = pp
    return int(len(np.unique(parent[np.unique(f)])))


def _chart_options(config: AtlasConfig, unit_scale: float = 1.0):
    """xatlas chart options; ``unit_scale`` multiplies scene lengths (the mesh was scaled by it)."""
    import xatlas

    co = xatlas.ChartOptions()
    co.max_chart_area = float(config.max_chart_area) * unit_scale ** 2
    co.max_boundary_length = float(config.max_boundary_length) * unit_scale
    co.max_cost = float(config.max_cost)
    co.max_iterations = int(config.max_iterations)
    co.normal_deviation_weight = float(config.normal_deviation_weight)
    co.roundness_weight = float(config.roundness_weight)
    co.straightness_weight = float(config.straightness_weight)
    co.normal_seam_weight = float(config.normal_seam_weight)
    co.texture_seam_weight = float(config.texture_seam_weight)
    return co


def _pack_options(config: AtlasConfig, texels_per_unit: float):
    import xatlas

    po = xatlas.PackOptions()
    po.padding = int(config.padding)
    po.bilinear = bool(config.bilinear)
    po.rotate_charts = bool(config.rotate_charts)
    po.bruteForce = bool(config.brute_force)
    po.blockAlign = bool(config.block_align)
    po.texels_per_unit = float(texels_per_unit)
    po.resolution = 0  # one atlas whose size follows from the density (we control the size)
    return po


XATLAS_SETTLE_S = 0.02
"""how long an xatlas atlas is kept after its last use before it is destroyed (:class:`_Atlas`)"""


class _Atlas:
    """An ``xatlas.Atlas`` destroyed only once its worker threads are asleep again. xatlas's TaskScheduler
    destructor sets each worker's wake-up flag and notifies it without holding the worker's mutex: a worker that
    has just finished its last task and checked the flag, but not yet blocked, misses the notification, and the
    destructor's join waits forever (a CI run hung so in ``xatlas::Destroy``). The workers block within
    microseconds of their last task, so a pause before the release closes that window."""

    def __init__(self):
        import xatlas

        self._atlas = xatlas.Atlas()

    def __getattr__(self, name):
        if name == "_atlas":  # not made (xatlas failed in __init__)
            raise AttributeError(name)
        return getattr(self._atlas, name)

    def __del__(self):
        time.sleep(XATLAS_SETTLE_S)  # the wrapped atlas is released after this returns


def _pack(uv_world: np.ndarray, faces: np.ndarray, chart: np.ndarray, config: AtlasConfig, tpu: float):
    import xatlas

    # xatlas welds UV vertices closer than an absolute epsilon (~1e-4), which folds small faces
    # of a scene in metres; in texel units nothing that far apart matters.
    atlas = _Atlas()
    atlas.add_uv_mesh((uv_world * tpu).astype(np.float32), faces.astype(np.uint32),
                      chart.astype(np.uint32).reshape(-1, 1))
    atlas.generate(xatlas.ChartOptions(), _pack_options(config, 1.0))
    return atlas


def _xatlas_atlas(mesh: SurfaceMesh, config: AtlasConfig, weights: np.ndarray | None,
                  device: str) -> tuple[SurfaceMesh, AtlasInfo]:
    import xatlas

    faces_in = np.asarray(mesh.faces, dtype=np.uint32)
    area3 = mesh.face_areas()
    total = float(area3.sum())
    if total <= 0:
        raise InputError("all faces have zero area", None, "clean the mesh (texstream mesh) before atlasing")

    # Pass 1: charts. xatlas drops faces whose area is below float32 epsilon in absolute units
    # (a 20 cm object in metres loses its small faces), so it charts a copy scaled to a
    # bounding-box diagonal of 100; chart limits are scaled alike and UVs scaled back.
    lo, hi = mesh.bbox()
    s_norm = _XATLAS_DIAGONAL / max(float(np.linalg.norm(hi - lo)), 1e-30)
    verts_n = (np.asarray(mesh.vertices, np.float64) - 0.5 * (lo + hi)) * s_norm
    chart_atlas = _Atlas()
    normals = None if mesh.normals is None else np.asarray(mesh.normals, dtype=np.float32)
    try:
        chart_atlas.add_mesh(verts_n.astype(np.float32), faces_in, normals=normals)
    except RuntimeError as e:
        raise InputError(f"xatlas rejected the mesh ({e})", None,
                         "clean the mesh (texstream mesh) first") from None
    # The packing density here only sets the resolution of xatlas' chart flattening
    # bookkeeping; ~512 texels across is plenty and fast.
    tpu_a = 512.0 / math.sqrt(total * s_norm ** 2)
    chart_atlas.generate(_chart_options(config, s_norm), _pack_options(config, tpu_a))
    vm_a, idx_a, uv_a = chart_atlas.get_mesh(0)
    n_charts = chart_atlas.get_mesh_chart_count(0)
    chart = np.full(len(idx_a), -1, dtype=np.int64)
    for c in range(n_charts):
        chart[np.asarray(chart_atlas.get_mesh_chart(0, c).faces, dtype=np.int64)] = c
    # normalised UVs -> texels -> scene units (the flattening at unit density)
    uv_world = (np.asarray(uv_a, np.float64) * [chart_atlas.width, chart_atlas.height]
                / (chart_atlas.texels_per_unit * s_norm))
    vm_a = np.asarray(vm_a, np.int64)
    idx_a = np.asarray(idx_a, np.int64)
    # Faces xatlas still ignored (zero area): one chart each, laid flat here.
    chart, idx_a, uv_world, vm_a = _flat_face_charts(mesh, np.flatnonzero(chart < 0), chart, idx_a, uv_world, vm_a)
    n_charts = int(chart.max()) + 1

    # Pass 2: with weights, charts are split into density bands and scaled (_density_charts);
    # then packed (shrinking charts the packer enlarged, see _undo_snapping). Should the pieces be
    # too many to pack at all (very noisy weights in a small atlas), small pieces are merged
    # regardless of their weight and the packing is tried again.
    res = int(config.resolution)
    base = (chart, idx_a, uv_world, vm_a)
    for merge_any in ((0.0, 0.125, 1.0) if weights is not None and config.density_bands > 0 else (0.0,)):
        if weights is not None:
            chart, idx_a, uv_world, vm_a = _density_charts(*base, weights, area3, config, merge_any)
        try:
            atlas, tpu = _pack_to_config(uv_world, idx_a, chart, config, res)
            break
        except ConfigError:
            if merge_any == 1.0 or weights is None or config.density_bands <= 0 or config.texels_per_unit > 0:
                raise
    if weights is not None:
        atlas, tpu, uv_world = _undo_snapping(atlas, tpu, uv_world, idx_a, chart, config, res)
    face_scale = np.sqrt(np.maximum(np.abs(_uv_areas(uv_world, idx_a)), 0.0) / np.maximum(area3, 1e-300))
    out = _atlas_mesh(mesh, atlas, vm_a)
    w, h = int(atlas.width), int(atlas.height)
    n_cov, n_orphan, n_without, owned = _coverage(out, w, h, device, return_owned=True)
    # Every face must own a texel: faces left without one (slivers, pole fans, faces crowded in a
    # texel) get a chart of their own of at least 2 texels and the charts are packed again, at
    # one fixed density a little under the first one (room for the new charts): a chart packed
    # at the same density mostly rasterises the same, so after the first repack the rounds
    # converge. Rounds stop when
    # the density would have to drop below half the first one (the atlas is too small for the
    # face count; faces_without_texels then says how many are left).
    # With texels_per_unit given, the density stays and rounds stop when the atlas would exceed
    # the resolution.
    tpu_first = tpu
    best = (n_without, out, atlas, tpu, n_cov, n_orphan, int(chart.max()) + 1)
    tpu_fixed = tpu * (1.0 if config.texels_per_unit > 0 else 0.95)
    for _ in range(_MIN_TEXEL_ROUNDS):
        if n_without == 0:
            break
        sel = np.flatnonzero(owned == 0)
        c2, i2, u2, v2 = _flat_face_charts(mesh, sel, chart, idx_a, uv_world, vm_a, face_scale[sel],
                                           2.0 / tpu_fixed ** 2)
        fits = False
        while tpu_fixed >= 0.5 * tpu_first:
            atlas2 = _pack(u2, i2, c2, config, tpu_fixed)
            fits = max(atlas2.width, atlas2.height) <= res
            if fits or config.texels_per_unit > 0:
                break
            tpu_fixed *= 0.97
        if not fits:
            break
        chart, idx_a, uv_world, vm_a, atlas = c2, i2, u2, v2, atlas2
        out = _atlas_mesh(mesh, atlas, vm_a)
        w, h = int(atlas.width), int(atlas.height)
        n_cov, n_orphan, n_without, owned = _coverage(out, w, h, device, return_owned=True)
        tpu = tpu_fixed
        if n_without < best[0]:
            best = (n_without, out, atlas, tpu, n_cov, n_orphan, int(chart.max()) + 1)
    # the round with the fewest faces without a texel (the first density change can cost a few)
    n_without, out, atlas, tpu, n_cov, n_orphan, n_charts = best
    w, h = int(atlas.width), int(atlas.height)
    info = AtlasInfo(width=w, height=h, n_charts=int(n_charts), utilization=float(atlas.utilization),
                     faces_without_texels=n_without, source="xatlas", texels_per_unit=float(tpu),
                     n_covered=n_cov, orphan_faces=n_orphan)
    return out, info


# bounding-box diagonal of the copy xatlas charts (_xatlas_atlas); rounds of enlarging charts
# whose faces own no texel
_XATLAS_DIAGONAL = 100.0
_MIN_TEXEL_ROUNDS = 8


def _undo_snapping(atlas, tpu: float, uv_world: np.ndarray, idx: np.ndarray, chart: np.ndarray,
                   config: AtlasConfig, res: int, rounds: int = 2, max_shrink: float = 0.25):
    """Shrink charts that xatlas' packer enlarged, and pack again.

    The packer snaps charts to whole texels and to at least about one texel (a chart 1.2 texels
    across comes out 2 across: 2.8x the texels), which for the small pieces of a density atlas
    undoes their scale. Each round divides every chart's linear size by the square root of its
    packed-to-asked area ratio (never below ``max_shrink`` of its asked size).

    Returns:
        (atlas, tpu, uv_world) of the last packing.
    """
    n = int(chart.max()) + 1
    asked = np.bincount(chart, weights=np.abs(_uv_areas(uv_world, idx)), minlength=n)
    cum = np.ones(n)
    for _ in range(rounds):
        _, idx_b, uv_b = atlas.get_mesh(0)
        got = np.bincount(chart, weights=np.abs(_uv_areas(np.asarray(uv_b, np.float64), np.asarray(idx_b, np.int64))),
                          minlength=n) * (atlas.width * atlas.height)
        now = asked * cum ** 2 * tpu ** 2
        ratio = np.divide(got, now, out=np.ones(n), where=now > 0)
        step = np.clip(1.0 / np.sqrt(np.maximum(ratio, 1e-12)), max_shrink / cum, 1.0)
        if np.all(step > 0.98):
            break
        cum = cum * step
        uv_world = _scale_charts(uv_world, idx, chart, step)
        atlas, tpu = _pack_to_config(uv_world, idx, chart, config, res)
    return atlas, tpu, uv_world


def _pack_to_config(uv_world: np.ndarray, idx: np.ndarray, chart: np.ndarray, config: AtlasConfig, res: int):
    """Pack at ``texels_per_unit`` (error if it exceeds ``res``) or search the density filling ``res``."""
    if config.texels_per_unit > 0:
        tpu = float(config.texels_per_unit)
        atlas = _pack(uv_world, idx, chart, config, tpu)
        if max(atlas.width, atlas.height) > res:
            raise ConfigError(f"texels_per_unit {tpu:g} needs a {atlas.width}x{atlas.height} atlas, larger "
                              f"than resolution {res}", fix="lower --texels-per-unit or raise --resolution")
        return atlas, tpu
    return _fit_density(uv_world, idx, chart, config, res)


def _atlas_mesh(mesh: SurfaceMesh, atlas, vm_a: np.ndarray) -> SurfaceMesh:
    """The packed atlas as a SurfaceMesh (split vertices mapped back to the input's)."""
    vm_b, idx_b, uv_b = atlas.get_mesh(0)
    src = vm_a[np.asarray(vm_b, np.int64)]
    return SurfaceMesh(
        vertices=np.asarray(mesh.vertices, np.float64)[src],
        faces=np.asarray(idx_b, dtype=np.int32),
        normals=None if mesh.normals is None else np.asarray(mesh.normals, np.float64)[src],
        uvs=from_xatlas_uv(uv_b),
        source_vertex=(src if mesh.source_vertex is None
                       else np.asarray(mesh.source_vertex)[src]).astype(np.int32),
    )


def _flat_face_charts(mesh: SurfaceMesh, sel: np.ndarray, chart: np.ndarray, idx: np.ndarray, uv: np.ndarray,
                      vmap: np.ndarray, scale: np.ndarray | float = 1.0, min_area: float = 0.0):
    """Give each face in ``sel`` a chart of its own: the triangle laid flat without distortion,
    scaled by ``scale`` and enlarged to a UV area of at least ``min_area``.

    Degenerate triangles get a small non-zero height so that they still own a texel after packing.
    The face's old vertices stay (possibly unused; the packer drops unreferenced ones).

    Returns:
        (chart (F,), idx (F, 3), uv (V', 2), vmap (V',)).
    """
    sel = np.asarray(sel, np.int64)
    if sel.size == 0:
        return chart, idx, uv, vmap
    n_charts = int(chart.max()) + 1
    f = np.asarray(mesh.faces, np.int64)[sel]
    p = np.asarray(mesh.vertices, np.float64)[f]
    e1, e2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    l1 = np.linalg.norm(e1, axis=1)
    typical = math.sqrt(float(mesh.face_areas().mean()))
    ln = np.maximum(l1, 1e-3 * typical)
    x = np.divide(e1, l1[:, None], out=np.zeros_like(e1), where=l1[:, None] > 0)
    u2 = np.einsum("ij,ij->i", e2, x)
    v2 = np.maximum(np.linalg.norm(np.cross(e1, e2), axis=1) / ln, 1e-3 * typical)
    tri = np.zeros((sel.size, 3, 2))
    tri[:, 1, 0] = ln
    tri[:, 2] = np.stack([u2, v2], 1)
    k = np.broadcast_to(np.asarray(scale, np.float64), (sel.size,))
    k = np.maximum(k, np.sqrt(min_area / (0.5 * ln * v2)))
    tri *= k[:, None, None]
    chart = chart.copy()
    idx = idx.copy()
    chart[sel] = n_charts + np.arange(sel.size)
    idx[sel] = len(uv) + np.arange(3 * sel.size).reshape(-1, 3)
    return chart, idx, np.concatenate([uv, tri.reshape(-1, 2)]), np.concatenate([vmap, f.reshape(-1)])


def _fit_density(uv_world: np.ndarray, faces: np.ndarray, chart: np.ndarray, config: AtlasConfig,
                 res: int, max_tries: int = 12):
    """Largest density whose packed atlas fits in res x res.

    The side grows about linearly with the density (less so with many small charts, whose
    borders do not scale), so each try aims at ``res`` along that line, kept inside the bracket
    of densities known to fit and known not to.
    """
    area = float(np.abs(_uv_areas(uv_world, faces)).sum())
    tpu = res * math.sqrt(0.6 / max(area, 1e-30))  # ~60% packing efficiency as a first guess
    best = None
    lo, hi = 0.0, math.inf
    for _ in range(max_tries):
        atlas = _pack(uv_world, faces, chart, config, tpu)
        side = max(atlas.width, atlas.height)
        if side <= res:
            lo = tpu
            if best is None or tpu > best[1]:
                best = (atlas, tpu)
            if side >= 0.97 * res:
                break
        else:
            hi = tpu
        # aim slightly under res so the next try likely fits
        nxt = tpu * (res / max(side, 1)) * (0.99 if side > res else 0.995)
        if not lo < nxt < hi:
            nxt = 0.5 * hi if lo == 0 else (math.sqrt(lo * hi) if math.isfinite(hi) else 1.5 * lo)
        tpu = nxt
    if best is None:
        raise ConfigError(f"could not pack the {int(chart.max()) + 1} charts into {res}x{res} texels",
                          fix="raise --resolution (or, with face weights, raise --min-piece-texels)")
    return best


# ----------------------------------------------------------------------------------------------
# stage


def _fingerprint(path, face_weights: np.ndarray | None) -> dict:
    import hashlib
    from pathlib import Path

    h = hashlib.sha256(Path(path).read_bytes()).hexdigest()
    fp = {"mesh": str(Path(path).resolve()), "mesh_sha256": h}
    if face_weights is not None:
        fp["face_weights_sha256"] = hashlib.sha256(
            np.ascontiguousarray(face_weights, dtype=np.float64).tobytes()).hexdigest()
    return fp


def photo_texel_density(mesh: SurfaceMesh, frames, min_texel_pixels: float) -> tuple[float, dict]:
    """(texels per scene unit, why) of texels ``min_texel_pixels`` pixels wide in the tenth of ``frames`` that see
    ``mesh`` largest (:func:`.density.pixel_footprints`: a pixel's surface length at the mesh's median depth)."""
    sizes = pixel_footprints(mesh, frames)
    sizes = sizes[np.isfinite(sizes)]
    if not sizes.size:
        return 0.0, {"reason": "no photo sees the mesh"}
    pixel = float(np.quantile(sizes, 0.1))
    return 1.0 / (min_texel_pixels * pixel), {"pixel_footprint": pixel, "min_texel_pixels": min_texel_pixels}


def sized_by_photos(mesh: SurfaceMesh, config: AtlasConfig, frames) -> tuple[AtlasConfig | None, dict]:
    """(the config packing at the photos' density, or None to keep ``config``; what was decided and why). The
    photos' density applies when ``resolution`` could give finer texels: at a utilization of 1 (every texel
    covered) an atlas ``resolution`` wide has sqrt(surface area) / resolution wide texels, the finest it can."""
    if frames is None or config.min_texel_pixels <= 0 or config.texels_per_unit > 0:
        return None, {"sized_by": "resolution"}
    tpu, why = photo_texel_density(mesh, frames, config.min_texel_pixels)
    finest = config.resolution / math.sqrt(max(float(mesh.face_areas().sum()), 1e-30))
    why = {"sized_by": "resolution", "photo_texels_per_unit": tpu, **why}
    if tpu <= 0 or tpu >= finest:
        return None, why
    return dataclasses.replace(config, texels_per_unit=tpu), {**why, "sized_by": "photos"}


def _sizing_line(info: AtlasInfo, sizing: dict) -> str:
    """The run's resolution line of the atlas (pipelines/resolutions.py)."""
    size = f"{info.width}x{info.height} texels"
    if sizing.get("sized_by") == "photos":
        return (f"{size}, sized by the photos: texels {sizing['min_texel_pixels']:g} px wide in the tenth of them "
                "that see the mesh largest (atlas.min_texel_pixels; finer texels than the photos resolve add no detail)")
    if "photo_texels_per_unit" in sizing:
        return f"{size} (atlas.resolution: the photos resolve texels at least this fine)"
    return f"{size} (atlas.resolution)"


def atlas_stage(mesh_path, out, config: AtlasConfig | None = None, face_weights: np.ndarray | None = None,
                device: str = "cpu", force: bool = False, capture=None, photos=None):
    """The atlas stage: mesh file -> folder with the UV-mapped mesh and the texel bake.

    Writes (atomically, all or nothing) into ``out``:
        ``mesh.obj``          the mesh with UVs (split at chart seams; welded ``v`` records),
        ``bake.npz``          the :class:`~texstream.geometry.bake.TexelBake`,
        ``seams.npz``         the :class:`~texstream.geometry.seams.Seams` (texels tied across chart
                              seams; ``average_across_seams`` removes cracks from fitted maps),
        ``atlas_config.json`` the resolved :class:`AtlasConfig`,
        ``atlas_info.json``   :class:`AtlasInfo` plus bake statistics and the input fingerprint,
        ``charts.png``        preview: normals as colours on the atlas, black outside charts.

    Skipped (``StageResult.skipped``) when ``out`` already holds the output of the same mesh file,
    weights and config, unless ``force``.

    Args:
        mesh_path: OBJ/PLY/STL/GLB/glTF mesh.
        out: output folder.
        config: atlas options (defaults when None).
        face_weights: optional (F,) per-face importance (see :func:`build_atlas`).
        device: Warp device for the bake.
        force: recompute even when an up-to-date output exists.
        capture: capture folder whose photos set the texel density (faces seen larger get more
            texels: :func:`.density.density_face_weights`); ignored when ``face_weights`` is given.
            The summary then reports the texel size in the photos (``texel_size_px``). Its photos also size
            the atlas, as ``photos`` does.
        photos: capture folder whose photos cap the texel density (``config.min_texel_pixels``: no finer texels
            than the photos resolve; the run's posed capture); the summary's ``sizing`` says which applied.

    Returns:
        StageResult whose summary is the atlas info.
    """
    from pathlib import Path

    config = config or AtlasConfig()
    out = Path(out)
    mesh = load_mesh(mesh_path)
    frames = depths = None
    if capture is not None:
        frames = read_capture(capture).frames
        with phase("atlas", f"texel density from {len(frames)} photos"):
            depths = depth_maps(mesh, frames, device)
            if face_weights is None:
                face_weights = density_face_weights(mesh, frames, device, depths)
    sizing_frames = frames if frames is not None else (read_capture(photos).frames if photos is not None else None)
    packing, sizing = sized_by_photos(mesh, config, sizing_frames)
    fp = {**_fingerprint(mesh_path, face_weights), "sizing": dict(sizing)}
    if not force and (out / "atlas_info.json").is_file() and (out / "atlas_config.json").is_file() \
            and (out / "bake.npz").is_file() and (out / "mesh.obj").is_file() and (out / "seams.npz").is_file():
        try:
            same = (read_json(out / "atlas_config.json") == config_to_dict(config)
                    and read_json(out / "atlas_info.json").get("input") == fp)
        except Exception:  # an unreadable old output is simply rebuilt
            same = False
        if same:
            return StageResult(output=out, summary=read_json(out / "atlas_info.json"), skipped=True,
                               reason="output exists for the same mesh and config")
    with phase("atlas", f"xatlas charts and packing of {mesh.n_faces} faces"):
        try:
            try:
                atlas_mesh, info = build_atlas(mesh, packing or config, face_weights, device)
            except ConfigError:  # the photos' density would need an atlas wider than resolution: resolution's
                if packing is None:
                    raise
                sizing["sized_by"] = "resolution"
                atlas_mesh, info = build_atlas(mesh, config, face_weights, device)
        except InputError as e:  # the mesh's own fault (no area, nothing to chart): name its file
            if e.path is None:
                e.path = str(mesh_path)
                e.args = (e.one_line(),)
            raise
    with phase("atlas", f"texel bake ({info.width}x{info.height})"):
        bake = bake_texels(atlas_mesh, info.width, info.height, device=device, padding=config.padding)

    with phase("atlas", "seams"):
        seams = find_seams(atlas_mesh, info.width, info.height, bake.fill_source)
    summary = {**info.to_dict(), "n_faces": atlas_mesh.n_faces, "n_vertices": atlas_mesh.n_vertices,
               "seam_edges": seams.n_edges, "seam_samples": seams.n_samples,
               "density": "photos" if capture is not None else ("weights" if face_weights is not None else "uniform"),
               "sizing": sizing, "resolution": _sizing_line(info, sizing),
               "bake_faces_without_texels": bake.faces_without_texels.tolist()[:100],
               "bake_coverage": bake.coverage, "input": fp}
    if frames is not None:
        summary["texel_size_px"] = texel_size_spread(atlas_mesh, info.width, info.height, frames, device, depths)
    with atomic_output_dir(out) as tmp:
        save_mesh(tmp / "mesh.obj", atlas_mesh)
        bake.save(tmp / "bake.npz")
        seams.save(tmp / SEAMS_FILE)
        save_config(config, tmp / "atlas_config.json")
        write_json_atomic(tmp / "atlas_info.json", summary)
        _write_preview(tmp / "charts.png", bake)
    return StageResult(output=out, summary=summary)


def _write_preview(path, bake) -> None:
    """Normals as colours (already display codes, so written unencoded as 8-bit)."""
    img = np.clip(np.rint(bake.normal_preview() * 255.0), 0, 255).astype(np.uint8)
    write_image(path, img, bits=8)
