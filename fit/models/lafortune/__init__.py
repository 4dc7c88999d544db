"""The Lafortune SBRDF model (``--model lafortune``): its plugin declaration."""

from __future__ import annotations

from texstream.render.layout import LayoutTraits
from texstream.fit.models.registry import AppearanceModel, register

from texstream.fit.models.lafortune import choice as choice_module
from texstream.fit.models.lafortune import fit as fit_module
from texstream.fit.models.lafortune import folder as folder_module

PLUGIN = register(AppearanceModel(
    kind="lafortune",
    title="Lafortune SBRDF",
    needs_light=True,
    units="BRDF values in 1/sr (capture/conventions.py)",
    fit=fit_module.fit,
    load=folder_module.load,
    layout_traits=LayoutTraits(lit=True, lobes=True, ambient=True),
    candidates=choice_module.candidates,
    auto_rank=0,
))
