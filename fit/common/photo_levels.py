"""Photos streamed at the resolution the texels need (issue 40): a pyramid level L of a photo averages its
2^L x 2^L pixel boxes, and its camera is the same pinhole at 1/2^L the scale.

The fit samples a texel at its centre in each photo (seed ch. 4), so when a texel spans many pixels, the
pixels between texel centres cost decoding, upload, memory and depth-map work but add no sample; a coarser
level keeps their light (a box filter) at a quarter of the cost per level. The level is chosen from the
texels' footprint in the photos (:func:`texstream.geometry.density.photo_level_for`). Held-out views are
always scored at full resolution: the model handed back is judged on the photos as they are.

The readers are module-level classes so the decoding pool's worker processes can receive them
(fit/stream/decode_pool.py). numpy only.
"""

from __future__ import annotations

import numpy as np

from texstream.capture.pyramid import box_average, frame_at_level  # noqa: F401 - frame_at_level: for the fit's callers
from texstream.core.errors import InputError


def _check_level_size(path, full_hw: tuple[int, int], want_hw, level: int, rows) -> None:
    """The photo's full size must give the level's expected (H, W) (H unchecked when reading rows)."""
    if want_hw is None:
        return
    s = 2 ** level
    h_ok = rows is not None or full_hw[0] // s == int(want_hw[0])
    if not (h_ok and full_hw[1] // s == int(want_hw[1])):
        raise InputError(f"photo is {full_hw[1]}x{full_hw[0]} pixels, its camera expects "
                         f"{int(want_hw[1]) * s}x{int(want_hw[0]) * s}", path,
                         "re-register the capture or give the photos at the size capture.json names")


class LevelImageReader:
    """Reads a photo at a pyramid level, as ``PhotoFiles.read_image`` does at full resolution: (path, rows,
    size) -> (H, W, 3) float32 with rows and size in the level's pixels."""

    def __init__(self, read_image, level: int):
        self.read_image, self.level = read_image, int(level)
        inner = getattr(read_image, "cache_key", None)  # a reader through a photo response names its curve
        self.cache_key = f"level{self.level}" if inner is None else f"{inner}-level{self.level}"
        """names the level in the decoded photos' cache key (fit/stream/photo_stream.PhotoCache)"""

    def __call__(self, path, rows=None, size=None) -> np.ndarray:
        s = 2 ** self.level
        full = self.read_image(path, rows=None if rows is None else (rows[0] * s, rows[1] * s))
        _check_level_size(path, full.shape[:2], size, self.level, rows)
        return box_average(full, self.level)


class LevelMaskReader:
    """Reads a mask at a pyramid level: a level pixel is object only where every pixel of its box is (the
    background's light must not leak into a texel's samples through the average)."""

    def __init__(self, read_mask, level: int):
        self.read_mask, self.level = read_mask, int(level)

    def __call__(self, path, shape=None, rows=None) -> np.ndarray:
        s = 2 ** self.level
        full = self.read_mask(path, None, rows=None if rows is None else (rows[0] * s, rows[1] * s))
        _check_level_size(path, full.shape[:2], shape, self.level, rows)
        h, w = full.shape[0] // s, full.shape[1] // s
        return full[: h * s, : w * s].reshape(h, s, w, s).all(axis=(1, 3))
