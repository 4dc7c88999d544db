"""A view-dependent radiance model folder read back (eval, export, report, viewer): exported as the
radiance seen along the normal (fit/models/radiance/export.py), its view terms shown by the report."""

from __future__ import annotations

from pathlib import Path

from texstream.fit.models.per_texel.folder import load_per_texel
from texstream.fit.models.previews import magnitude_preview
from texstream.fit.models.radiance.folder import RadianceModel
from texstream.fit.models.registry import FittedModel


class ViewRadianceModel(RadianceModel):
    """Radiance along the normal (columns 0:3) plus view-direction terms, unlit."""

    note = ("View-dependent radiance model: unlit (radiance as a function of the view direction), the light "
            "controls do nothing.")
    radiance_caption = ", seen along the normal"
    shader_folder = Path(__file__).parent

    def report_maps(self, save, seen) -> None:
        super().report_maps(save, seen)
        # how much the view changes the radiance: the coefficients' magnitude over the view terms
        a, sa = magnitude_preview(self.grid[..., 3:18])
        save("view_dependence", a, f"view dependence: |view-term coefficients| (divided by {sa:.4g}; sRGB)")


def load(model_dir: Path, manifest: dict) -> FittedModel:
    return load_per_texel(ViewRadianceModel, "view_radiance", model_dir, manifest)
