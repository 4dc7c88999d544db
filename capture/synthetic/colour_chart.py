"""Synthetic photos with a ColorChecker in view, through a camera's tone curve (issue 39's test data: exported
JPEGs are tone-mapped, and the chart is what undoes it).

:func:`paste_chart` draws the chart (24 patches on a dark surround, the ColorChecker Classic's layout) into a
linear photo as a plane seen in perspective, its patches at reflectance x the photo's light; :func:`filmic_codes`
is a tone curve of the kind raw converters apply (a soft shoulder, then sRGB's encoding), so the stored codes are
far from linear and from plain sRGB."""

from __future__ import annotations

import numpy as np

from texstream.calib.colour_chart import chart_reflectance

PATCH_PX, GAP_PX, BORDER_PX = 60, 10, 20
"""the flat chart's layout before warping: the Classic's 4 x 6 patches with gaps and a border"""
SURROUND_REFLECTANCE = 0.012
"""the chart's black frame"""


def chart_plane(reflectance: np.ndarray | None = None) -> np.ndarray:
    """The chart as a flat (h, w, 3) linear reflectance image."""
    refl = chart_reflectance() if reflectance is None else reflectance
    h = 4 * PATCH_PX + 3 * GAP_PX + 2 * BORDER_PX
    w = 6 * PATCH_PX + 5 * GAP_PX + 2 * BORDER_PX
    plane = np.full((h, w, 3), SURROUND_REFLECTANCE)
    for r in range(4):
        for c in range(6):
            y, x = BORDER_PX + r * (PATCH_PX + GAP_PX), BORDER_PX + c * (PATCH_PX + GAP_PX)
            plane[y:y + PATCH_PX, x:x + PATCH_PX] = refl[r * 6 + c]
    return plane


def paste_chart(linear: np.ndarray, corners: np.ndarray, light: np.ndarray) -> np.ndarray:
    """``linear`` (H, W, 3) with the chart drawn where ``corners`` (4, 2: top-left, top-right, bottom-right,
    bottom-left, in pixels) put it, lit so a patch's radiance is its reflectance x ``light`` (3,)."""
    import cv2

    plane = chart_plane().astype(np.float32)
    h, w = plane.shape[:2]
    src = np.float32([[0, 0], [w, 0], [w, h], [0, h]])
    m = cv2.getPerspectiveTransform(src, np.float32(corners))
    size = (linear.shape[1], linear.shape[0])
    warped = cv2.warpPerspective(plane, m, size, flags=cv2.INTER_AREA)
    cover = cv2.warpPerspective(np.ones((h, w), np.float32), m, size, flags=cv2.INTER_AREA)[..., None]
    return linear * (1.0 - cover) + warped * np.asarray(light, np.float32) * cover


def filmic_codes(linear: np.ndarray, white: float = 4.0) -> np.ndarray:
    """Stored code values in [0, 1]: an extended Reinhard shoulder (``white`` maps to 1), then sRGB's encoding."""
    x = np.maximum(np.asarray(linear, np.float64), 0.0)
    tone = x * (1.0 + x / white ** 2) / (1.0 + x)
    tone = np.clip(tone, 0.0, 1.0)
    return np.where(tone <= 0.0031308, 12.92 * tone, 1.055 * tone ** (1 / 2.4) - 0.055)
