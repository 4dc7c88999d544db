"""A view-independent radiance model folder read back (eval, export, report, viewer)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from texstream.capture.imageio import read_image
from texstream.core.errors import InputError
from texstream.fit.models.per_texel.folder import PerTexelModel, checked, load_per_texel
from texstream.fit.models.previews import read_shader, rgb_scaled
from texstream.fit.models.radiance.export import radiance_material
from texstream.fit.models.registry import ExportMaterial, FittedModel, ViewerModel
from texstream.geometry.mesh_io import load_mesh
from texstream.render.layout import ModelLayout


class RadianceModel(PerTexelModel):
    """Exitant radiance per texel (columns 0:3), unlit."""

    note = "Radiance model: unlit (view-independent radiance), the light controls do nothing."
    radiance_caption = ""  # what the radiance map's caption adds
    shader_folder = Path(__file__).parent  # the viewer.glsl beside the kind's plugin

    def export_material(self, cfg) -> ExportMaterial:
        return radiance_material(self.grid, self.covered, cfg.radiance_scale)

    def report_maps(self, save, seen) -> None:
        img, s = rgb_scaled(self.grid[..., 0:3])
        save("radiance", img, f"radiance (RGB, divided by {s:.4g}, the 99th percentile; sRGB)" + self.radiance_caption)

    def viewer(self) -> ViewerModel:
        return ViewerModel(self.grid, read_shader(self.shader_folder), lit=False, note=self.note)


def load(model_dir: Path, manifest: dict) -> FittedModel:
    if "layout" not in manifest:  # a radiance map and a mesh only (model.json: kind, maps, mesh)
        return _load_radiance_map(Path(model_dir), manifest)
    return load_per_texel(RadianceModel, "radiance", model_dir, manifest)


def _load_radiance_map(d: Path, man: dict) -> RadianceModel:
    name = (man.get("maps") or {}).get("radiance", "radiance.exr")
    if not (d / name).is_file():
        raise InputError("radiance model has no radiance map", d / name, "re-run the fit that wrote this folder")
    grid = read_image(d / name, channels=3).astype(np.float32)
    mesh = load_mesh(d / man.get("mesh", "mesh.obj")).with_normals()
    return checked(RadianceModel, "radiance", d, mesh, grid, ModelLayout(kind="radiance"), man)
