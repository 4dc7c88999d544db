"""Automatic object masks from photos of an object on a plain (dark or uniform) background.

For each photo (read linear, shown as sRGB so dark shadows and a black background are told apart the
way an eye does):

1. **Background colour from the border.** The outer strip of the photo (``border`` of the shorter
   side) gives the background's median colour and the colour distance ``d`` of every pixel to it
   (largest channel difference, sRGB 0-1). A border is *uniform* when at least ``uniform_fraction``
   of its pixels lie within ``tolerance`` of that colour (the object may leave the frame on a side).
2. **Threshold** (mode ``border``): object where ``d`` exceeds the background's own spread (99th
   percentile of the border's inliers plus a margin, at least ``min_threshold``).
3. **GrabCut** (mode ``grabcut``, OpenCV ``cv2.grabCut`` with a mask initialisation): sure background
   = the border strip's background-coloured pixels and everything far from any candidate object
   pixel; probable object / background = the threshold; sure object = the clearly distinct
   pixels of the kept components and the photo's SfM points (projected 3D points observed in that
   photo, when given), so dark object parts that touch seeds stay object.
4. **Clean-up**: grow the outline by up to two pixels into pixels above a lower threshold (the
   background's spread plus a small margin: the dark rim of a convex object); keep the largest component and those at least ``keep_fraction`` of its area (or
   holding an SfM point); fill a hole only when it is tiny, does not look like the background
   (a dark shadow region of the object) or holds an SfM point. Background-coloured holes stay open:
   the gaps between the Middlebury temple's columns are real.

``auto`` decides from the data: masks are made (with GrabCut) only when most photos have a uniform
border and show something distinct from it; otherwise none, and the reason is recorded.

**Judged, and undone when doubtful.** A dark object in a dim room passes the border test (its walls look
like a plain background) and what is distinct from that background is the lit wall, a window and the
flash highlights: masks that keep the background and drop the object. So every mask is judged against what
the data say (:func:`doubt`): a mask holding much of the photo's border strip, or nearly the whole photo,
or lying mostly at one near-white patch (a highlight or a window), or (with SfM points) missing most of
the outline of the photo's object points is doubtful; and the masks' areas varying across the photos far
more than an object's silhouette does make them all doubtful. More than ``max_doubtful`` of them
doubtful: no automatic masks at all (what misled those is in the others too); fewer: those photos go
without. The decision and its reason are printed in one line and recorded (``doubtful`` per photo).

:func:`masks_for_images` works on arrays (ingest calls it); :func:`make_masks` runs on an existing
capture folder (after registration it seeds GrabCut with the SfM points of ``sparse/0``) and writes
``masks/NAME.png``, each frame's ``mask_path``, ``masks_report.json`` and a reviewable contact sheet
``previews/masks.png`` (mask outlines drawn on the photos).
"""

from __future__ import annotations

import dataclasses
import os
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from texstream.capture.capture_json import read_capture, write_capture
from texstream.capture.imageio import linear_to_srgb, read_image, write_image
from texstream.capture.preview import write_contact_sheet
from texstream.core.config import option
from texstream.core.errors import ConfigError, InputError
from texstream.core.outputs import StageResult, write_json_atomic
from texstream.core.progress import bar, say

MASK_MODES = ("auto", "none", "border", "grabcut")
REPORT_FILE = "masks_report.json"
PREVIEW_FILE = "previews/masks.png"


@dataclasses.dataclass
class MaskConfig:
    """Options of automatic object masks."""

    mode: str = option("auto", help="auto (GrabCut masks when the photos' borders show a uniform background, "
                       "else none), none, border (threshold against the border's colour), grabcut "
                       "(threshold refined by GrabCut)", choices=MASK_MODES)
    border: float = option(0.03, help="width of the border strip that samples the background, as a fraction "
                           "of the photo's shorter side")
    tolerance: float = option(0.15, help="colour distance (sRGB, 0-1, largest channel difference) within which a "
                              "border pixel counts as background colour")
    uniform_fraction: float = option(0.7, help="a border is uniform when at least this fraction of its pixels lie "
                                     "within --tolerance of its median colour")
    min_threshold: float = option(0.06, help="smallest object/background colour distance (sRGB 0-1)")
    keep_fraction: float = option(0.05, help="keep object components of at least this fraction of the largest one")
    min_object_fraction: float = option(0.002, help="a photo whose object covers less than this fraction gets no mask")
    grabcut_iterations: int = option(4, help="GrabCut iterations")
    max_size: int = option(1024, help="masks are computed on a copy downscaled to this longest side "
                           "(then upsampled with GrabCut's edges kept by a final threshold at full size)")
    grabcut_size: int = option(1024, help="GrabCut runs on a copy downscaled to this longest side (its cost grows "
                               "with the pixel count: 3 s for a 1024 x 683 photo, 0.4 s at 512 x 341); its outline "
                               "then gains the distinct pixels within a few pixels of it at the working size. 1024 "
                               "(the working size: no second downscale) because 512 changed the Middlebury temple's "
                               "masks by 1-3% (IoU 0.97-0.99) and cost its run 0.56 dB held out (24.67 against 25.23 "
                               "dB); 512 is the faster choice for large photos")
    max_border_fraction: float = option(0.3, help="a mask holding more than this fraction of the photo's border strip "
                                        "is doubtful (it keeps the background: an object leaving the frame on one "
                                        "side holds a quarter of it or less)")
    max_mask_fraction: float = option(0.9, help="a mask covering more than this fraction of the photo is doubtful")
    max_highlight_fraction: float = option(0.5, help="a mask whose pixels lie mostly near its largest near-white patch "
                                           "(sRGB 0.95 or more in a channel; within 1.5 radii of its area), in one "
                                           "convex part (95% of its convex hull or more), is doubtful: the flash "
                                           "highlight of a dark object or a window, not the object")
    min_points_inside: float = option(0.5, help="with SfM points: a mask holding less than this fraction of the "
                                      "outline (convex hull) of the photo's object points is doubtful")
    max_area_variation: float = option(0.5, help="the masks' areas (fraction of the photo) varying across the "
                                       "photos by more than this coefficient of variation make them all doubtful: "
                                       "an object seen all round keeps its size within about 2x (0.3), a window "
                                       "or a lit wall entering and leaving the frame does not")
    max_doubtful: float = option(0.25, help="more than this fraction of doubtful masks: no automatic masks for "
                                 "any photo (what misled the doubtful ones is in the others too); fewer: only the "
                                 "doubtful photos go without")

    def validate(self) -> None:
        if self.mode not in MASK_MODES:
            raise ConfigError(f"mask mode {self.mode!r} unknown", fix=f"use one of {MASK_MODES}")
        if not 0 < self.border < 0.5 or not 0 < self.uniform_fraction <= 1 or not self.tolerance > 0:
            raise ConfigError(f"mask border {self.border}, uniform fraction {self.uniform_fraction}, tolerance "
                              f"{self.tolerance} out of range", fix="use 0 < border < 0.5, 0 < fraction <= 1, "
                              "tolerance > 0")


# ---------------------------------------------------------------------------------------------- per photo


def display_image(img: np.ndarray, eight_bit_codes: bool = False) -> np.ndarray:
    """(H, W, 3) float32 sRGB-encoded in [0, 1] from a linear photo; HDR photos are scaled so their
    99.5th percentile is 1 first. ``eight_bit_codes``: the input is already sRGB in [0, 1]."""
    a = np.asarray(img, dtype=np.float32)
    if a.ndim == 2:
        a = a[:, :, None]
    a = a[:, :, :3] if a.shape[2] >= 3 else np.repeat(a[:, :, :1], 3, axis=2)
    if eight_bit_codes:
        return np.clip(a, 0.0, 1.0)
    hi = float(np.percentile(a, 99.5))
    if hi > 1.0:
        a = a / np.float32(hi)
    return np.clip(linear_to_srgb(np.clip(a, 0.0, 1.0)), 0.0, 1.0).astype(np.float32)


def _border_width(h: int, w: int, frac: float) -> int:
    return max(2, int(round(frac * min(h, w))))


def _border_band(h: int, w: int, b: int) -> np.ndarray:
    band = np.zeros((h, w), bool)
    band[:b] = band[-b:] = True
    band[:, :b] = band[:, -b:] = True
    return band


def border_stats(disp: np.ndarray, cfg: MaskConfig) -> dict:
    """Background statistics of a display image's border strip.

    Returns:
        dict: ``color`` (median sRGB), ``uniform_fraction`` (border pixels within ``tolerance``),
        ``uniform`` (bool), ``spread`` (99th percentile of the inliers' distance), ``threshold`` (the
        object/background distance used), ``object_fraction`` (pixels beyond the threshold).
    """
    h, w = disp.shape[:2]
    band = _border_band(h, w, _border_width(h, w, cfg.border))
    px = disp[band]
    color = np.median(px, axis=0)
    d_border = np.abs(px - color).max(1)
    inl = d_border <= cfg.tolerance
    frac = float(inl.mean())
    spread = float(np.percentile(d_border[inl], 99)) if inl.any() else float(cfg.tolerance)
    thr = float(max(cfg.min_threshold, spread + 0.03))
    d = np.abs(disp - color).max(2)
    return {"color": [round(float(c), 4) for c in color], "uniform_fraction": round(frac, 4),
            "uniform": frac >= cfg.uniform_fraction, "spread": round(spread, 4), "threshold": round(thr, 4),
            "object_fraction": round(float((d > thr).mean()), 4)}


def _components(mask: np.ndarray) -> tuple[int, np.ndarray, np.ndarray]:
    import cv2

    n, lab, st, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    return n, lab, st


def clean_mask(mask: np.ndarray, d: np.ndarray, thr: float, seeds: np.ndarray | None, cfg: MaskConfig) -> np.ndarray:
    """Largest components kept, small / object-coloured / seeded holes filled (see the module doc)."""
    import cv2

    h, w = mask.shape
    n, lab, st = _components(mask)
    if n <= 1:
        return mask.copy()
    areas = st[1:, cv2.CC_STAT_AREA]
    keep = areas >= cfg.keep_fraction * areas.max()
    if seeds is not None and seeds.any():
        seeded = np.unique(lab[seeds & mask])
        keep[seeded[seeded > 0] - 1] = True
    out = np.isin(lab, np.flatnonzero(keep) + 1)
    # Holes: background components that do not touch the photo's edge.
    n, lab, st = _components(~out)
    edge = np.unique(np.concatenate([lab[0], lab[-1], lab[:, 0], lab[:, -1]]))
    tiny = max(16, int(2e-4 * h * w))
    near_seed = None if seeds is None else cv2.dilate(seeds.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    for k in range(1, n):
        if k in edge:
            continue
        hole = lab == k
        area = int(st[k, cv2.CC_STAT_AREA])
        if area <= tiny or float(np.median(d[hole])) > thr or (near_seed is not None and bool((near_seed & hole).any())):
            out |= hole
    return out


def _grow(mask: np.ndarray, d: np.ndarray, low: float, steps: int) -> np.ndarray:
    """Hysteresis at the outline: add neighbours of the mask above the lower threshold ``low``, at most
    ``steps`` pixels out (the dark rim of a convex object seen at grazing angles)."""
    import cv2

    out = mask.copy()
    k = np.ones((3, 3), np.uint8)
    for _ in range(steps):
        out |= (cv2.dilate(out.astype(np.uint8), k) > 0) & (d > low)
    return out


def _grabcut(disp: np.ndarray, gc: np.ndarray, d: np.ndarray, thr: float, cfg: MaskConfig) -> np.ndarray:
    """GrabCut's object pixels for a display image and its initial labels (modified), run on a copy
    downscaled to ``cfg.grabcut_size``: its cost grows with the pixel count (3 s at 1024 x 683, 0.4 s at
    512 x 341). Upsampled, the outline gains the pixels of a band a few pixels wide whose colour distance
    ``d`` exceeds the threshold ``thr`` (detail the small copy lost); sure labels (GC_BGD / GC_FGD) stay.
    On a dark object on black at 1086 x 724 the mask's IoU with the truth is 0.980 (0.986 with GrabCut at
    full size): the difference is the object's grazing rim, as dark as the background."""
    import cv2

    h, w = d.shape
    g = min(1.0, cfg.grabcut_size / max(h, w))
    small = disp if g == 1.0 else cv2.resize(disp, (max(1, round(w * g)), max(1, round(h * g))),
                                              interpolation=cv2.INTER_AREA)
    labels = gc if g == 1.0 else cv2.resize(gc, small.shape[1::-1], interpolation=cv2.INTER_NEAREST)
    code = np.ascontiguousarray(np.clip(small * 255 + 0.5, 0, 255).astype(np.uint8)[:, :, ::-1])
    bgd, fgd = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
    cv2.setRNGSeed(0)
    cv2.grabCut(code, labels, None, bgd, fgd, int(cfg.grabcut_iterations), cv2.GC_INIT_WITH_MASK)
    fg = (labels == cv2.GC_FGD) | (labels == cv2.GC_PR_FGD)
    if g == 1.0:
        return fg
    up = cv2.resize(fg.astype(np.float32), (w, h), interpolation=cv2.INTER_LINEAR) > 0.5
    r = int(np.ceil(1.0 / g)) + 1
    k = np.ones((2 * r + 1, 2 * r + 1), np.uint8)
    out = up | ((cv2.dilate(up.astype(np.uint8), k) > 0) & (d > thr))
    out[gc == cv2.GC_BGD] = False
    out[gc == cv2.GC_FGD] = True
    return out


def _judge_metrics(mask: np.ndarray, disp: np.ndarray, info: dict, cfg: MaskConfig, points: np.ndarray | None) -> None:
    """What :func:`doubt` judges a mask by, into ``info``: ``border_fraction`` (of the photo's border strip
    inside the mask), ``highlight_fraction`` (of the mask's pixels near its largest near-white patch) and
    ``highlight_convexity`` (area over convex hull of the mask's part holding that patch),
    ``points_inside`` (of the outline (convex hull) of the photo's SfM object points inside the mask, when
    given)."""
    import cv2

    h, w = mask.shape
    band = _border_band(h, w, _border_width(h, w, cfg.border))
    info["border_fraction"] = round(float(mask[band].mean()), 4)
    n, lab, st = _components(mask & (disp.max(2) >= 0.95))
    info["highlight_fraction"] = 0.0
    if n > 1:
        # the mask's pixels near its largest near-white patch (within 1.5 radii of its area): nearly all of a
        # mask that is a flash highlight and its halo on a dark object, or a window (0.86-0.99 in the dim-room
        # scene); little of a white object with scattered clipped spots (Middlebury temple and dino: <= 0.21)
        core = lab == 1 + int(np.argmax(st[1:, cv2.CC_STAT_AREA]))
        dist = cv2.distanceTransform((~core).astype(np.uint8), cv2.DIST_L2, 3)
        radius = float(np.sqrt(core.sum() / np.pi))
        info["highlight_fraction"] = round(float((dist[mask] <= 1.5 * radius + 1.0).mean()), 4)
        # and how convex the mask's part around it is (area over its convex hull's): a highlight's halo or a
        # window is one convex patch (>= 0.998 in the dim-room scene); the temple's colonnade with its
        # clipped front face 0.67-0.80, the dino 0.83-0.94
        n, lab, _ = _components(mask)
        part = (lab == int(np.bincount(lab[core]).argmax())).astype(np.uint8)
        hull = cv2.contourArea(cv2.convexHull(cv2.findNonZero(part)))
        info["highlight_convexity"] = round(float(part.sum() / max(hull, 1.0)), 4)
    if points is not None and len(points) >= 3:
        # the outline of the photo's object points, not the points themselves: they seed GrabCut as sure
        # object, so they are inside any mask; their outline is the object's (less the gaps of a concave one)
        hull = np.zeros((h, w), np.uint8)
        cv2.fillConvexPoly(hull, cv2.convexHull(np.round(points).astype(np.int32)), 1)
        hull = hull > 0
        if hull.sum() >= 16:
            info["points_inside"] = round(float(mask[hull].mean()), 4)


def doubt(info: dict, cfg: MaskConfig) -> str | None:
    """Why a photo's mask is doubtful (from :func:`compute_mask`'s info), or None when nothing says so."""
    if info.get("border_fraction", 0.0) > cfg.max_border_fraction:
        return (f"the mask holds {100 * info['border_fraction']:.0f}% of the photo's border (more than "
                f"{100 * cfg.max_border_fraction:.0f}%): it keeps the background")
    if info.get("mask_fraction", 0.0) > cfg.max_mask_fraction:
        return f"the mask covers {100 * info['mask_fraction']:.0f}% of the photo"
    if info.get("highlight_fraction", 0.0) > cfg.max_highlight_fraction and info.get("highlight_convexity", 1.0) > 0.95:
        return (f"{100 * info['highlight_fraction']:.0f}% of the mask lies at its largest near-white patch: a "
                "highlight or a window, not the object (a dark object on a dark background?)")
    if info.get("points_inside", 1.0) < cfg.min_points_inside:
        return f"the mask holds only {100 * info['points_inside']:.0f}% of the outline of the photo's SfM object points"
    return None


def compute_mask(img: np.ndarray, cfg: MaskConfig | None = None, mode: str | None = None,
                 points: np.ndarray | None = None, eight_bit_codes: bool = False) -> tuple[np.ndarray | None, dict]:
    """The object mask of one photo.

    Args:
        img: (H, W, C) linear photo (or sRGB codes in [0, 1] with ``eight_bit_codes``).
        cfg: options.
        mode: ``border`` or ``grabcut`` (default: ``grabcut`` unless cfg.mode is ``border``).
        points: (N, 2) pixel coordinates of the object's SfM points in this photo (x, y; pixel centres
            at +0.5), sure-object seeds for GrabCut (filter background points out first, as
            :func:`sfm_points_per_image` does).
        eight_bit_codes: see :func:`display_image`.

    Returns:
        ((H, W) bool mask or None, info dict with the border statistics, ``mode`` and ``reason`` when
        no mask).
    """
    import cv2

    cfg = cfg or MaskConfig()
    mode = mode or ("border" if cfg.mode == "border" else "grabcut")
    disp_full = display_image(img, eight_bit_codes)
    H, W = disp_full.shape[:2]
    s = min(1.0, cfg.max_size / max(H, W))
    disp = disp_full if s == 1.0 else cv2.resize(disp_full, (max(1, round(W * s)), max(1, round(H * s))),
                                                  interpolation=cv2.INTER_AREA)
    h, w = disp.shape[:2]
    st = border_stats(disp, cfg)
    info: dict[str, Any] = {"mode": mode, **st}
    color = np.asarray(st["color"], np.float32)
    thr = st["threshold"]
    d = np.abs(disp - color).max(2)
    cand = d > thr
    if cand.mean() < cfg.min_object_fraction:
        info["reason"] = f"nothing distinct from the background ({100 * cand.mean():.2f}% of pixels beyond {thr:.2f})"
        return None, info
    seeds = None
    if points is not None and len(points):
        p = np.asarray(points, np.float64).reshape(-1, 2) * s
        ij = np.floor(p).astype(int)
        ok = (ij[:, 0] >= 0) & (ij[:, 0] < w) & (ij[:, 1] >= 0) & (ij[:, 1] < h)
        seeds = np.zeros((h, w), bool)
        seeds[ij[ok, 1], ij[ok, 0]] = True
        info["seed_points"] = int(ok.sum())
    base = clean_mask(cand, d, thr, seeds, cfg)
    if mode == "border":
        out = base
    else:
        b = _border_width(h, w, cfg.border)
        gc = np.where(cand, cv2.GC_PR_FGD, cv2.GC_PR_BGD).astype(np.uint8)
        # Sure background: far from every candidate object pixel, and the border strip's background pixels.
        near = base if seeds is None else base | seeds
        far = cv2.distanceTransform((~near).astype(np.uint8), cv2.DIST_L2, 3) > max(4.0, 0.04 * min(h, w))
        gc[far] = cv2.GC_BGD
        gc[_border_band(h, w, b) & ~cand] = cv2.GC_BGD
        # Sure object: clearly distinct pixels inside the kept components (eroded), and SfM seeds.
        sure = cv2.erode((base & (d > min(0.9, 2 * thr))).astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
        gc[sure] = cv2.GC_FGD
        if seeds is not None:
            gc[seeds] = cv2.GC_FGD
        fg_any = (gc == cv2.GC_FGD) | (gc == cv2.GC_PR_FGD)
        bg_any = (gc == cv2.GC_BGD) | (gc == cv2.GC_PR_BGD)
        if fg_any.sum() < 10 or bg_any.sum() < 10:
            out = base
            info["grabcut"] = "skipped (too few object or background samples)"
        else:
            fg = _grabcut(disp, gc, d, thr, cfg)
            out = clean_mask(fg, d, thr, seeds, cfg)
    out = _grow(out, d, max(0.5 * thr, st["spread"] + 0.015), steps=2)
    _judge_metrics(out, disp, info, cfg, None if points is None else np.asarray(points, np.float64).reshape(-1, 2) * s)
    if s != 1.0:
        out = cv2.resize(out.astype(np.float32), (W, H), interpolation=cv2.INTER_LINEAR) > 0.5
    frac = float(out.mean())
    info["mask_fraction"] = round(frac, 4)
    if frac < cfg.min_object_fraction:
        info["reason"] = f"object covers only {100 * frac:.2f}% of the photo"
        return None, info
    return out, info


def decide_auto(stats: Sequence[dict], cfg: MaskConfig) -> tuple[bool, str]:
    """Whether ``auto`` makes masks for a capture, from its photos' border statistics, and why."""
    n = len(stats)
    if n == 0:
        return False, "no photos"
    uni = [s for s in stats if s["uniform"]]
    med = float(np.median([s["uniform_fraction"] for s in stats]))
    if len(uni) < max(1, 0.5 * n):
        return False, (f"background not uniform: {len(uni)}/{n} photo border(s) have >= {100 * cfg.uniform_fraction:.0f}% "
                       f"of their pixels within {cfg.tolerance:g} of one colour (median {100 * med:.0f}%); "
                       "not an object on a plain background, so no automatic masks")
    obj = [s for s in uni if s["object_fraction"] >= cfg.min_object_fraction]
    if len(obj) < max(1, 0.5 * n):
        return False, (f"uniform background but no distinct object in {n - len(obj)}/{n} photo(s); no automatic masks")
    col = np.median([s["color"] for s in uni], axis=0)
    return True, (f"uniform background in {len(uni)}/{n} photo(s) (median {100 * med:.0f}% of border pixels within "
                  f"{cfg.tolerance:g} of colour {[round(float(c), 3) for c in col]})")


def masks_for_images(images: Sequence[np.ndarray], cfg: MaskConfig | None = None,
                     points: Sequence[np.ndarray | None] | None = None,
                     eight_bit_codes: Sequence[bool] | None = None, names: Sequence[str] | None = None,
                     ) -> tuple[list[np.ndarray | None], dict]:
    """Masks for a capture's photos (mode from ``cfg``; ``auto`` decided over all photos).

    Returns:
        (per photo a bool mask or None, summary dict: ``mode`` (the mode used, or ``none``),
        ``decision`` (why), ``masks`` (count), ``photos`` (per-photo info, with ``reason`` when a
        photo got no mask), ``seconds``).
    """
    import cv2

    cfg = cfg or MaskConfig()
    cfg.validate()
    t0 = time.perf_counter()
    n = len(images)
    names = list(names) if names is not None else [str(i) for i in range(n)]
    codes = list(eight_bit_codes) if eight_bit_codes is not None else [False] * n
    summary: dict[str, Any] = {"requested": cfg.mode}
    if cfg.mode == "none":
        summary.update(mode="none", decision="masks off (mode none)", masks=0, photos={})
        return [None] * n, summary
    mode = cfg.mode
    per: dict[str, dict] = {}
    if mode == "auto":
        stats = []
        for img, c in zip(images, codes):
            disp = display_image(img, c)
            s = min(1.0, 512 / max(disp.shape[:2]))
            if s < 1.0:
                disp = cv2.resize(disp, (max(1, round(disp.shape[1] * s)), max(1, round(disp.shape[0] * s))),
                                  interpolation=cv2.INTER_AREA)
            stats.append(border_stats(disp, cfg))
        ok, why = decide_auto(stats, cfg)
        summary["decision"] = why
        if not ok:
            summary.update(mode="none", masks=0, photos={})
            return [None] * n, summary
        mode = "grabcut"
    else:
        summary["decision"] = f"mode {mode} requested"
    summary["mode"] = mode
    out: list[np.ndarray | None] = []

    # a bar on a terminal only: GrabCut takes most of a second per photo
    for i, img in enumerate(bar(images, "masks", unit="photo")):
        pts = points[i] if points is not None else None
        m, info = compute_mask(img, cfg, mode, pts, codes[i])
        if m is not None and cfg.mode == "auto" and not info["uniform"]:
            m, info["reason"] = None, (f"border not uniform in this photo ({100 * info['uniform_fraction']:.0f}% "
                                       f"background-coloured)")
        out.append(m)
        per[names[i]] = info
    out = _undo_doubtful(out, per, names, cfg, summary)
    summary["masks"] = sum(m is not None for m in out)
    summary["photos"] = per
    summary["seconds"] = round(time.perf_counter() - t0, 3)
    return out, summary


def _undo_doubtful(masks: list, per: dict, names: list, cfg: MaskConfig, summary: dict) -> list:
    """The masks with the doubtful ones undone (see :func:`doubt` and ``cfg.max_area_variation``): all of them
    when more than ``cfg.max_doubtful`` of the photos' masks are doubtful or their areas vary too much, else
    only the doubtful photos'. The decision goes to ``summary`` (``doubtful``, ``decision``) and, when masks
    are undone, one line to the log."""
    doubtful = {}
    for name, m in zip(names, masks):
        why = doubt(per[name], cfg) if m is not None else None
        if why:
            doubtful[name] = per[name]["reason"] = f"doubtful: {why}"
    areas = np.array([per[name]["mask_fraction"] for name, m in zip(names, masks) if m is not None])
    variation = float(areas.std() / areas.mean()) if len(areas) >= 4 and areas.mean() > 0 else 0.0
    summary["doubtful"] = doubtful
    summary["area_variation"] = round(variation, 3)
    made = len(areas)
    if not doubtful and variation <= cfg.max_area_variation:
        return masks
    if variation > cfg.max_area_variation:
        why = (f"the masks' areas vary across the photos by {100 * variation:.0f}% (coefficient of variation, more "
               f"than {100 * cfg.max_area_variation:.0f}%): they follow something other than the object")
    elif len(doubtful) > cfg.max_doubtful * made:
        first = next(iter(doubtful.items()))
        why = f"{len(doubtful)} of {made} masks are doubtful (e.g. {first[0]}: {first[1][len('doubtful: '):]})"
    else:
        line = (f"{len(doubtful)} of {made} masks doubtful and not used (e.g. {next(iter(doubtful))}: "
                f"{next(iter(doubtful.values()))[len('doubtful: '):]})")
        summary["decision"] += f"; {line}"
        say("masks", line)
        return [None if n in doubtful else m for n, m in zip(names, masks)]
    line = f"no automatic masks: {why}"
    summary.update(mode="none", decision=f"{summary['decision']}; then undone: {why}")
    say("masks", line)
    return [None] * len(masks)


# ----------------------------------------------------------------------------------- capture folders


def sfm_points_per_image(capture: Any, sparse: str | os.PathLike) -> dict[str, np.ndarray]:
    """Object SfM points per frame, projected with the frame's (undistorted) pose and intrinsics.

    Only 3D points observed in that photo are used, and only those within the object cluster (robust
    distance to the points' median below 3 x the median distance; background features on a cloth or
    a turntable further out are left out).

    Args:
        capture: the :class:`~texstream.capture.capture_json.Capture` (registered).
        sparse: COLMAP model folder (``sparse/0``).

    Returns:
        frame name -> (N, 2) pixel coordinates (x, y; pixel centres at +0.5).
    """
    import pycolmap

    rec = pycolmap.Reconstruction(str(sparse))
    ids = np.array(list(rec.points3D.keys()), dtype=np.int64)
    if len(ids) == 0:
        return {}
    xyz = np.array([rec.points3D[int(i)].xyz for i in ids])
    med = np.median(xyz, axis=0)
    r = np.linalg.norm(xyz - med, axis=1)
    good = dict(zip(ids.tolist(), (r <= 3.0 * np.median(r)).tolist()))
    by_name = {Path(im.name).stem: im for im in rec.images.values() if im.has_pose}
    out: dict[str, np.ndarray] = {}
    for f in capture.frames:
        im = by_name.get(f.name)
        if im is None:
            continue
        pid = [p.point3D_id for p in im.points2D if p.has_point3D() and good.get(p.point3D_id, False)]
        if not pid:
            continue
        X = np.array([rec.points3D[i].xyz for i in pid])
        cam = X @ f.R.T + f.t
        cam = cam[cam[:, 2] > 0]
        uv = cam @ f.intrinsics.matrix().T
        out[f.name] = uv[:, :2] / uv[:, 2:3]
    return out


def make_masks(capture_dir: str | os.PathLike, config: MaskConfig | None = None, *, use_sfm: bool = True,
               replace: bool = False, preview: bool = True) -> StageResult:
    """Compute automatic masks for an existing capture folder and record them in its capture.json.

    Args:
        capture_dir: capture folder (ingest or registration output).
        config: options (``auto`` decides from the photos).
        use_sfm: seed GrabCut with the SfM points of ``sparse/0`` when the folder has them (registered).
        replace: replace masks the frames already have (default: keep them; they were given by the
            user or a renderer).
        preview: write ``previews/masks.png`` (contact sheet with mask outlines).

    Returns:
        StageResult; summary as :func:`masks_for_images` plus ``written`` and ``kept``.

    Raises:
        InputError: unreadable capture.json or photo.
    """
    cfg = config or MaskConfig()
    cfg.validate()
    root = Path(capture_dir)
    cap = read_capture(root)
    todo = [f for f in cap.frames if replace or f.mask_path is None]
    kept = len(cap.frames) - len(todo)
    images, codes = [], []
    for f in todo:
        p = cap.image_path(f)
        if p.suffix.lower() in (".png", ".jpg", ".jpeg", ".tif", ".tiff") and _is_8bit(p):
            images.append(read_image(p, channels=3, linear=False))
            codes.append(True)
        else:
            images.append(read_image(p, channels=3) / np.float32(f.exposure))
            codes.append(False)
    pts = None
    sparse = root / "sparse" / "0"
    if use_sfm and sparse.is_dir() and todo:
        try:
            per = sfm_points_per_image(cap, sparse)
        except Exception as e:  # noqa: BLE001 - an unreadable model only loses the seeds
            raise InputError(f"cannot read the SfM model ({e})", sparse, "re-run registration or pass use_sfm=False") from None
        pts = [per.get(f.name) for f in todo]
    masks, summary = masks_for_images(images, cfg, pts, codes, [f.name for f in todo])
    written = 0
    for f, m in zip(todo, masks):
        if m is None:
            continue
        rel = Path("masks") / (f.name + ".png")
        write_image(root / rel, np.where(m, np.uint8(255), np.uint8(0)), bits=8)
        f.mask_path = str(rel)
        written += 1
    summary.update(written=written, kept=kept, sfm_seeds=pts is not None)
    cap.extra["auto_masks"] = {k: summary[k] for k in ("mode", "decision", "masks")}
    write_capture(cap, root)
    write_json_atomic(root / REPORT_FILE, summary)
    if preview and written:
        write_mask_preview(root)
    return StageResult(output=root, summary=summary)


def write_mask_preview(root: str | os.PathLike) -> Path:
    """Contact sheet of the capture with every mask's outline (and its outside dimmed)."""
    return write_contact_sheet(root, Path(root) / PREVIEW_FILE, mask_style="both")


def _is_8bit(path: Path) -> bool:
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        oiio.geterror()
        return False
    try:
        return inp.spec().format == oiio.UINT8
    finally:
        inp.close()


def mask_iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union of two bool masks (1.0 when both are empty)."""
    a, b = np.asarray(a, bool), np.asarray(b, bool)
    u = np.logical_or(a, b).sum()
    return float(np.logical_and(a, b).sum() / u) if u else 1.0
