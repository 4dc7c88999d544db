"""View-map taps of many local directions at once (the LFM export's mean over view directions).

Uses ``view_taps`` of fit/kernels/lfm.py, so the export averages exactly the lookups the renderer
and the fit make.
"""

from __future__ import annotations

import warp as wp

from texstream.fit.kernels import lfm as LK

wp.set_module_options({"enable_backward": False})


@wp.kernel
def direction_taps_kernel(dirs: wp.array(dtype=wp.vec3d), mapping: int, res: int, lookup: int,
                          tap_idx: wp.array(dtype=wp.vec4i), tap_w: wp.array(dtype=wp.vec4d)):
    """One thread per local direction (z = the vertex normal): its view-map texels and weights."""
    i = wp.tid()
    idx, wt = LK.view_taps(dirs[i], mapping, res, lookup)
    tap_idx[i] = idx
    tap_w[i] = wt
