"""A synthetic capture written as a raw converter exports it: JPEGs with a camera body's EXIF whose focal-plane
tags describe the full sensor (:mod:`.exif`), and nothing else; the truth (poses, intrinsics) in a capture.json
beside them. Tests and ``benchmarks/intrinsics_prior.py`` run ingest + registration on it and compare the
focal length registration ends with against the renderer's.
"""

from __future__ import annotations

import os
from pathlib import Path

from texstream.capture.imageio import linear_to_srgb
from texstream.core.outputs import atomic_output_dir

from .exif import CameraBody, exif_for, write_jpeg
from .synth import SynthConfig, load_scene, render_scene


def write_exif_capture(out_dir: str | os.PathLike, *, scene: str = "textured_sphere", size: tuple[int, int] = (480, 320),
                       photos: int = 20, body: CameraBody | None = None, stale: bool = True,
                       drop_tags: tuple[str, ...] = (), cameras: dict | None = None, device: str = "cpu") -> dict:
    """Render ``scene`` at ``size`` (width, height) from ``photos`` cameras and write ``out_dir/photo_NNN.jpg``
    with ``body``'s EXIF (``stale``: the full sensor's focal-plane resolution and pixel dimensions, as a
    converter leaves them on a resized export; ``drop_tags``: EXIF tags left out, e.g. ``PixelXDimension``
    and ``Make`` so no cross-check can catch the stale tags) (written atomically). ``cameras``: overrides of the
    scene's camera layout (e.g. ``distance``).

    The lens' focal length in millimetres is the renderer's focal length in pixels over the photo's
    pixels per millimetre on the sensor (the photo covers the whole sensor width).

    Returns:
        dict: ``photos`` (folder), ``frames`` (the true capture Frames, in the photos' order), ``focal_px``
        (true), ``focal_mm``, ``naive_focal_px`` (FocalLength x FocalPlaneXResolution: what ingest used to
        take), ``body``.
    """
    body = body or CameraBody()
    sc = load_scene(scene)
    sc["cameras"] = {**sc["cameras"], **(cameras or {}), "width": int(size[0]), "height": int(size[1]), "count": int(photos)}
    sc["photo"] = {**sc["photo"], "bits": 32}  # linear floats; encoded once here as the JPEG's sRGB
    rendered = render_scene(sc, SynthConfig(progress=False, preview=False, device=device))
    fx = float(rendered.frames[0].intrinsics.fx)
    focal_mm = fx * body.sensor_width_mm / size[0]
    tags = exif_for(body, focal_mm, size, stale=stale)
    for key in drop_tags:
        tags.pop(key, None)
    out = Path(out_dir)
    with atomic_output_dir(out) as tmp:
        for i, img in enumerate(rendered.images):
            write_jpeg(tmp / f"photo_{i:03d}.jpg", linear_to_srgb(img.clip(0, 1)), tags)
    per_mm = body.sensor_px[0] / body.sensor_width_mm if stale else size[0] / body.sensor_width_mm
    return {"photos": out, "frames": rendered.frames, "focal_px": fx, "focal_mm": focal_mm,
            "naive_focal_px": focal_mm * per_mm, "body": body.model}
