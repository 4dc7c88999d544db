"""The view-independent radiance model (``--model radiance``): its plugin declaration."""

from __future__ import annotations

from texstream.render.layout import LayoutTraits
from texstream.fit.models.registry import AppearanceModel, register

from texstream.fit.models.radiance import choice as choice_module
from texstream.fit.models.radiance import fit as fit_module
from texstream.fit.models.radiance import folder as folder_module

PLUGIN = register(AppearanceModel(
    kind="radiance",
    title="view-independent radiance",
    needs_light=False,
    units="exitant radiance in photo values per unit exposure",
    fit=fit_module.fit,
    load=folder_module.load,
    layout_traits=LayoutTraits(lit=False, lobes=False, robust_loss="cauchy"),
    candidates=choice_module.candidates,
    escalate=choice_module.escalate,
    escalation_key="lfm",
    auto_rank=0,
))
