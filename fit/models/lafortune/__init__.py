"""The Lafortune SBRDF model (``--model lafortune``): its plugin declaration."""

from __future__ import annotations

from texstream.fit.models.registry import AppearanceModel, register

from texstream.fit.models.lafortune import fit as fit_module
from texstream.fit.models.lafortune import folder as folder_module

PLUGIN = register(AppearanceModel(
    kind="lafortune",
    title="Lafortune SBRDF",
    needs_light=True,
    units="BRDF values in 1/sr (capture/conventions.py)",
    fit=fit_module.fit,
    load=folder_module.load,
))
