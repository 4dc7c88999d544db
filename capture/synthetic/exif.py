"""Synthetic photos as a camera and a raw converter write them: 8-bit JPEGs with EXIF.

Real exports break what rendered PNGs never touch. A raw converter that exports at a quarter of the sensor
resolution keeps the camera body's ``FocalPlaneXResolution`` (pixels per unit of the *full* sensor) and its
``PixelXDimension``, so a focal length computed from them is 4x too long for the exported pixels. These helpers
write such files on purpose, so ingest's cross-checks and the camera imports are tested against them.

:class:`CameraBody` is what the EXIF says about the camera; :func:`exif_for` gives the tags for one photo
(``stale=True``: the full sensor's tags on a resized photo, as a converter leaves them); :func:`write_jpeg`
writes the pixels with the tags through OpenImageIO (a declared dependency, imported inside the function).
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import tempfile
from pathlib import Path

import numpy as np



@dataclasses.dataclass(frozen=True)
class CameraBody:
    """A camera body and lens as EXIF names them.

    ``sensor_px``: the sensor's full resolution (width, height) in pixels; ``sensor_width_mm``: its width.
    The defaults are a full-frame 22-megapixel body (Canon EOS 5D Mark III: 36 x 24 mm, 5760 x 3840 px).
    """

    make: str = "Canon"
    model: str = "Canon EOS 5D Mark III"
    sensor_width_mm: float = 36.0
    sensor_px: tuple[int, int] = (5760, 3840)

    def focal_px(self, focal_mm: float, width_px: int) -> float:
        """The focal length in pixels of a photo ``width_px`` wide covering the whole sensor width."""
        return float(focal_mm) * width_px / self.sensor_width_mm


def exif_for(body: CameraBody, focal_mm: float, size: tuple[int, int], *, stale: bool = False,
             focal_35mm: float | None = None) -> dict[str, object]:
    """EXIF tags (OpenImageIO names) for a photo of ``size`` (width, height) taken by ``body`` at ``focal_mm``.

    ``stale``: the focal-plane resolution and pixel dimensions of the full sensor, whatever ``size`` is (what
    a raw converter keeps on a resized export); otherwise those of ``size``, as if the sensor had that many
    pixels. ``focal_35mm``: the 35 mm-equivalent tag, left out when None (many bodies omit it).
    """
    px_w, px_h = body.sensor_px if stale else size
    per_cm = px_w / (body.sensor_width_mm / 10.0)
    tags: dict[str, object] = {
        "Make": body.make, "Model": body.model, "Orientation": 1,
        "Exif:FocalLength": float(focal_mm),
        "Exif:FocalPlaneXResolution": float(per_cm), "Exif:FocalPlaneYResolution": float(per_cm),
        "Exif:FocalPlaneResolutionUnit": 3,  # centimetres
        "Exif:PixelXDimension": int(px_w), "Exif:PixelYDimension": int(px_h),
    }
    if focal_35mm is not None:
        tags["Exif:FocalLengthIn35mmFilm"] = int(round(focal_35mm))
    return tags


def to_8bit(image: np.ndarray) -> np.ndarray:
    """A display-referred image in [0, 1] (float) or uint8 as uint8, rounded and clipped."""
    if image.dtype == np.uint8:
        return image
    return np.clip(np.rint(np.asarray(image, np.float64) * 255.0), 0, 255).astype(np.uint8)


def write_jpeg(path: str | os.PathLike, image: np.ndarray, tags: dict[str, object], quality: int = 95) -> Path:
    """Write ``image`` ((H, W, 3) uint8, or float in [0, 1] already display-encoded) as a JPEG with ``tags``."""
    import OpenImageIO as oiio

    pixels = np.ascontiguousarray(to_8bit(image))
    h, w = pixels.shape[:2]
    channels = 1 if pixels.ndim == 2 else pixels.shape[2]
    spec = oiio.ImageSpec(w, h, channels, oiio.UINT8)
    for key, value in tags.items():
        spec.attribute(key, value)
    spec.attribute("Compression", f"jpeg:{int(quality)}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    # OpenImageIO picks the format from the extension, so the temporary file keeps it; renamed into place.
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    try:
        out = oiio.ImageOutput.create(tmp)
        if out is None or not out.open(tmp, spec):
            raise OSError(f"cannot write {path}: {oiio.geterror()}")
        try:
            out.write_image(pixels)
        finally:
            out.close()
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp made it 0600; give it what open() would
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
    return path
