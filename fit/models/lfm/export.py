"""The unlit approximation of a light field mapping model, which glTF and OBJ export (fit/stages/export.py).

Exported unlit like the radiance models. Base colour per texel: the view-independent term d(s)
plus, for each of the texel's three vertex light fields and each term k, its surface map value
times the mean of the vertex's view map over view directions, cosine-weighted over the vertex's
hemisphere (``lfm_view_mean = "cosine"``: seen from viewpoints all around, a surface element
covers pixels in proportion to cos(theta_v), so this is the pixel-weighted average colour of the
element); ``"none"`` keeps d(s) alone. The mean uses the renderer's own view-map lookups
(``view_taps`` of fit/kernels/lfm.py at a 128 x 128 grid of disk-uniform directions). The exact
surface and view maps stay in ``maps/*.exr`` (diffuse, surface_k{k}_v{j}, view_k{k}).

Imports numpy and warp (through the LFM kernels) at module level; the unlit renderer is the per-texel one
(fit/common/setup.py ``render_model``).
"""

from __future__ import annotations

import numpy as np

from texstream.core.errors import ConfigError
from texstream.fit.common.setup import render_model
from texstream.fit.kernels import lfm as LK
from texstream.fit.kernels.lfm_lookup import direction_taps_kernel
from texstream.fit.models.lfm.model_folder import grid_source
from texstream.render.layout import ModelLayout

LFM_VIEW_MEANS = ("cosine", "none")
VIEW_MEAN_GRID = 128
"""disk-uniform directions per side of the grid the LFM view-map means average over (12,868 in the disk)"""


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
    """(N, 3) the unlit radiance of each compact texel of an LFM model (model_folder.py
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
    b = model.bake
    src = grid_source(b, model.grid_index)
    v = np.asarray(values)
    out = np.zeros((b.height * b.width, v.shape[1]), np.float32)
    out[src >= 0] = v[src[src >= 0]]
    return out.reshape(b.height, b.width, v.shape[1])


def lfm_unlit_renderer(model, view_mean: str = "cosine", device: str = "cpu"):
    """frame -> (image, coverage): the exported unlit approximation of an LFM model rendered by
    texstream's radiance renderer (render/renderer.py, bilinear atlas lookup, times the frame's exposure),
    to score it against the full model or the photos."""
    grid = lfm_atlas(model, lfm_unlit_radiance(model, view_mean, device))
    layout = ModelLayout(kind="radiance")
    mesh = model.mesh

    def render(frame):
        return render_model(mesh, grid, layout, frame, device)
    return render
