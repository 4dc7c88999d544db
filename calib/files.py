"""Photo folder scanning and small report helpers shared by the calib stages."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from texstream.core.errors import InputError
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
