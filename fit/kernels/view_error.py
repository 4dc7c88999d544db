"""A rendered view's squared error against its photo, on the device: the materials choice scores every
candidate on the validation photos this way (fit/common/view_scores.py), so no render is copied back.

One thread per image row sums its row in order (float64), so the sums are the same on every run; the host
adds the rows of a view. The arithmetic per pixel is fit/common/model_folder.py ``image_metrics``'s: the
render times the exposure and the difference in float32, its square in float64.
"""

from __future__ import annotations

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.kernel
def view_error_rows_kernel(radiance: wp.array2d(dtype=wp.vec3), coverage: wp.array2d(dtype=wp.uint8),
                           photo: wp.array2d(dtype=wp.vec3), photo_mask: wp.array2d(dtype=wp.uint8),
                           exposure: wp.float32, view: int, rows: wp.array3d(dtype=wp.float64)):
    """``rows[view, y]`` = (sum of squared channel differences, foreground pixels) of row y: the foreground
    is the render's coverage and the photo's mask."""
    y = wp.tid()
    sse = wp.float64(0.0)
    count = wp.float64(0.0)
    for x in range(radiance.shape[1]):
        if coverage[y, x] != wp.uint8(0) and photo_mask[y, x] != wp.uint8(0):
            d = radiance[y, x] * exposure - photo[y, x]
            d0 = wp.float64(d[0])
            d1 = wp.float64(d[1])
            d2 = wp.float64(d[2])
            sse += d0 * d0 + d1 * d1 + d2 * d2
            count += wp.float64(1.0)
    rows[view, y, 0] = sse
    rows[view, y, 1] = count
