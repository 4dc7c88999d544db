"""The relightable diffuse model under one unknown environment light (``--model env_diffuse``): its plugin
declaration.

Photos under one fixed, unknown lighting (no ``light`` per frame, as for the radiance models); its global
parameters are the light, order-2 SH (render/sh.py), fitted with a per-texel albedo (fit.py, solve.py).

It is never a base model (``candidates`` None). With the choice's ``relightable`` option (``texstream run
--relightable``) it is fitted beside the radiance models of a capture without lights and kept where its
validation error is within ``relightable_margin_db`` of the best one (fit/stages/choice.py), since its renders
under the photos' own light are a diffuse approximation of what the radiance models fit freely. Its folder
says it can be relit (``EnvDiffuseModel.relightable``, ``relit_renderer``).
"""

from __future__ import annotations

from texstream.fit.models.registry import AppearanceModel, register

from texstream.fit.models.env_diffuse import fit as fit_module
from texstream.fit.models.env_diffuse import folder as folder_module

PLUGIN = register(AppearanceModel(
    kind="env_diffuse",
    title="relightable diffuse under an estimated environment light",
    needs_light=False,
    units=fit_module.UNITS,
    fit=fit_module.fit,
    load=folder_module.load,
    relightable=True,
))
