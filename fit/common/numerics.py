"""Warnings about a fit's numerical regime, read from its stream options and its photos before it runs (what
the stiff-and-extreme suite, fit/diagnostics/stiffcheck.py, and the summation study found unsafe)."""

from __future__ import annotations

import numpy as np

from texstream.fit.stream import config as stream_config  # read at call time: tests lower the threshold there

FP16_MAX = 65504.0
FP16_MIN_NORMAL = 2.0 ** -14


def numerics_warnings(stream, photos: int, images=None, masks=None) -> list[str]:
    """One line per regime the suite and the summation study found unsafe for ``stream``'s precision
    (a StreamConfig) on a capture of ``photos`` fitted photos (``images``/``masks``: their foreground values):

    - float32 sums chosen by hand above the photo count where their relative error of E passes 1e-5
      (``FP32_SAFE_PHOTOS``; the million_photos case: 2.4e-3 at 10^6 photos) without Kahan summation;
    - float16 photos (``image_precision`` fp16) with foreground values above float16's largest (they
      become Inf and are dropped as clipped) or more than 1% of them subnormal in float16.
    """
    FP32_SAFE_PHOTOS = stream_config.FP32_SAFE_PHOTOS
    out = []
    if stream.accumulate == "fp32" and not stream.kahan and photos > FP32_SAFE_PHOTOS:
        out.append(f"numerics: float32 sums over {photos} photos lose accuracy (relative error of the objective "
                   f"above 1e-5 past {FP32_SAFE_PHOTOS} photos, docs/numerics.md); use --stream.accumulate auto "
                   "(fp64 here) or --stream.kahan")
    if stream.image_precision == "fp16" and images is not None:
        peak, tiny, total = 0.0, 0, 0
        for img, m in zip(images, masks if masks is not None else [None] * len(images)):
            v = np.abs(np.asarray(img if m is None else img[m], np.float32))
            if v.size:
                peak = max(peak, float(v.max()))
                tiny += int(((v > 0) & (v < FP16_MIN_NORMAL)).sum())
                total += int(v.size)
        if peak > FP16_MAX:
            out.append(f"numerics: photo values up to {peak:.3g} exceed float16's {FP16_MAX:.0f} and would be dropped "
                       "as clipped; use --stream.image-precision fp32 (or a lower exposure scale)")
        elif total and tiny > 0.01 * total:
            out.append(f"numerics: {100 * tiny / total:.0f}% of the photo values are below float16's smallest normal "
                       f"({FP16_MIN_NORMAL:.2g}) and keep fewer than 11 bits; use --stream.image-precision fp32")
    return out
