"""Contact sheet of a capture folder: a grid of thumbnails, tone-mapped linear -> sRGB.

Each photo is read linear (:func:`imageio.read_image`), divided by its frame's ``exposure`` (so the
sheet shows radiance, comparable across frames), scaled by one sheet-wide exposure, clipped and
sRGB-encoded. The sheet-wide exposure maps the 99th percentile of all thumbnail pixels to 0.9
(``exposure="auto"``) or is a given linear factor. Masked-out pixels can be dimmed and mask outlines drawn to show the masks.
Frame indices are drawn in the corner of each thumbnail (OpenCV's Hershey font) when ``label``.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from texstream.core.errors import ConfigError

from .capture_json import read_capture
from .imageio import linear_to_srgb, read_image, read_mask, write_image


def _thumbnail(img: np.ndarray, thumb: int) -> np.ndarray:
    """Area-averaged downsample of (H, W, 3) to fit in thumb x thumb, centred on a black tile."""
    import cv2

    h, w = img.shape[:2]
    s = min(thumb / w, thumb / h)
    tw, th = max(1, round(w * s)), max(1, round(h * s))
    small = cv2.resize(img, (tw, th), interpolation=cv2.INTER_AREA if s < 1 else cv2.INTER_LINEAR)
    tile = np.zeros((thumb, thumb, 3), np.float32)
    y0, x0 = (thumb - th) // 2, (thumb - tw) // 2
    tile[y0:y0 + th, x0:x0 + tw] = small.reshape(th, tw, -1)[:, :, :3]
    return tile


def _label(tile8: np.ndarray, text: str) -> None:
    import cv2

    scale = max(0.3, tile8.shape[0] / 400)
    org = (3, int(14 * scale / 0.4))
    cv2.putText(tile8, text, org, cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), 3, cv2.LINE_AA)
    cv2.putText(tile8, text, org, cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), 1, cv2.LINE_AA)


def _outline(tile8: np.ndarray, mask: np.ndarray) -> None:
    """Draw a thumbnail mask's outline in green onto the tile, in place."""
    import cv2

    cs, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
    t = np.ascontiguousarray(tile8)
    cv2.drawContours(t, cs, -1, (0, 255, 0), 1)
    tile8[...] = t


def write_contact_sheet(capture_dir: str | os.PathLike, out_png: str | os.PathLike, max_images: int = 64,
                        thumb: int = 160, *, exposure: float | str = "auto", label: bool = True,
                        show_masks: bool = True, columns: int | None = None, mask_style: str = "dim") -> Path:
    """Write a PNG grid of thumbnails of a capture's photos.

    Args:
        capture_dir: capture folder (``capture.json`` or nerfstudio ``transforms.json``) or the file.
        out_png: output PNG path (written atomically).
        max_images: at most this many frames, evenly spaced over the capture.
        thumb: thumbnail size in pixels (square tiles, aspect ratio kept).
        exposure: "auto" (99th percentile -> 0.9) or a linear scale applied after dividing by each
            frame's exposure.
        label: draw the frame index on each tile.
        show_masks: show the masks where frames have ``mask_path`` (see ``mask_style``).
        mask_style: ``dim`` (masked-out pixels at 30%), ``outline`` (the mask's outline drawn in green)
            or ``both`` (for reviewing automatic masks).
        columns: grid columns (default: about square).

    Returns:
        The path written.

    Raises:
        InputError: unreadable capture.json, missing or corrupt images.
        ConfigError: bad max_images / thumb / exposure.
    """
    if max_images < 1 or thumb < 8:
        raise ConfigError(f"max_images={max_images}, thumb={thumb}", fix="use max_images >= 1 and thumb >= 8")
    if mask_style not in ("dim", "outline", "both"):
        raise ConfigError(f"mask style {mask_style!r} unknown", fix="use dim, outline or both")
    if exposure != "auto" and not (isinstance(exposure, (int, float)) and exposure > 0):
        raise ConfigError(f"exposure {exposure!r} is neither 'auto' nor a positive number",
                          fix="pass auto or e.g. 2.0")
    out_png = Path(out_png)
    if out_png.suffix.lower() != ".png":
        raise ConfigError("contact sheet must be a .png", out_png, "name the output *.png")
    cap = read_capture(capture_dir)
    n = len(cap.frames)
    idx = np.unique(np.round(np.linspace(0, n - 1, min(n, max_images))).astype(int))
    tiles, outlines = [], []
    for i in idx:
        f = cap.frames[i]
        img = read_image(cap.image_path(f), channels=3) / np.float32(f.exposure)
        outline = None
        if show_masks and f.mask_path is not None:
            m = read_mask(cap.mask_path(f), shape=img.shape[:2])
            if mask_style in ("dim", "both"):
                img = img * np.where(m, 1.0, 0.3).astype(np.float32)[:, :, None]
            if mask_style in ("outline", "both"):
                outline = _thumbnail(np.repeat(m[:, :, None].astype(np.float32), 3, axis=2), thumb)[:, :, 0] > 0.5
        tiles.append(_thumbnail(img, thumb))
        outlines.append(outline)
    stack = np.stack(tiles)
    if exposure == "auto":
        p99 = float(np.percentile(stack, 99))
        scale = 0.9 / p99 if p99 > 0 else 1.0
    else:
        scale = float(exposure)
    enc = linear_to_srgb(np.clip(stack * np.float32(scale), 0.0, 1.0))
    tiles8 = np.floor(enc * 255 + 0.5).astype(np.uint8)
    for k, o in enumerate(outlines):
        if o is not None:
            _outline(tiles8[k], o)
    if label:
        for k, i in enumerate(idx):
            t = np.ascontiguousarray(tiles8[k])
            _label(t, str(int(i)))
            tiles8[k] = t
    cols = columns or int(np.ceil(np.sqrt(len(idx))))
    rows = int(np.ceil(len(idx) / cols))
    gap = 2
    sheet = np.full((rows * (thumb + gap) + gap, cols * (thumb + gap) + gap, 3), 40, np.uint8)
    for k in range(len(idx)):
        r, c = divmod(k, cols)
        y, x = gap + r * (thumb + gap), gap + c * (thumb + gap)
        sheet[y:y + thumb, x:x + thumb] = tiles8[k]
    write_image(out_png, sheet)  # uint8: written as the sRGB codes they are
    return out_png
