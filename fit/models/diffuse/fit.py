"""The fit of this per-texel model: the shared per-texel fit (fit/models/per_texel/fit.py); what differs
between the per-texel kinds is their layout traits (declared in this plugin's __init__.py)."""

from __future__ import annotations

from texstream.fit.models.per_texel.fit import fit

__all__ = ["fit"]
