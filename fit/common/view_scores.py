"""Views of a per-texel model scored against their photos on the device: the materials choice renders its
validation photos once per candidate (fit/models/per_texel/lobes.py ``mesh_view_scores``).

What :func:`~texstream.fit.common.setup.heldout_psnr` does per view (a renderer built, the render copied back, the
error summed by numpy), with the renderer (the mesh's BVH, normals, output buffers) built once, the photos and
masks uploaded once, and each view's error summed where it was rendered (fit/kernels/view_error.py): for the
full ornament's 220 validation views of 430x430, 4 candidates made 880 BVH builds and copied 3.4 GB of renders
back: 8.7 s of the materials choice's 18 s on an H200, 0.5 s this way. The per-view PSNRs equal heldout_psnr's to
float rounding (the rows summed in another order).
"""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from texstream.fit.common.setup import ModelRenders
from texstream.fit.kernels.view_error import view_error_rows_kernel
from texstream.render.layout import ModelLayout


class ViewScores:
    """The PSNR of each of ``frames`` rendered from parameter maps against ``photos`` (foreground: the photo's
    ``masks`` and the render's coverage), for one map after another."""

    def __init__(self, mesh, layout: ModelLayout, frames, photos, masks, device: str):
        self.frames = list(frames)
        self.renders = ModelRenders(mesh, layout, device)
        self.device = device
        self.photos = [wp.array(np.ascontiguousarray(p[..., :3], np.float32), dtype=wp.vec3, device=device)
                       for p in photos]
        self.masks = [wp.array(np.ascontiguousarray(m, np.uint8), dtype=wp.uint8, device=device) for m in masks]
        height = max((p.shape[0] for p in self.photos), default=1)
        self.rows = wp.zeros((len(self.frames), height, 2), dtype=wp.float64, device=device)

    def psnr(self, grid: np.ndarray) -> list[float]:
        """Per view, the PSNR (peak 1) of ``grid``'s render; nan where no pixel is foreground."""
        self.renders.set_grid(grid)
        self.rows.zero_()
        for k, (frame, photo, mask) in enumerate(zip(self.frames, self.photos, self.masks)):
            radiance, coverage = self.renders.renderer.frame_on_device(frame)
            if radiance.shape != photo.shape:
                raise ValueError(f"view {k}: render {radiance.shape} and photo {photo.shape} differ in size")
            wp.launch(view_error_rows_kernel, dim=radiance.shape[0], device=self.device,
                      inputs=[radiance, coverage, photo, mask, float(frame.exposure), k], outputs=[self.rows])
        sums = self.rows.numpy().sum(axis=1)
        out = []
        for sse, count in sums:
            if count == 0:
                out.append(float("nan"))
                continue
            mse = sse / (3.0 * count)
            out.append(10 * math.log10(1.0 / mse) if mse > 0 else float("inf"))
        return out
