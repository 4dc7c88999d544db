"""Which photos see which tile of texels (fit/multi/tiles.py): the distribution step's acceptance test per
(photo, texel), reduced to a flag per (tile, photo)."""

from __future__ import annotations

from typing import Any

import warp as wp

from texstream.fit.kernels.overloads import IMAGE_PIXEL, declare
from texstream.fit.kernels.stream import SampleOptions, TexelFrames, observe_func, observe_with_unlit_func
from texstream.render.camera import ImageInfo


def tile_visibility_kernel_for(radiance: bool = False):
    """The tile-visibility kernel for reflectance models (``radiance`` False: light, cosine and shadow
    tests, an unlit photo's camera tests alone as the ambient layouts' passes take it,
    :func:`texstream.fit.kernels.stream.observe_with_unlit_func`) or the radiance models
    (:func:`texstream.fit.kernels.stream.observe_func`)."""
    obs = observe_func(True) if radiance else observe_with_unlit_func()

    def tile_visibility(tex: TexelFrames, images: wp.array3d(dtype=Any), depth: wp.array3d(dtype=wp.float32),
                        shadow: wp.array3d(dtype=wp.float32), infos: wp.array(dtype=ImageInfo), photo_begin: int,
                        photo_offset: int, opt: SampleOptions, tile_of_texel: wp.array(dtype=wp.int32),
                        seen: wp.array2d(dtype=wp.int32)):
        """seen[tile of texel i, photo_offset + k] = 1 when photo k (photo_begin + the launch's first index)
        of the window has a sample of texel i (every thread that writes writes 1: deterministic without
        atomics). A sample the passes use passes this test first, so the flags hold every photo a tile's
        passes read."""
        kk, i = wp.tid()
        k = photo_begin + kk
        ok, y, w, u, v, xs, ys = obs(images, depth, shadow, infos, k, tex, i, opt)
        if ok:
            seen[tile_of_texel[i], photo_offset + k] = 1

    kernel = wp.kernel(tile_visibility, name="tile_visibility_radiance" if radiance else "tile_visibility",
                       enable_backward=False, module="unique")
    declare(kernel, images=IMAGE_PIXEL)  # the default run's overload (fit/kernels/overloads.py)
    return kernel


tile_visibility_kernel = tile_visibility_kernel_for(False)
tile_visibility_radiance_kernel = tile_visibility_kernel_for(True)


@wp.kernel
def gather_rows_kernel(src: wp.array(dtype=Any), rows: wp.array(dtype=wp.int32), out: wp.array(dtype=Any)):
    """out[k] = src[rows[k]]: a tile's texels that other tiles hold as halo, packed for the copy."""
    k = wp.tid()
    out[k] = src[rows[k]]


@wp.kernel
def scatter_rows_kernel(values: wp.array(dtype=Any), rows: wp.array(dtype=wp.int32), dst: wp.array(dtype=Any)):
    """dst[rows[k]] = values[k]: the copied values into a tile's halo texels."""
    k = wp.tid()
    dst[rows[k]] = values[k]
