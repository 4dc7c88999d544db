"""Dense stereo at a pyramid level (geometry/mvs.py, MvsConfig.level; issue 40): depth maps finer than the mesh
needs cost sweep time (4x the pixels and 2x the planes per level) and give points the fusion voxels
and Poisson merge anyway, since the mesh stage decimates to MeshConfig.faces. How coarse is coarse enough was
measured on the temple (MvsConfig.level_min_mask_pixels). A level averages the photo's 2^L x 2^L boxes and scales
its camera, as the fit's photo levels do (fit/common/photo_levels.py, a layer above, whose rule this repeats).
numpy only."""

from __future__ import annotations

import dataclasses
from typing import Sequence

import numpy as np


def matching_level(mask: np.ndarray, min_mask_pixels: int, max_level: int = 4) -> int:
    """MvsConfig.level auto: the coarsest level (at most ``max_level``) at which the median photo's mask, ``mask``
    (n, H, W) at full resolution, keeps ``min_mask_pixels`` pixels."""
    pixels = float(np.median(np.count_nonzero(mask.reshape(len(mask), -1), axis=1)))
    level = 0
    while level < max_level and pixels / 4 ** (level + 1) >= min_mask_pixels:
        level += 1
    return level


def frame_at_level(frame, level: int):
    """``frame`` with the camera of its photo's pyramid level (the same rule as the fit's
    fit/common/photo_levels.py ``frame_at_level``: sizes floor-divided, focal lengths and principal point divided
    by 2^level, pixel centres at +0.5 at every level)."""
    s = 2 ** level
    intr = frame.intrinsics
    return dataclasses.replace(frame, intrinsics=dataclasses.replace(
        intr, width=int(intr.width) // s, height=int(intr.height) // s, fx=intr.fx / s, fy=intr.fy / s,
        cx=intr.cx / s, cy=intr.cy / s))


def stack_at_level(grey: np.ndarray, mask: np.ndarray, frames: Sequence, level: int
                   ) -> tuple[np.ndarray, np.ndarray]:
    """The matching stack at ``level``: each photo's 2^level boxes of grey averaged (the box filter keeps the
    texture's mean, against aliasing), its mask kept where the whole box is object; ``frames`` at the level."""
    s = 2 ** level
    n, hmax, wmax = len(frames), max(f.intrinsics.height for f in frames), max(f.intrinsics.width for f in frames)
    out_grey, out_mask = np.zeros((n, hmax, wmax), np.float32), np.zeros((n, hmax, wmax), np.uint8)
    for c, f in enumerate(frames):
        h, w = f.intrinsics.height, f.intrinsics.width
        boxes = grey[c, :h * s, :w * s].reshape(h, s, w, s)
        out_grey[c, :h, :w] = boxes.mean(axis=(1, 3), dtype=np.float64)
        out_mask[c, :h, :w] = mask[c, :h * s, :w * s].reshape(h, s, w, s).min(axis=(1, 3))
    return out_grey, out_mask
