"""Fitting a capture with the diffuse (Lambertian) BRDF model."""

from __future__ import annotations


def fit(request):
    raise NotImplementedError("placeholder: the fit side of the diffuse plugin")
