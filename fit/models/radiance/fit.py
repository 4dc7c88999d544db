"""Fitting a capture with the view-independent radiance model."""

from __future__ import annotations


def fit(request):
    raise NotImplementedError("placeholder: the fit side of the radiance plugin")
