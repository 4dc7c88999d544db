"""A dark, glossy object photographed with a flash in a dim, textured room: the case automatic masks get wrong.

A real bronze in a dim room fooled the border statistics (the room's dark walls look like a plain
background) and GrabCut kept what was distinct from that background, the bright wall, the window and the
flash highlights, as the object: the masks were inverted. This scene makes that case with ground truth.

The object (the ornament mesh, one material: albedo 0.01, a strong specular lobe, so only its flash highlights
stand out) is rendered by texstream's renderer with a point light at each camera, which also gives the true
object masks. The room is ray-cast here: an axis-aligned box around the object whose walls carry a dim
value-noise albedo lit by the flash (1/r^2) and a faint ambient light, with a lit wall panel and a window (far
brighter) on two walls. Each photo is the object where the renderer's mask says, the room elsewhere.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from texstream.capture.imageio import linear_to_srgb

from .materials import value_noise
from .synth import SynthConfig, load_scene, render_scene


@dataclasses.dataclass
class DimRoom:
    """What :func:`dim_room_photos` returns: ``images`` (sRGB in [0, 1], (H, W, 3) float32), ``masks`` (the
    renderer's object masks), ``frames`` (capture Frames: poses, intrinsics, lights)."""

    images: list
    masks: list
    frames: list


# (wall axis, wall side, (u0, u1, v0, v1) in the wall's coordinates [0, 1], radiance): a lit panel and a window
_PATCHES = ((0, 1.0, (0.3, 0.7, 0.35, 0.8), 0.35), (1, -1.0, (0.15, 0.45, 0.45, 0.9), 1.2))


def _room_radiance(origin: np.ndarray, dirs: np.ndarray, half: float, flash: float, ambient: float,
                   seed: int) -> np.ndarray:
    """Linear RGB radiance of the room's walls seen along ``dirs`` (N, 3) from ``origin`` inside the box
    [-half, half]^3: value-noise albedo (0.02-0.12, slightly warm) lit by the flash at the camera (cosine,
    1/r^2) and a faint ambient, plus the bright patches of :data:`_PATCHES`."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t_axis = np.where(dirs != 0, (np.sign(dirs) * half - origin) / dirs, np.inf)
    axis = np.argmin(t_axis, axis=1)
    t = t_axis[np.arange(len(dirs)), axis]
    hit = origin + dirs * t[:, None]
    side = np.sign(hit[np.arange(len(dirs)), axis])
    # wall coordinates: the other two axes, in [0, 1]
    others = np.array([[1, 2], [0, 2], [0, 1]])[axis]
    uv = (np.take_along_axis(hit, others, 1) / half + 1) / 2
    wall = axis * 2 + (side > 0)
    noise = value_noise(uv[:, 0] * 0.5 + 0.5 * (wall % 2), uv[:, 1], (24, 12), octaves=3, seed=seed + 7)
    albedo = 0.07 + 0.05 * noise
    cos = np.abs(dirs[np.arange(len(dirs)), axis]) / np.linalg.norm(dirs, axis=1)
    rad = albedo * (flash * cos / np.maximum(t * np.linalg.norm(dirs, axis=1), 1e-6) ** 2 / np.pi + ambient)
    out = rad[:, None] * np.array([1.0, 0.93, 0.82])
    for ax, sd, (u0, u1, v0, v1), level in _PATCHES:
        on = (axis == ax) & (side == sd) & (uv[:, 0] >= u0) & (uv[:, 0] <= u1) & (uv[:, 1] >= v0) & (uv[:, 1] <= v1)
        out[on] = level * np.array([1.0, 0.97, 0.9]) * (1 + 0.1 * noise[on, None])
    return out


def dim_room_photos(count: int = 8, size: int | tuple[int, int] = 160, seed: int = 0, device: str = "cpu") -> DimRoom:
    """``count`` photos (``size``: width and height, or one side of a square; a ring at 15 degrees
    elevation) of the dark glossy ornament in the dim room, with the renderer's object masks."""
    sc = load_scene("ornament")
    sc["materials"] = {"bronze": {"rho_d": [0.012, 0.009, 0.006],
                                  "lobes": [{"rho_s": [0.9, 0.75, 0.5], "c_z": 1.0, "n": 40}]}}
    sc["assignment"] = {"rule": "uniform", "material": "bronze"}
    w, h = (size, size) if isinstance(size, int) else size
    sc["cameras"] = {"layout": "ring", "count": int(count), "rings": [15.0], "distance": 4.5, "fov_deg": 40.0 * w / h,
                     "width": int(w), "height": int(h), "target": [0.0, 0.0, 0.15]}
    flash = 30.0
    sc["light"] = {"type": "point", "mode": "camera", "offset": [0.0, 0.0, 0.0], "intensity": flash}
    sc["texture"] = {"width": 220, "height": 110, "padding": 2}
    res = render_scene(sc, SynthConfig(progress=False, bits=32, shadows=False, device=device))
    images = []
    for f, img, m in zip(res.frames, res.images, res.masks):
        h, w = m.shape
        j, i = np.mgrid[0:h, 0:w]
        pix = np.stack([i.ravel() + 0.5, j.ravel() + 0.5, np.ones(h * w)], 1)
        dirs = (pix @ np.linalg.inv(f.intrinsics.matrix()).T) @ np.asarray(f.R)
        room = _room_radiance(np.asarray(f.center, np.float64), dirs, 9.0, flash, 0.12, seed).reshape(h, w, 3)
        lin = np.where(m[..., None], img, room).astype(np.float32)
        images.append(np.clip(linear_to_srgb(np.clip(lin, 0, 1)), 0, 1).astype(np.float32))
    return DimRoom(images=images, masks=list(res.masks), frames=list(res.frames))
