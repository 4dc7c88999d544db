"""A light field mapping model folder read back (eval, export, report, viewer).

The viewer draws it from per-texel data, view-map textures and vertex frames (:func:`viewer_grid`,
:func:`viewer_data`) with viewer.glsl, which sums the terms as model_folder.py's LFMRenderer does.
"""

from __future__ import annotations

import base64
import math
from pathlib import Path

import numpy as np

from texstream.core.errors import InputError
from texstream.fit.models.lfm.export import lfm_atlas, lfm_unlit_radiance
from texstream.fit.models.lfm.model_folder import load_lfm_model, tile_view_maps
from texstream.fit.models.previews import magnitude_preview, read_shader, rgb_scaled
from texstream.fit.models.radiance.export import radiance_material
from texstream.fit.models.registry import ExportMaterial, FittedModel, ViewerModel

FRAME_COLUMNS = 512
"""vertices per row of the LFM viewer's vertex-frame texture (4 texels each: 2048 wide, WebGL2's minimum)"""


class LFMModel(FittedModel):
    """An LFM model folder (``lfm``: model_folder.py's LFMModelFolder: mesh, bake, geometry, parameters)."""

    def __init__(self, lfm):
        covered = np.asarray(lfm.bake.covered, bool)
        if not covered.any():
            covered = np.ones((lfm.bake.height, lfm.bake.width), bool)
        super().__init__("lfm", lfm.folder, lfm.mesh, lfm.manifest, covered)
        self.lfm = lfm
        self._viewer_grid = None

    def renderer(self, device: str = "cpu"):
        return self.lfm.renderer(device).render_frame

    def export_material(self, cfg) -> ExportMaterial:
        grid = lfm_atlas(self.lfm, lfm_unlit_radiance(self.lfm, cfg.lfm_view_mean))
        mat = radiance_material(grid, self.covered, cfg.radiance_scale)
        mat.extras = {"lfm_view_mean": cfg.lfm_view_mean}  # the unlit approximation of a light field
        return mat

    @property
    def viewer_grid(self) -> np.ndarray:
        if self._viewer_grid is None:
            self._viewer_grid = viewer_grid(self.lfm)
        return self._viewer_grid

    def report_maps(self, save, seen) -> None:
        model, grid = self.lfm, self.viewer_grid
        img, s = rgb_scaled(grid[..., 0:3])
        save("diffuse", img, f"view-independent term d (RGB, divided by {s:.4g}, the 99th percentile; sRGB)")
        img, s = rgb_scaled(np.maximum(lfm_atlas(model, lfm_unlit_radiance(model)), 0.0))
        save("unlit", img, "the exported unlit colour: d plus each term's cosine-weighted mean over view directions "
             f"(divided by {s:.4g}; sRGB)")
        a, sa = magnitude_preview(grid[..., 6:])
        save("surface_maps", a, f"view dependence: |surface maps| over slots and terms (divided by {sa:.4g}; sRGB)")
        views = tile_view_maps(np.asarray(model.params.H[:, 0]), model.view_res)
        v, sv = rgb_scaled(np.abs(views))
        save("view_k0", v, f"term 0's view maps |h|, one {model.view_res}x{model.view_res} tile per vertex "
             f"(divided by {sv:.4g}; sRGB)")

    def report_facts(self) -> list[tuple[str, str]]:
        man = self.manifest
        lay, lf = man.get("layout") or {}, man.get("lfm") or {}
        res = lay.get("view_res")
        desc = (f"{self.kind}, K={lay.get('terms')}, {res}x{res} {lay.get('view_map')} view maps, {lay.get('method')}, "
                f"{lf.get('vertices_welded')} vertices")
        return [("model", desc), ("texels", f"{lf.get('texels')} of {self.lfm.bake.width}x{self.lfm.bake.height}"),
                ("iterations", _fmt((man.get("method_info") or {}).get("iterations"))),
                ("fit time", f"{_fmt(man.get('fit_s'))} s"),
                ("sample PSNR", f"{_fmt((man.get('sample_error') or {}).get('psnr_db'))} dB")]

    def viewer(self) -> ViewerModel:
        note = ("Light field mapping model: unlit, the view-independent term plus, per vertex of the texel's "
                "triangle and term, surface map times the vertex's view map looked up along the view direction in "
                "the vertex's frame (fit/models/lfm/model_folder.py LFMRenderer); 'diffuse' shows the view-independent term, "
                "'specular' the view-dependent terms; the light controls do nothing.")
        return ViewerModel(self.viewer_grid, read_shader(Path(__file__).parent), lit=False, data=viewer_data(self.lfm),
                           note=note)


def _fmt(x) -> str:
    """A figure as the report's summary writes it (4 significant digits)."""
    if isinstance(x, float):
        return f"{x:.4g}" if math.isfinite(x) else "nan"
    return str(x)


def viewer_grid(model) -> np.ndarray:
    """(H, W, 6 + 9 K) float32 per atlas texel of an LFM model (what its renderer reads there: the texel
    itself or, for padding, the texel it copies): the view-independent term d (0:3), the welded vertex
    of each of its three slots (3:6, -1: no texel), and the surface maps G[slot j, term k] at
    6 + 3 (j K + k) (fit/kernels/lfm.py ``texel_radiance``)."""
    p = model.params
    n, k = p.diffuse.shape[0], model.terms
    per_texel = np.concatenate([p.diffuse, model.geom.slot_vertex.reshape(n, 3).astype(np.float64),
                                np.asarray(p.G, np.float64).reshape(n, 9 * k)], axis=1)
    grid = lfm_atlas(model, per_texel)
    valid = lfm_atlas(model, np.ones((n, 1)))[..., 0] > 0
    grid[~valid, 3:6] = -1.0
    return grid


def viewer_data(model) -> dict:
    """The viewer's LFM textures and options: the view maps as RGBA32F layers (term k in layer k, vertex
    v's R x R tile at tile column v % cols, row v // cols: model_folder.py ``tile_view_maps``) and the
    welded vertices' positions and frames (texels 4 (v % FRAME_COLUMNS) + [0: position, 1: tangent,
    2: bitangent, 3: normal], row v // FRAME_COLUMNS), with the lookup options as the shader's integers."""
    p, g, res = model.params, model.geom, model.view_res
    tiles = np.stack([tile_view_maps(np.asarray(p.H[:, k]), res) for k in range(model.terms)])  # (K, h, w, 3)
    views = np.zeros((*tiles.shape[:3], 4), np.float32)
    views[..., :3] = tiles
    V = g.n_vertices
    rows = -(-V // FRAME_COLUMNS)
    frames = np.zeros((rows * FRAME_COLUMNS, 4, 4), np.float32)
    frames[:V, :, :3] = np.stack([g.vpos, g.vtan, g.vbit, g.vnrm], axis=1)
    frames = frames.reshape(rows, FRAME_COLUMNS * 4, 4)
    c = model.cfg
    uniforms = {"u_terms": model.terms, "u_vres": res, "u_vcols": max(1, int(np.ceil(np.sqrt(V)))),
                "u_fcols": FRAME_COLUMNS, "u_vmap": int(c.view_map == "hemioct"),
                "u_vlookup": int(c.lookup != "nearest"), "u_vinterp": int(c.render_view != "vertex"),
                "u_slookup": int(c.surface_lookup != "nearest")}
    textures = [{"name": "u_views", "width": int(views.shape[2]), "height": int(views.shape[1]),
                 "layers": int(views.shape[0]), "data": _b64(views)},
                {"name": "u_vframe", "width": int(frames.shape[1]), "height": int(frames.shape[0]),
                 "data": _b64(frames)}]
    return {"uniforms": uniforms, "textures": textures}


def _b64(a: np.ndarray) -> str:
    return base64.b64encode(np.ascontiguousarray(a, dtype="<f4").tobytes()).decode("ascii")


def load(model_dir: Path, manifest: dict) -> FittedModel:
    d = Path(model_dir)
    try:
        model = load_lfm_model(d)
    except (KeyError, TypeError, ValueError) as e:
        why = f"model.json or lfm.npz are inconsistent ({type(e).__name__}: {e})"
        raise InputError(why, d / "model.json", "re-run `texstream fit --model lfm` to rewrite the folder") from None
    if model.mesh.uvs is None:
        raise InputError("mesh has no texture coordinates", d / "mesh.obj",
                         "export the mesh.obj the fit wrote (it carries the atlas UVs)")
    return LFMModel(model)
