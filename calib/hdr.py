"""Exposure brackets: grouping photos of one view and merging them to linear HDR radiance.

8-bit brackets go through OpenCV's photo module: the camera response curve is recovered with
Debevec & Malik's method (``createCalibrateDebevec``) or Robertson's (``createCalibrateRobertson``)
and the brackets are merged with the matching ``createMerge*``. The result is relative radiance
(value / exposure time). Linear inputs (16-bit, float) need no response: they are merged by a
weighted average of value / time that ignores clipped and near-black samples.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from texstream.capture.imageio import linear_to_srgb
from texstream.core.errors import ConfigError

HDR_METHODS = ("debevec", "robertson")


def group_brackets(times: Sequence[float | None], sizes: Sequence[tuple[int, int]], bracket_size: int = 0) -> list[list[int]]:
    """Group photo indices (in name order) into exposure brackets of the same view.

    Args:
        times: exposure time per photo (s), None when unknown.
        sizes: (width, height) per photo.
        bracket_size: photos per bracket; 0 = auto: consecutive photos of one size whose exposure
            times are all different form a bracket, which ends when a time repeats or is unknown
            (how cameras' auto-exposure-bracketing mode writes them); 1 = no brackets.

    Returns:
        list of index lists, each sorted by exposure time (shortest first).
    """
    n = len(times)
    groups: list[list[int]] = []
    if bracket_size == 1:
        groups = [[i] for i in range(n)]
    elif bracket_size > 1:
        groups = [list(range(i, min(i + bracket_size, n))) for i in range(0, n, bracket_size)]
    else:
        # The first run of distinct times defines the camera's bracket pattern; later brackets
        # use the same times (a photo with another time is a single shot of its own).
        pattern: list[float] | None = None
        cur: list[int] = []
        for i in range(n):
            t = times[i]
            ok = (bool(cur) and t is not None and times[cur[0]] is not None and sizes[i] == sizes[cur[0]]
                  and all(abs(times[j] - t) > 1e-3 * t for j in cur)
                  and (pattern is None or any(abs(p - t) <= 1e-3 * t for p in pattern))
                  and (pattern is None or all(any(abs(p - times[j]) <= 1e-3 * p for p in pattern) for j in cur)))
            if ok:
                cur.append(i)
            else:
                if cur:
                    groups.append(cur)
                    if pattern is None and len(cur) > 1:
                        pattern = [times[j] for j in cur]
                cur = [i]
        if cur:
            groups.append(cur)
    return [sorted(g, key=lambda i: (times[i] is None, times[i] or 0.0)) for g in groups]


def calibrate_response(images8: list[np.ndarray], times: Sequence[float], method: str = "debevec",
                       samples: int = 70, lambda_: float = 10.0) -> np.ndarray:
    """Camera response (256, 1, 3) float32 (code -> relative linear exposure) from 8-bit brackets.

    Args:
        images8: (H, W, 3) uint8 images of one static view, RGB or BGR (channels are independent).
        times: exposure time of each (s).
        method: ``debevec`` or ``robertson``.
        samples: pixels sampled by Debevec's least squares.
        lambda_: Debevec's smoothness weight.
    """
    import cv2

    t = np.asarray(times, dtype=np.float32)
    if method == "debevec":
        cal = cv2.createCalibrateDebevec(samples=samples, lambda_=lambda_, random=False)
    elif method == "robertson":
        cal = cv2.createCalibrateRobertson()
    else:
        raise ConfigError(f"unknown HDR method {method!r}", fix=f"use one of {HDR_METHODS}")
    return cal.process([np.ascontiguousarray(im) for im in images8], t)


def merge_brackets_8bit(images8: list[np.ndarray], times: Sequence[float], response: np.ndarray,
                        method: str = "debevec") -> np.ndarray:
    """Merge 8-bit brackets with a known response: (H, W, 3) float32 relative radiance."""
    import cv2

    t = np.asarray(times, dtype=np.float32)
    merge = cv2.createMergeDebevec() if method == "debevec" else cv2.createMergeRobertson()
    return merge.process([np.ascontiguousarray(im) for im in images8], t, response)


def merge_brackets_linear(images: list[np.ndarray], times: Sequence[float], saturation: float = 0.98,
                          floor: float = 1e-3) -> np.ndarray:
    """Merge linear brackets: weighted mean of value / time over unclipped, non-black samples.

    Args:
        images: (H, W, C) float32 linear images (1.0 = full scale).
        times: exposure time of each.
        saturation: values at or above this are clipped and ignored.
        floor: values below this are ignored (noise), unless no exposure is usable.

    Returns:
        (H, W, C) float32 radiance (value per second). Pixels clipped in every bracket take the
        shortest exposure's value / time (a lower bound).
    """
    stack = np.stack(images).astype(np.float32)
    t = np.asarray(times, dtype=np.float32).reshape(-1, 1, 1, 1)
    # Hat weight on the value: trusts mid-range most, as Debevec's weighting does.
    w = np.minimum(stack - floor, saturation - stack).clip(min=0.0)
    w = np.where((stack >= saturation) | (stack <= floor), 0.0, w + 1e-6)
    num = (w * stack / t).sum(0)
    den = w.sum(0)
    i_short = int(np.argmin(np.asarray(times)))
    fallback = stack[i_short] / t[i_short]
    return np.where(den > 0, num / np.maximum(den, 1e-12), fallback).astype(np.float32)


BRACKET_MODES = ("auto", "on", "off")


def is_exif_bracket(exposure_modes: Sequence[float | None]) -> bool:
    """True when every photo's EXIF ExposureMode is 2 ("auto bracket")."""
    return bool(exposure_modes) and all(m is not None and int(m) == 2 for m in exposure_modes)


def bracket_alignment(images: Sequence[np.ndarray], times: Sequence[float], tol_px: float = 2.0,
                      max_side: int = 480, identity_ncc: float = 0.98) -> dict:
    """Whether the photos of a candidate bracket show one viewpoint (so merging them cannot ghost).

    Each photo (linear) is brought to the middle exposure's level (value x t_mid / t), clipped,
    sRGB-encoded, converted to grey and downscaled to ``max_side``. A photo whose rank correlation
    (Spearman: blind to the unknown response curve) with the middle one, in place over the pixels well exposed in both, is at least ``identity_ncc``
    agrees with it as it is; otherwise OpenCV's ECC (``findTransformECC``,
    affine motion, which ignores remaining gain and offset differences) aligns it to the middle
    photo, starting from the identity. The bracket is aligned when every ECC converges and moves no
    image corner by more than ``tol_px`` (full-resolution pixels).

    Args:
        images: (H, W, C) linear float photos of one size.
        times: exposure time of each.
        tol_px: largest accepted corner displacement, pixels.
        max_side: working resolution (longest side).

    Returns:
        dict: ``aligned`` (bool), ``max_shift_px`` (largest corner displacement, None when ECC failed),
        ``correlation`` (smallest ECC correlation), ``in_place`` (smallest correlation in place) and
        ``reason`` (one line).
    """
    import cv2

    n = len(images)
    if n < 2:
        return {"aligned": True, "max_shift_px": 0.0, "correlation": 1.0, "reason": "single photo"}
    h, w = images[0].shape[:2]
    if any(im.shape[:2] != (h, w) for im in images):
        return {"aligned": False, "max_shift_px": None, "correlation": None, "reason": "photo sizes differ"}
    s = min(1.0, max_side / max(h, w))
    size = (max(8, round(w * s)), max(8, round(h * s)))
    order = np.argsort(times)
    ref_i = int(order[n // 2])
    t_ref = float(times[ref_i])

    def grey(i: int) -> np.ndarray:
        a = np.asarray(images[i], np.float32)
        a = a[..., :3].mean(-1) if a.ndim == 3 else a
        g = linear_to_srgb(np.clip(a * np.float32(t_ref / float(times[i])), 0.0, 1.0)).astype(np.float32)
        return cv2.resize(g, size, interpolation=cv2.INTER_AREA)

    ref = grey(ref_i)
    corners = np.array([[0, 0, 1], [size[0], 0, 1], [0, size[1], 1], [size[0], size[1], 1]], np.float64)
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-5)
    worst, corr = 0.0, 1.0
    ncc_min = 1.0
    for i in range(n):
        if i == ref_i:
            continue
        g = grey(i)
        ok = (ref > 0.03) & (ref < 0.97) & (g > 0.03) & (g < 0.97)
        if ok.mean() > 0.05:
            # Rank correlation: blind to the (unknown) camera response left after normalisation.
            a, b = (np.argsort(np.argsort(x[ok])).astype(np.float64) for x in (ref, g))
            a, b = a - a.mean(), b - b.mean()
            ncc = float((a * b).sum() / max(np.sqrt((a * a).sum() * (b * b).sum()), 1e-12))
        else:
            ncc = 0.0
        ncc_min = min(ncc_min, ncc)
        if ncc >= identity_ncc:
            continue  # agrees in place: nothing for ECC to find (and smooth scenes make it ill-posed)
        warp = np.eye(2, 3, dtype=np.float32)
        try:
            cc, warp = cv2.findTransformECC(ref, g, warp, cv2.MOTION_AFFINE, crit, None, 5)
        except cv2.error:
            return {"aligned": False, "max_shift_px": None, "correlation": None,
                    "reason": "photos do not align (ECC found no consistent motion: different viewpoints or content)"}
        moved = corners @ warp.astype(np.float64).T
        worst = max(worst, float(np.abs(moved - corners[:, :2]).max()) / s)
        corr = min(corr, float(cc))
    ok = worst <= tol_px
    reason = (f"photos align: largest corner displacement {worst:.2f} px <= {tol_px:g} px (correlation in place "
              f"{ncc_min:.3f}, after ECC {corr:.3f})" if ok else f"photos do not align: corner displacement {worst:.1f} px > {tol_px:g} px (different viewpoints)")
    return {"aligned": ok, "max_shift_px": round(worst, 3), "correlation": round(corr, 4),
            "in_place": round(ncc_min, 4), "reason": reason}
