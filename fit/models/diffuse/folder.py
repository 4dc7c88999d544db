"""A diffuse (Lambertian) BRDF model folder read back (eval, export, report, viewer): a Lafortune model
with no lobes (fit/models/lafortune/folder.py), exported with no specular layer."""

from __future__ import annotations

from pathlib import Path

from texstream.fit.models.lafortune.folder import LafortuneModel
from texstream.fit.models.per_texel.folder import load_per_texel
from texstream.fit.models.registry import FittedModel


def load(model_dir: Path, manifest: dict) -> FittedModel:
    return load_per_texel(LafortuneModel, "diffuse", model_dir, manifest)
