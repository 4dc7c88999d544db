"""A per-texel model folder read back: the parameter maps (capture/synthetic/param_maps.py ``read_param_maps``), the
mesh and model.json, through fit/common/setup.py ``load_model``; rendered by texstream's renderer
(render/renderer.py). The kinds' folders subclass :class:`PerTexelModel` for their material, maps and
viewer shading."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from texstream.core.errors import ConfigError, InputError
from texstream.fit.common import setup
from texstream.fit.models.registry import FittedModel
from texstream.render.renderer import Renderer


class PerTexelModel(FittedModel):
    """A model with one parameter vector per atlas texel.

    Attributes (beside :class:`FittedModel`'s):
        grid: (H, W, P) float32 parameters per atlas texel (padding filled).
        layout: its ModelLayout (render/layout.py).
    """

    def __init__(self, kind: str, folder: Path, mesh, manifest: dict, covered: np.ndarray, grid: np.ndarray,
                 layout):
        super().__init__(kind, folder, mesh, manifest, covered)
        self.grid, self.layout = grid, layout

    def renderer(self, device: str = "cpu"):
        """Frame -> (image times the frame's exposure, coverage), as ``render_model``, with the mesh, its BVH and
        the maps uploaded once for every frame."""
        rend = Renderer(self.mesh, self.grid, self.layout, device=device)

        def render(frame):
            res = rend.render_frame(frame)
            return res.radiance * np.float32(frame.exposure), res.mask
        return render

    def report_facts(self) -> list[tuple[str, str]]:
        lay = self.layout
        lobes = (f", {lay.n_lobes} lobe(s)" if lay.n_lobes else "") + (" anisotropic" if lay.anisotropic else "")
        if lay.n_lobes:
            lobes += f", lobe shape {(self.manifest.get('layout') or {}).get('lobe_shape')}"
        return [("model", f"{self.kind}{lobes}")]


def load_per_texel(model_class: type, kind: str, model_dir: Path, manifest: dict) -> PerTexelModel:
    """Read a per-texel model folder as ``model_class``; every problem is an InputError naming the file and
    the fix. ``covered``: bake.npz's covered texels (all, without a usable bake)."""
    d = Path(model_dir)
    try:
        mesh, grid, layout, man = setup.load_model(d)
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
    return checked(model_class, kind, d, mesh, grid, layout, man)


def checked(model_class: type, kind: str, d: Path, mesh, grid: np.ndarray, layout, man: dict) -> PerTexelModel:
    """The model, once its mesh has UVs and its maps the layout's channels."""
    if mesh.uvs is None:
        raise InputError("mesh has no texture coordinates", d / "mesh.obj",
                         "export the mesh.obj the fit wrote (it carries the atlas UVs)")
    need = layout.n_params
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
    return model_class(kind, d, mesh, man, covered, grid, layout)
