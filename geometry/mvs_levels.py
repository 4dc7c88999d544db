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


REFERENCE_SIDE = 640
"""the longer side (pixels) of the photos ``MvsConfig.depths`` was chosen for: the Middlebury temple's 640x480, about
one pixel of parallax per plane"""


def planes_at_level(depths: int, frames_at_level: Sequence, level: int) -> int:
    """The plane sweep's depth hypotheses for photos matched at ``level`` (``frames_at_level``: their cameras there):
    the parallax across the object's depth range grows with the matched photo's size, so ``depths`` per
    :data:`REFERENCE_SIDE` pixels of its longer side, and never fewer than ``depths / 2^level`` (the same parallax
    per plane as the full-size photo's ``depths``, the rule for photos no larger than the temple's). Before, photos
    of 3072x2048 matched at level 2 swept 40 planes, several pixels of parallax each, and the consistency test kept
    2,236 points; 192 planes keep 114,281 (docs/scale.md)."""
    side = max((max(int(f.intrinsics.width), int(f.intrinsics.height)) for f in frames_at_level), default=0)
    return max(8, int(depths) >> int(level), round(int(depths) * side / REFERENCE_SIDE))


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
