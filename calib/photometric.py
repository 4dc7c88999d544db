"""Photometric consistency: per-photo exposure and white-balance gains from shared surface points.

Every SfM point seen in several photos is one surface point observed under (nearly) the same
light; for a roughly diffuse surface its colour differs between photos only by each photo's
exposure and white balance: ``I[i, p, c] = g[i, c] * L[p, c]``. The gains are estimated in the log
domain by alternating medians (robust to speculars, occlusion and mismatches), with the median
photo as reference (gain 1). Applied as ``exposure *= luminance gain`` and exported per channel, so
the fit sees the brightness jumps users complain about in texture tools as known exposure.
"""

from __future__ import annotations

from typing import Any

import numpy as np


def estimate_gains(image_idx: np.ndarray, point_idx: np.ndarray, values: np.ndarray, n_images: int,
                   iters: int = 20) -> tuple[np.ndarray, np.ndarray]:
    """Robust per-image, per-channel gains from repeated observations of points.

    Args:
        image_idx: (M,) int, photo of each observation.
        point_idx: (M,) int, point of each observation.
        values: (M, C) float, observed linear values (> 0; non-positive ones are ignored).
        n_images: number of photos.
        iters: alternating-median rounds.

    Returns:
        gains (n_images, C) with median 1 over the photos that have observations (others 1), and
        the number of observations used per photo (n_images,).
    """
    image_idx = np.asarray(image_idx, dtype=np.int64)
    point_idx = np.asarray(point_idx, dtype=np.int64)
    v = np.asarray(values, dtype=np.float64)
    if v.ndim == 1:
        v = v[:, None]
    ok = np.all(v > 0, axis=1)
    # Points seen in one photo only say nothing about gains.
    _, inv, counts = np.unique(point_idx[ok], return_inverse=True, return_counts=True)
    keep = np.flatnonzero(ok)[counts[inv] >= 2]
    ii, pp, lv = image_idx[keep], point_idx[keep], np.log(v[keep])
    _, pp = np.unique(pp, return_inverse=True)
    n_pts = int(pp.max()) + 1 if len(pp) else 0
    c = lv.shape[1]
    log_g = np.zeros((n_images, c))
    used = np.bincount(ii, minlength=n_images)
    if n_pts == 0:
        return np.ones((n_images, c)), used
    for _ in range(iters):
        log_l = _group_median(pp, lv - log_g[ii], n_pts)
        new = _group_median(ii, lv - log_l[pp], n_images)
        new[used == 0] = 0.0
        has = used > 0
        new[has] -= np.median(new[has], axis=0)
        if np.max(np.abs(new - log_g)) < 1e-7:
            log_g = new
            break
        log_g = new
    return np.exp(log_g), used


def _group_median(groups: np.ndarray, x: np.ndarray, n: int) -> np.ndarray:
    """Per-group median of rows of x (M, C) -> (n, C); empty groups get 0 (vectorised: sort by group then value)."""
    out = np.zeros((n, x.shape[1]))
    counts = np.bincount(groups, minlength=n)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    for ch in range(x.shape[1]):
        order = np.lexsort((x[:, ch], groups))
        xs = x[order, ch]
        has = counts > 0
        lo = starts[has] + (counts[has] - 1) // 2
        hi = starts[has] + counts[has] // 2
        out[has, ch] = 0.5 * (xs[lo] + xs[hi])
    return out


def observations_from_model(rec: Any, images: dict[str, np.ndarray], masks: dict[str, np.ndarray] | None = None,
                            saturation: dict[str, float | None] | None = None):
    """Sample every photo at its SfM observations (bilinear).

    Args:
        rec: pycolmap.Reconstruction (its image names are the keys of ``images``).
        images: name -> (H, W, C) linear float image, in the model's (distorted) pixel frame.
        masks: name -> (H, W) bool object mask (observations on the background are dropped).
        saturation: name -> clip level (observations with any channel at/above it are dropped).

    Returns:
        (image_idx (M,), point_idx (M,), values (M, C), names list indexed by image_idx).
    """
    names = sorted(images)
    ii, pp, vals = [], [], []
    for k, name in enumerate(names):
        im = rec.find_image_with_name(name)
        if im is None or not im.has_pose:
            continue
        pts = [(p.xy, p.point3D_id) for p in im.points2D if p.has_point3D()]
        if not pts:
            continue
        xy = np.array([p[0] for p in pts], dtype=np.float64) - 0.5  # COLMAP pixel centres at +0.5
        pid = np.array([p[1] for p in pts], dtype=np.int64)
        img = images[name]
        h, w = img.shape[:2]
        x0 = np.clip(np.floor(xy[:, 0]).astype(int), 0, w - 2)
        y0 = np.clip(np.floor(xy[:, 1]).astype(int), 0, h - 2)
        fx = np.clip(xy[:, 0] - x0, 0, 1)[:, None]
        fy = np.clip(xy[:, 1] - y0, 0, 1)[:, None]
        v = (img[y0, x0] * (1 - fx) * (1 - fy) + img[y0, x0 + 1] * fx * (1 - fy)
             + img[y0 + 1, x0] * (1 - fx) * fy + img[y0 + 1, x0 + 1] * fx * fy)
        good = np.ones(len(v), dtype=bool)
        if masks and masks.get(name) is not None:
            good &= masks[name][np.clip(np.round(xy[:, 1]).astype(int), 0, h - 1),
                                np.clip(np.round(xy[:, 0]).astype(int), 0, w - 1)]
        sat = (saturation or {}).get(name)
        if sat is not None:
            good &= np.all(img[y0, x0] < sat, axis=1)
        ii.append(np.full(good.sum(), k))
        pp.append(pid[good])
        vals.append(v[good])
    if not ii:
        return np.zeros(0, int), np.zeros(0, int), np.zeros((0, 3)), names
    return np.concatenate(ii), np.concatenate(pp), np.concatenate(vals), names
