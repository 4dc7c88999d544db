"""Fitting a capture with the view-dependent radiance model."""

from __future__ import annotations


def fit(request):
    raise NotImplementedError("placeholder: the fit side of the view_radiance plugin")
