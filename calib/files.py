"""Photo folder scanning and small report helpers shared by the calib stages."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from texstream.core.errors import InputError, StageError
from texstream.core.outputs import write_json_atomic

# Formats OpenImageIO / OpenCV read that cameras and tools produce.
IMAGE_EXTS = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".exr", ".hdr", ".bmp", ".webp", ".pfm")


def list_images(folder: str | os.PathLike, what: str = "photo folder", min_count: int = 1) -> list[Path]:
    """Image files directly in ``folder``, sorted by name (stable across runs and platforms).

    Hidden files (``.``-prefixed) are skipped. Raises InputError when the folder is missing or holds
    fewer than ``min_count`` images.
    """
    p = Path(folder)
    if not p.is_dir():
        raise InputError(f"{what} not found or not a folder", p, "pass the folder that holds the photos")
    files = sorted((f for f in p.iterdir() if f.is_file() and not f.name.startswith(".")
                    and f.suffix.lower() in IMAGE_EXTS), key=lambda f: f.name)
    if len(files) < min_count:
        got = "no images" if not files else f"{len(files)} image(s)"
        raise InputError(f"{what} holds {got} ({', '.join(IMAGE_EXTS)}); at least {min_count} needed", p,
                         "put the photos directly in this folder" if not files else "add more photos")
    return files


def failure_report_path(out: str | os.PathLike) -> Path:
    """Where a stage that fails writes its partial report: beside the (unwritten) output."""
    out = Path(out)
    return out.parent / f"{out.name}.failed_report.json"


def write_failure_report(out: str | os.PathLike, report: dict[str, Any]) -> Path:
    """Write a partial report for a failed stage (the output itself is not written)."""
    path = failure_report_path(out)
    write_json_atomic(path, report)
    return path


def read_stored_pixels(path: Path, what: str = "image") -> tuple[np.ndarray, Any]:
    """(pixels (H, W, C) in the file's own format, its OpenImageIO spec): what a resampling writes back in the
    same format and bit depth. An unreadable file is an InputError naming it."""
    import OpenImageIO as oiio

    buf = oiio.ImageBuf(str(path))
    spec = buf.spec()
    px = buf.get_pixels(spec.format if spec.format != oiio.UNKNOWN else oiio.FLOAT)
    if px is None or px.size == 0:
        raise InputError(f"cannot read the {what} ({oiio.geterror() or 'no pixels'})", path, "replace the file")
    return px, spec


def remap_channels(px: np.ndarray, map_x: np.ndarray, map_y: np.ndarray, interpolation: int, **border) -> np.ndarray:
    """``cv2.remap`` of each channel of ``px`` (OpenCV remaps at most 4 channels of some formats at once)."""
    import cv2

    return np.stack([cv2.remap(np.ascontiguousarray(px[..., c]), map_x, map_y, interpolation, **border)
                     for c in range(px.shape[2])], -1)


def write_stored_pixels(path: Path, px: np.ndarray, spec: Any, what: str = "image") -> None:
    """Write ``px`` with OpenImageIO ``spec`` (format, bit depth, metadata) to ``path``; a StageError names it."""
    import OpenImageIO as oiio

    path.parent.mkdir(parents=True, exist_ok=True)
    out = oiio.ImageOutput.create(str(path))
    if out is None or not out.open(str(path), spec):
        raise StageError(f"cannot write the {what} ({oiio.geterror()})", path)
    out.write_image(px)
    out.close()
