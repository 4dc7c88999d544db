"""The light field mapping model (``--model lfm``): its plugin declaration."""

from __future__ import annotations

from texstream.fit.models.registry import AppearanceModel, register

from texstream.fit.models.lfm import fit as fit_module
from texstream.fit.models.lfm import folder as folder_module

PLUGIN = register(AppearanceModel(
    kind="lfm",
    title="light field mapping",
    needs_light=False,
    units="exitant radiance in photo values per unit exposure",
    fit=fit_module.fit,
    load=folder_module.load,
))
