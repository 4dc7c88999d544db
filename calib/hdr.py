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
