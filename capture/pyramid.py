"""Photo pyramids: a level L of a photo averages its 2^L x 2^L pixel boxes, and its camera is the same pinhole at
1/2^L the scale. The fit streams the level its texels need (fit/common/photo_levels.py) and the photometric
refinement runs coarse to fine over them (geometry/refine_levels.py). numpy only."""

from __future__ import annotations

import dataclasses

import numpy as np


def frame_at_level(frame, level: int):
    """``frame`` (a capture Frame) with the camera of its photo's level ``level``: the image
    ``width >> level`` x ``height >> level`` (the last rows and columns of a size not divisible by 2^level are
    dropped), the focal lengths and principal point divided by 2^level (pixel centres at +0.5 at every level,
    so continuous pixel coordinates scale exactly)."""
    if level == 0:
        return frame
    s = 2 ** level
    intr = frame.intrinsics
    scaled = dataclasses.replace(intr, width=int(intr.width) // s, height=int(intr.height) // s,
                                 fx=intr.fx / s, fy=intr.fy / s, cx=intr.cx / s, cy=intr.cy / s)
    return dataclasses.replace(frame, intrinsics=scaled)


def box_average(pixels: np.ndarray, level: int) -> np.ndarray:
    """Mean of each 2^level x 2^level box of an (H, W, C) array (trailing rows and columns dropped)."""
    s = 2 ** level
    h, w = pixels.shape[0] // s, pixels.shape[1] // s
    boxes = pixels[: h * s, : w * s].reshape(h, s, w, s, *pixels.shape[2:])
    return boxes.mean(axis=(1, 3), dtype=np.float64).astype(pixels.dtype)
