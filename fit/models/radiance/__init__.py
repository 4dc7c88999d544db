"""The view-independent radiance model (``--model radiance``): its plugin declaration."""

from __future__ import annotations

from texstream.fit.models.registry import AppearanceModel, register

from texstream.fit.models.radiance import fit as fit_module
from texstream.fit.models.radiance import folder as folder_module

PLUGIN = register(AppearanceModel(
    kind="radiance",
    title="view-independent radiance",
    needs_light=False,
    units="exitant radiance in photo values per unit exposure",
    fit=fit_module.fit,
    load=folder_module.load,
))
