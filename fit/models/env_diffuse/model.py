"""The env_diffuse model as radiance: albedo x (T . L) per atlas texel, rendered by texstream's renderer as a
radiance map (render/renderer.py, layout kind "radiance"), under the fitted light or any other."""

from __future__ import annotations

import numpy as np

from texstream.render.layout import ModelLayout
from texstream.render.renderer import Renderer

ENV_MAP_SIZE = (32, 64)
"""(height, width) of the latitude-longitude map written for an SH light (order 2 has no finer detail)"""


def transfer_grid(bake, grid_index: np.ndarray, transfer: np.ndarray) -> np.ndarray:
    """(H, W, 9) the compact texels' transfer vectors on the atlas, padding copied from its source texels."""
    flat = np.zeros((bake.height * bake.width, transfer.shape[1]), np.float32)
    flat[np.asarray(grid_index, np.int64)] = transfer
    return bake.fill_padding(flat.reshape(bake.height, bake.width, -1))


def lit_radiance(albedo: np.ndarray, transfer: np.ndarray, light: np.ndarray) -> np.ndarray:
    """(H, W, 3) albedo (H, W, 3) lit by the SH light (9, 3) through transfer (H, W, 9); an order-2 light can dip
    below 0 in directions it barely lights, and radiance cannot: clamped at 0."""
    return np.maximum(np.asarray(albedo, np.float64) * (np.asarray(transfer, np.float64) @ light), 0.0)


class EnvDiffuseRenderer:
    """Frames -> (image x the frame's exposure, coverage) of the model under ``light`` (9, 3); the renderer (the
    mesh's BVH) is built once, :meth:`set_light` relights it."""

    def __init__(self, mesh, albedo: np.ndarray, transfer: np.ndarray, light: np.ndarray, device: str = "cpu"):
        self.albedo, self.transfer = albedo, transfer
        # the radiance layout, made here: its kind is registered by the radiance plugin, loaded after this one
        self.renderer = Renderer(mesh, lit_radiance(albedo, transfer, light).astype(np.float32),
                                 ModelLayout(kind="radiance"), device=device)

    def set_light(self, light: np.ndarray) -> None:
        grid = lit_radiance(self.albedo, self.transfer, light).reshape(-1, 3)
        self.renderer.params.assign(np.ascontiguousarray(grid, dtype=np.float32))

    def render(self, frame) -> tuple[np.ndarray, np.ndarray]:
        res = self.renderer.render_frame(frame)
        return res.radiance * np.float32(frame.exposure), res.mask
