"""A light field mapping model folder read back (eval, export, report, viewer)."""

from __future__ import annotations

from pathlib import Path

from texstream.fit.models.registry import FittedModel


def load(model_dir: Path, manifest: dict) -> FittedModel:
    raise NotImplementedError("placeholder: the model-folder side of the lfm plugin")
