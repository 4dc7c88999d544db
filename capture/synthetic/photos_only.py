"""A synthetic capture's photos as a camera leaves them, for tests and benchmarks of the photos-only path
(registration from the images and their EXIF alone)."""

from __future__ import annotations

import os
from pathlib import Path

from texstream.core.outputs import atomic_output_dir

from texstream.capture.capture_json import Intrinsics
from texstream.capture.capture_json import flash_fired, no_flash_frames, read_capture
from texstream.capture.imageio import copy_with_metadata

from .flash_capture import EXIF_FLASH_FIRED, EXIF_FLASH_OFF


SENSOR_WIDTH_MM = 36.0  # the synthetic camera's sensor: full frame, so the 35 mm equivalent is the focal length


def camera_exif(intrinsics: Intrinsics) -> dict:
    """The EXIF fields a camera writes about its lens for a pinhole of these intrinsics, as OpenImageIO names
    them: the focal length in mm on a full-frame sensor (36 mm over the image's longer side), its 35 mm
    equivalent (an integer, as cameras store it) and the sensor's pixels per mm (focal plane resolution)."""
    px_per_mm = max(intrinsics.width, intrinsics.height) / SENSOR_WIDTH_MM
    focal_mm = float(intrinsics.fx) / px_per_mm
    return {"Make": "texstream", "Model": "synthetic pinhole camera", "Exif:FocalLength": focal_mm,
            "Exif:FocalLengthIn35mmFilm": round(focal_mm * 36.0 / SENSOR_WIDTH_MM),
            "Exif:FocalPlaneXResolution": px_per_mm, "Exif:FocalPlaneYResolution": px_per_mm,
            "Exif:FocalPlaneResolutionUnit": 4}  # 4: millimetres


def write_photos_only(capture_dir: str | os.PathLike, out_dir: str | os.PathLike) -> list[Path]:
    """A synthetic capture's photos as a camera leaves them: a folder of its images (same names, stored
    values unchanged) carrying the camera's EXIF focal length (:func:`camera_exif`) and, when some frames are
    marked ``no_flash`` (flash/no-flash pairs), the EXIF Flash tag the camera writes (fired or not), and nothing
    else (no capture.json, masks, poses or lights). Written atomically; returns the photo paths."""

    cap = read_capture(capture_dir)
    pairs = bool(no_flash_frames(cap.frames))
    out_dir = Path(out_dir)
    with atomic_output_dir(out_dir) as tmp:
        for f in cap.frames:
            flash = {"Exif:Flash": EXIF_FLASH_FIRED if flash_fired(f) else EXIF_FLASH_OFF} if pairs else {}
            copy_with_metadata(cap.image_path(f), tmp / Path(f.file_path).name, {**camera_exif(f.intrinsics), **flash})
    return [out_dir / Path(f.file_path).name for f in cap.frames]
