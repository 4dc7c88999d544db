"""The view-dependent radiance model (``--model view_radiance``): its plugin declaration."""

from __future__ import annotations

from texstream.render.layout import LayoutTraits, VIEW_TERMS
from texstream.fit.models.registry import AppearanceModel, register

from texstream.fit.models.view_radiance import fit as fit_module
from texstream.fit.models.view_radiance import folder as folder_module

PLUGIN = register(AppearanceModel(
    kind="view_radiance",
    title="view-dependent radiance",
    needs_light=False,
    units="exitant radiance in photo values per unit exposure (along the normal; view terms alike)",
    fit=fit_module.fit,
    load=folder_module.load,
    layout_traits=LayoutTraits(lit=False, lobes=False, view_terms=len(VIEW_TERMS)),
))
