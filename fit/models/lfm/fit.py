"""Fitting a capture with the light field mapping model."""

from __future__ import annotations


def fit(request):
    raise NotImplementedError("placeholder: the fit side of the lfm plugin")
