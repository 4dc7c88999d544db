"""An LFM model folder (light field mapping, fit/models/lfm): reading it back and rendering it.

The model folder: mesh.obj, bake.npz, lfm.npz (the exact float64 parameters: diffuse (N, 3), G
(3N, K, 3), H (V, K, R*R, 3), and the compact texels' atlas index), the maps as float EXR for
viewing (diffuse.exr; surface_k{k}_v{j}.exr: term k's surface map of each texel's face vertex j;
view_k{k}.exr: term k's view maps tiled per vertex, R x R tiles in vertex order), model.json
(layout kind "lfm", the LFM options, welded vertex count, trace, held-out scores) and renders/.
The fit that writes it is fit/stages/lfm_stage.py. Imports OpenImageIO inside its functions.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np

from texstream.capture.imageio import write_image
from texstream.core.errors import InputError
from texstream.core.outputs import read_json
from texstream.fit.kernels import lfm as LK
from texstream.fit.models.lfm.problem import LFMConfig, LFMGeometry, LFMParams
from texstream.geometry.bake import TexelBake
from texstream.geometry.mesh_io import load_mesh
from texstream.render.camera import pinhole_camera


def lfm_geometry(mesh, bake, texels):
    gi = np.asarray(texels.grid_index, np.int64)
    return LFMGeometry.build(mesh.vertices, mesh.faces, mesh.vertex_normals(), bake.face.reshape(-1)[gi],
                             bake.bary.reshape(-1, 3)[gi], texels.position)


def grid_source(bake, grid_index: np.ndarray) -> np.ndarray:
    """(H * W,) compact texel each atlas texel reads (itself or the texel its padding copies), -1 none."""
    n = bake.height * bake.width
    compact = -np.ones(n, np.int64)
    compact[np.asarray(grid_index, np.int64)] = np.arange(len(grid_index))
    src = np.arange(n) if getattr(bake, "fill_source", None) is None else np.asarray(bake.fill_source).reshape(-1)
    return np.where(src >= 0, compact[np.maximum(src, 0)], -1).astype(np.int32)


class LFMRenderer:
    """Renders an LFM model (radiance per unit exposure) for capture frames (fit/kernels/lfm.py)."""

    def __init__(self, mesh, bake, geom, params, cfg, grid_index: np.ndarray, device: str = "cpu"):
        import warp as wp

        self.wp, self.cfg, self.device = wp, cfg, device
        d = device
        self.points = wp.array(np.asarray(mesh.vertices, np.float32), dtype=wp.vec3, device=d)
        self.indices = wp.array(np.asarray(mesh.faces, np.int32).reshape(-1), dtype=wp.int32, device=d)
        self.normals = wp.array(np.asarray(mesh.vertex_normals(), np.float32), dtype=wp.vec3, device=d)
        self.uvs = wp.array(np.asarray(mesh.uvs, np.float32), dtype=wp.vec2, device=d)
        self.mesh = wp.Mesh(points=self.points, indices=self.indices)
        self.source = wp.array(grid_source(bake, grid_index), dtype=wp.int32, device=d)
        self.tex_w, self.tex_h = int(bake.width), int(bake.height)
        K = params.G.shape[1]
        M = params.H.shape[2]
        self.K, self.R = K, int(round(math.sqrt(M)))
        self.diffuse = wp.array(np.asarray(params.diffuse, np.float64), dtype=wp.vec3d, device=d)
        self.G = wp.array(np.ascontiguousarray(params.G, np.float64), dtype=wp.vec3d, device=d)
        self.H = wp.array(np.ascontiguousarray(params.H.reshape(-1, M, 3), np.float64), dtype=wp.vec3d, device=d)
        self.slot_vertex = wp.array(geom.slot_vertex, dtype=wp.int32, device=d)
        self.vframe = [wp.array(a, dtype=wp.vec3d, device=d) for a in (geom.vpos, geom.vtan, geom.vbit, geom.vnrm)]

    def render_frame(self, frame, view_interp: str | None = None):
        wp = self.wp
        k = frame.intrinsics
        cam = pinhole_camera(frame.R, frame.t, k.fx, k.fy, k.cx, k.cy, k.width, k.height)
        rad = wp.zeros((k.height, k.width), dtype=wp.vec3, device=self.device)
        mask = wp.zeros((k.height, k.width), dtype=wp.uint8, device=self.device)
        interp = (view_interp or self.cfg.render_view) == "point"
        wp.launch(LK.render_lfm_kernel, dim=(k.height, k.width), device=self.device,
                  inputs=[self.mesh.id, self.points, self.indices, self.normals, self.uvs, self.source, self.tex_w,
                          self.tex_h, int(self.cfg.surface_lookup == "bilinear"), self.diffuse, self.slot_vertex,
                          self.G, self.H, *self.vframe, cam, int(interp), self.K,
                          0 if self.cfg.view_map == "disk" else 1, self.R, int(self.cfg.lookup == "bilinear")],
                  outputs=[rad, mask])
        return rad.numpy().reshape(k.height, k.width, 3) * np.float32(frame.exposure), mask.numpy().astype(bool)


def tile_view_maps(H: np.ndarray, res: int) -> np.ndarray:
    """(V, M, 3) view maps of one term tiled R x R per vertex, ceil(sqrt(V)) tiles per row."""
    V = H.shape[0]
    cols = max(1, math.ceil(math.sqrt(V)))
    rows = math.ceil(V / cols)
    out = np.zeros((rows * res, cols * res, 3), np.float32)
    for v in range(V):  # writing the maps once, not in the fit's iteration
        r, c = divmod(v, cols)
        out[r * res:(r + 1) * res, c * res:(c + 1) * res] = H[v].reshape(res, res, 3)
    return out


def write_lfm_maps(folder: Path, params, bake, grid_index: np.ndarray, res: int) -> dict:
    files = {}

    def atlas(values):
        grid = np.zeros((bake.height * bake.width, 3), np.float32)
        grid[grid_index] = values
        return bake.fill_padding(grid.reshape(bake.height, bake.width, 3))

    write_image(folder / "diffuse.exr", atlas(params.diffuse), bits=32)
    files["diffuse"] = "diffuse.exr"
    N = params.diffuse.shape[0]
    G = params.G.reshape(N, 3, -1, 3)
    for k in range(G.shape[2]):
        for j in range(3):
            name = f"surface_k{k}_v{j}"
            write_image(folder / f"{name}.exr", atlas(G[:, j, k]), bits=32)
            files[name] = f"{name}.exr"
        write_image(folder / f"view_k{k}.exr", tile_view_maps(params.H[:, k], res), bits=32)
        files[f"view_k{k}"] = f"view_k{k}.exr"
    return files


@dataclasses.dataclass
class LFMModelFolder:
    """An LFM model folder loaded for rendering, export and the report's viewer.

    Attributes:
        folder: the model folder.
        mesh: the mesh (with normals and UVs).
        bake: its TexelBake (atlas grid, padding sources).
        geom: the :class:`texstream.fit.models.lfm.problem.LFMGeometry` with the fit's exact vertex frames.
        params: the fitted :class:`texstream.fit.models.lfm.problem.LFMParams` (float64).
        cfg: the :class:`texstream.fit.models.lfm.problem.LFMConfig` the model was fitted with (lookups, mapping).
        grid_index: (N,) atlas index (y * W + x) of each compact texel.
        manifest: model.json.
    """

    folder: Path
    mesh: object
    bake: object
    geom: object
    params: object
    cfg: object
    grid_index: np.ndarray
    manifest: dict

    @property
    def terms(self) -> int:
        return int(self.params.G.shape[1])

    @property
    def view_res(self) -> int:
        return int(round(math.sqrt(self.params.H.shape[2])))

    def renderer(self, device: str = "cpu", view_interp: str | None = None) -> LFMRenderer:
        cfg = self.cfg if not view_interp else dataclasses.replace(self.cfg, render_view=view_interp)
        return LFMRenderer(self.mesh, self.bake, self.geom, self.params, cfg, self.grid_index, device)


def load_lfm_model(model_dir) -> LFMModelFolder:
    """Read an LFM model folder (model.json, mesh.obj, bake.npz, lfm.npz); InputError naming the file
    when one is missing or they disagree."""
    d = Path(model_dir)
    man = read_json(d / "model.json", what="model manifest")
    lay = dict(man["layout"])
    lay.pop("kind")
    cfg = LFMConfig(**{k: v for k, v in lay.items() if k in {f.name for f in dataclasses.fields(LFMConfig)}})
    for name in ("mesh.obj", "bake.npz", "lfm.npz"):
        if not (d / name).is_file():
            raise InputError(f"LFM model folder has no {name}", d / name,
                             "re-run `texstream fit --model lfm`")
    mesh = load_mesh(d / "mesh.obj").with_normals()
    bake = TexelBake.load(d / "bake.npz")
    z = np.load(d / "lfm.npz")
    gi = z["grid_index"]
    pos = bake.position.reshape(-1, 3)[gi]
    geom = LFMGeometry.build(mesh.vertices, mesh.faces, mesh.vertex_normals(), bake.face.reshape(-1)[gi],
                             bake.bary.reshape(-1, 3)[gi], pos)
    if geom.n_vertices != z["H"].shape[0]:
        raise InputError(f"lfm.npz has {z['H'].shape[0]} view maps for {geom.n_vertices} welded vertices", d / "lfm.npz",
                         "refit the model (the mesh changed)")
    # the fit's vertex frames exactly (the OBJ round trip may perturb the normals in the last digits)
    geom = dataclasses.replace(geom, vpos=z["vpos"], vnrm=z["vnrm"], vtan=z["vtan"], vbit=z["vbit"])
    return LFMModelFolder(d, mesh, bake, geom, LFMParams(z["diffuse"], z["G"], z["H"]), cfg, gi, man)


def load_lfm_renderer(model_dir, device: str = "cpu", view_interp: str | None = None):
    """A render function frame -> (image, coverage) for an LFM model folder."""
    return load_lfm_model(model_dir).renderer(device, view_interp).render_frame
