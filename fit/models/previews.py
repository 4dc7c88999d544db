"""Helpers the plugins share for the report's previews of their maps (fit/models/registry.py
``FittedModel.report_maps``)."""

from __future__ import annotations

import numpy as np

from texstream.capture.imageio import linear_to_srgb


def rgb_scaled(x: np.ndarray) -> tuple[np.ndarray, float]:
    """(sRGB image of ``x / s`` clipped to [0, 1], s): ``s`` the 99th percentile of the texels' largest
    channel (1 where that is not positive), so a few bright texels do not darken the preview."""
    scale = float(np.percentile(x.max(axis=2), 99))
    scale = scale if scale > 0 else 1.0
    return linear_to_srgb(np.clip(x / scale, 0, 1)), scale


def magnitude_preview(x: np.ndarray) -> tuple[np.ndarray, float]:
    """:func:`rgb_scaled` of the per-texel Euclidean norm of ``x`` (H, W, C), as a grey image."""
    amp = np.sqrt(np.sum(x ** 2, axis=-1))
    return rgb_scaled(np.repeat(amp[..., None], 3, axis=2))


def read_shader(folder, name: str = "viewer.glsl") -> str:
    """A plugin's GLSL for the report's viewer, shipped beside its Python (pyproject package-data)."""
    from pathlib import Path

    return (Path(folder) / name).read_text(encoding="utf-8")
