"""The fit of this per-texel model: the radiance models' fit (fit/models/radiance/fit.py: the shared per-texel
fit under their stopping rule); what differs between the per-texel kinds is their layout traits (declared in
this plugin's __init__.py)."""

from __future__ import annotations

from texstream.fit.models.radiance.fit import fit

__all__ = ["fit"]
