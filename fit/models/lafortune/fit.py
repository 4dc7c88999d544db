"""Fitting a capture with the Lafortune SBRDF model."""

from __future__ import annotations


def fit(request):
    raise NotImplementedError("placeholder: the fit side of the lafortune plugin")
