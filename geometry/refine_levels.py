"""The photometric refinement's photos at the resolution it needs (issue 40): a pyramid, coarse to fine, never
finer than the atlas's texels, and the fine levels only when the coarse one moved something.

The refinement compares every photo with one shared texture sampled at the texels' centres (geometry/refine.py):
pixels finer than a texel add depth-map and blur work (per pixel, the stage's cost at 6 megapixels) but no
sample. So its finest level is the coarsest pyramid level whose pixels are still no larger than the texels
(:func:`texstream.geometry.density.photo_level_for` at one pixel per texel, where the fit asks for two: the fit
samples a texel's light, the refinement the photos' gradients between texels), and each blur level of
``RefineConfig.blur`` runs on the level where its blur is the finest one's: blur 2, 1, 0.5 pixels of that
level become 0.5 pixel at two, one and zero levels above it (a box average and a half-pixel blur, about as
wide), each a quarter of the pixels of the next.

The first (coarsest) level is cheap. The finer levels run only when it moved a camera or the mesh by at least
``min_move`` pixels of the finest level (:func:`coarse_moved`); when it did not, the registration already
agrees with the photos to a fraction of a pixel there, and the finer levels, which only look closer, are
skipped with that reason in the summary. numpy and warp only.
"""

from __future__ import annotations

import math

import numpy as np

from texstream.capture.imageio import read_image, read_mask
from texstream.capture.pyramid import box_average, frame_at_level
from texstream.core.errors import InputError

from .bake import bake_texels
from .density import photo_level_for, pixel_footprints

MIN_LEVEL_SIDE = 64
"""a coarse level keeps every photo's short side at least this many pixels (a smaller photo holds too few
pixels of the object for a pose step)"""

REFINE_TEXEL_PIXELS = 1.0
"""``photo_level`` auto: the coarsest level whose texels stay at least this many of its pixels wide in the tenth
of the photos that see them smallest (the fit's is 2: fit/common/inputs.py)"""


def finest_level(mesh, bake, frames, requested: int) -> tuple[int, dict]:
    """(the pyramid level the refinement's finest level reads, why): ``requested`` when >= 0, else the coarsest
    whose pixels are no larger than the atlas's texels (see the module)."""
    side = float(np.sqrt(bake.width * bake.height))
    level, info = photo_level_for(mesh, frames, side, REFINE_TEXEL_PIXELS)
    first = frames[0].intrinsics
    if requested >= 0:
        level, why = requested, f"--refine.photo-level {requested}"
    elif info["texel_pixels"] is None:
        why = "auto: no photo sees the mesh; the photos as they are"
    else:
        why = (f"auto: texels {info['texel_pixels']:.2f} px wide at full resolution (the tenth of the photos that "
               f"see them smallest), at least {REFINE_TEXEL_PIXELS:g} px at level {level}")
    return level, dict(info, level=level, requested=requested, why=why,
                       size=[int(first.width) >> level, int(first.height) >> level])


def level_schedule(blurs: list[float], finest: int, frames, pyramid: bool) -> list[tuple[int, float]]:
    """(pyramid level, blur in that level's pixels) of each blur level (``blurs`` coarse to fine, in the finest
    level's pixels): with ``pyramid``, a blur k times the last one's runs log2(k) levels up (rounded down, the
    photos' short side kept at least :data:`MIN_LEVEL_SIDE`) at that blur over 2^levels; else every blur on the
    finest level."""
    short = min(min(int(f.intrinsics.width), int(f.intrinsics.height)) for f in frames)
    last = blurs[-1]
    out = []
    for sigma in blurs:
        up = int(math.floor(math.log2(sigma / last) + 1e-9)) if pyramid and last > 0 and sigma > last else 0
        while up > 0 and short >> (finest + up) < MIN_LEVEL_SIDE:
            up -= 1
        out.append((finest + up, sigma / 2 ** up))
    return out


def coarse_bake(mesh, bake, up: int, device: str):
    """The atlas's charts baked ``up`` levels coarser (texels 2^up times wider, a 4^up-th as many), for a level
    whose pixels are 2^up times the finest level's: every level samples the photos with as many texels per
    pixel as the finest, where the atlas's own would pay per-texel work for detail the level's pixels do not
    hold (a face too small for a texel centre still claims one: :func:`~.bake.bake_texels`)."""
    if up <= 0:
        return bake
    return bake_texels(mesh, max(bake.width >> up, 1), max(bake.height >> up, 1), device=device,
                       padding=bake.padding)


def _box_all(mask: np.ndarray, level: int) -> np.ndarray:
    """A mask at ``level`` levels up: a pixel is object where every pixel of its box is."""
    s = 2 ** level
    h, w = mask.shape[0] // s, mask.shape[1] // s
    return mask[: h * s, : w * s].reshape(h, s, w, s).all(axis=(1, 3))


class PhotoPyramid:
    """The photos and masks of a capture at the pyramid levels the refinement reads, each photo read once (host
    float32 images, bool masks: a level pixel is object where every pixel of its box is)."""

    def __init__(self, capture, levels):
        self.frames = list(capture.frames)
        self.levels = sorted(set(levels))
        self.images = {lv: [] for lv in self.levels}
        self.masks = {lv: [] for lv in self.levels}
        for f in self.frames:
            im = read_image(capture.image_path(f), channels=3, response=capture.response)
            h, w = im.shape[:2]
            if (w, h) != (int(f.intrinsics.width), int(f.intrinsics.height)):
                raise InputError(f"photo is {w}x{h}, its camera says {f.intrinsics.width}x{f.intrinsics.height}",
                                 capture.image_path(f), "re-run texstream register")
            mp = capture.mask_path(f)
            mk = read_mask(mp, (h, w)) if mp is not None and mp.exists() else np.ones((h, w), bool)
            done = 0
            for lv in self.levels:  # each level from the last one made: a box of boxes is the level's box
                im, mk = box_average(im, lv - done), _box_all(mk, lv - done)
                self.images[lv].append(im)
                self.masks[lv].append(mk)
                done = lv

    def frames_at(self, level: int) -> list:
        return [frame_at_level(f, level) for f in self.frames]

    def stacked(self, level: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(images (n, H, W, 3), masks (n, H, W) uint8, sizes (n, 2) as height, width) at ``level``, padded to
        the largest photo."""
        ims, mks = self.images[level], self.masks[level]
        sizes = np.array([im.shape[:2] for im in ims], np.int64)
        hmax, wmax = int(sizes[:, 0].max()), int(sizes[:, 1].max())
        images = np.zeros((len(ims), hmax, wmax, 3), np.float32)
        masks = np.zeros((len(ims), hmax, wmax), np.uint8)
        for i, (im, mk) in enumerate(zip(ims, mks)):
            images[i, : im.shape[0], : im.shape[1]] = im
            masks[i, : mk.shape[0], : mk.shape[1]] = mk
        return images, masks, sizes


def rescale_infos(infos: np.ndarray, sizes: np.ndarray, factor: float) -> np.ndarray:
    """The kernels' cameras (``ImageInfo`` records) at another level: intrinsics times ``factor`` (a power of
    two: exact), the level's image sizes; poses unchanged."""
    out = infos.copy()
    for key in ("fx", "fy", "cx", "cy"):
        out[key] = out[key] * np.float32(factor)
    out["height"], out["width"] = sizes[:, 0], sizes[:, 1]
    return out


def coarse_moved(job, start_frames, finest_frames, min_move: float) -> tuple[bool, dict]:
    """Whether the coarse level moved a camera or the mesh by at least ``min_move`` pixels of the finest level
    (rotation times the focal length, the centre's shift and the largest displacement over the pixel footprint
    at the object's median depth), and the movements in those pixels."""
    infos = job.infos.numpy()
    rot = np.asarray(infos["rot"], np.float64).reshape(-1, 3, 3)
    centres = -np.einsum("nji,nj->ni", rot, np.asarray(infos["trans"], np.float64).reshape(-1, 3))
    foot = pixel_footprints(job.mesh, finest_frames)  # scene units per finest-level pixel, per photo
    foot = np.where(np.isfinite(foot), foot, np.nanmedian(foot))
    rot_px, move_px = [], []
    for i, f in enumerate(start_frames):
        c = np.clip((np.trace(rot[i] @ np.asarray(f.R, float).T) - 1.0) / 2.0, -1.0, 1.0)
        rot_px.append(math.acos(c) * float(finest_frames[i].intrinsics.fx))
        move_px.append(float(np.linalg.norm(centres[i] - f.center)) / foot[i])
    disp_px = float(np.max(np.abs(job.disp.numpy()))) / float(np.min(foot)) if job.n_welded else 0.0
    moved = {"camera_rotation_px": max(rot_px), "camera_centre_px": max(move_px), "mesh_px": disp_px}
    return max(moved.values()) >= min_move, {k: round(v, 4) for k, v in moved.items()}
