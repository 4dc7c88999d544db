"""The diffuse (Lambertian) BRDF model (``--model diffuse``): its plugin declaration."""

from __future__ import annotations

from texstream.render.layout import LayoutTraits
from texstream.fit.models.registry import AppearanceModel, register

from texstream.fit.models.diffuse import fit as fit_module
from texstream.fit.models.diffuse import folder as folder_module

PLUGIN = register(AppearanceModel(
    kind="diffuse",
    title="diffuse (Lambertian) BRDF",
    needs_light=True,
    units="BRDF values in 1/sr (capture/conventions.py)",
    fit=fit_module.fit,
    load=folder_module.load,
    layout_traits=LayoutTraits(lit=True, lobes=False, ambient=True),
))
