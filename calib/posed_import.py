"""What the camera imports from photogrammetry tools share: the lens, the photo look-up, the capture writer.

Metashape (:mod:`texstream.calib.metashape`) and RealityCapture (:mod:`texstream.calib.realitycapture`) both
describe a camera as a pinhole with Brown radial / tangential distortion applied to the normalized camera
coordinates (x, y) = (X / Z, Y / Z) in OpenCV axes. :class:`LensCamera` holds one in texstream's naming:

    r2 = x^2 + y^2,  g = 1 + k1 r2 + k2 r2^2 + k3 r2^3 + k4 r2^4
    x' = x g + 2 p1 x y + p2 (r2 + 2 x^2)
    y' = y g + p1 (r2 + 2 y^2) + 2 p2 x y
    u = fx x' + skew y' + cx,   v = fy y' + cy        (capture pixels: pixel centres at +0.5)

which is OpenCV's model (``k1 k2 p1 p2 k3``) plus an r^8 term (``k4``, Metashape's K4, RealityCapture's
brown4) and a skew (Metashape's B2). Each format's module maps its own coefficients onto these names.

The fit renders pinhole cameras, so by default the import resamples every photo through the exact model above
onto the pinhole camera (fx, fy, cx, cy) of the same size (:func:`undistort_photo`; written as PNG, the source's
8 or 16 bits kept; the pinhole pixels whose ray leaves the photo masked out in ``masks/``): k4 and skew
included, which OpenCV's five coefficients cannot carry. With
``undistort=False`` the photos are copied or linked byte for byte and capture.json keeps the distortion
(``camera_model`` OPENCV with k1 k2 p1 p2 k3); a k4 or a skew that matters is then an error.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Callable

import numpy as np

from texstream.capture.capture_json import (MASK_KIND_KEY, NO_FLASH_KEY, VALID_PIXELS, Capture, Frame, Intrinsics,
                                             write_capture)
from texstream.capture.imageio import write_image
from texstream.core.errors import InputError, StageError

from .colmap_io import _copy_file
from .files import IMAGE_EXTS, read_stored_pixels, remap_channels, write_stored_pixels
from .lights import colocated_light
from .no_flash import decide_no_flash, read_flash_fired

FLOAT_EXTS = (".exr", ".hdr", ".pfm")
"""photo formats that store linear floats (no clipping level); the others store integers, which clip at 1"""

SKEW_TOLERANCE = 1e-6
"""|skew| / fx below which a skew is taken as 0 (a millionth of the focal length moves no pixel of any photo)."""


@dataclasses.dataclass(frozen=True)
class LensCamera:
    """A pinhole camera with Brown distortion (module doc), in capture pixels of a ``width`` x ``height`` image."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    skew: float = 0.0
    k1: float = 0.0
    k2: float = 0.0
    k3: float = 0.0
    k4: float = 0.0
    p1: float = 0.0
    p2: float = 0.0

    @property
    def has_distortion(self) -> bool:
        return any(v != 0.0 for v in (self.k1, self.k2, self.k3, self.k4, self.p1, self.p2)) or self.skew != 0.0

    def scaled(self, width: int, height: int) -> "LensCamera":
        """The same lens on a photo resampled to ``width`` x ``height`` (continuous pixel coordinates scale about
        the image corner, so focal lengths, skew and principal point scale by the size ratio; the distortion acts
        on normalized coordinates and stays)."""
        sx, sy = width / self.width, height / self.height
        return dataclasses.replace(self, width=int(width), height=int(height), fx=self.fx * sx, fy=self.fy * sy,
                                   cx=self.cx * sx, cy=self.cy * sy, skew=self.skew * sx)

    def distort(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Normalized undistorted (x, y) -> normalized distorted (x', y') (module doc)."""
        r2 = x * x + y * y
        g = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * (self.k3 + r2 * self.k4)))
        xd = x * g + 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x)
        yd = y * g + self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y
        return xd, yd

    def project(self, points_cam: np.ndarray) -> np.ndarray:
        """Camera-frame points (N, 3), OpenCV axes, -> distorted capture pixels (N, 2)."""
        p = np.asarray(points_cam, dtype=np.float64)
        xd, yd = self.distort(p[:, 0] / p[:, 2], p[:, 1] / p[:, 2])
        return np.stack([self.fx * xd + self.skew * yd + self.cx, self.fy * yd + self.cy], axis=1)

    def pinhole(self) -> Intrinsics:
        """The pinhole camera the undistorted photo has (same size, focal lengths and principal point)."""
        return Intrinsics(width=self.width, height=self.height, fx=self.fx, fy=self.fy, cx=self.cx, cy=self.cy)

    def opencv_intrinsics(self, where: str) -> Intrinsics:
        """Capture intrinsics keeping the distortion (OPENCV: k1 k2 p1 p2 k3); k4 or a skew cannot be kept."""
        if self.k4 != 0.0 or abs(self.skew) > SKEW_TOLERANCE * self.fx:
            term = "an r^8 radial term (k4)" if self.k4 != 0.0 else f"a skew of {self.skew:.4g} px"
            raise InputError(f"{where} has {term}, which capture.json's OpenCV distortion cannot hold",
                             fix="import with undistortion on (the default): the photos are resampled through "
                                 "the exact model")
        if not self.has_distortion:
            return self.pinhole()
        dist = {"k1": self.k1, "k2": self.k2, "p1": self.p1, "p2": self.p2, "k3": self.k3}
        return dataclasses.replace(self.pinhole(), camera_model="OPENCV", distortion=dist)


def photo_index(photos: Path) -> dict[str, Path]:
    """Lower-case file stem -> photo for the images directly in ``photos`` (several with one stem: an error)."""
    if not photos.is_dir():
        raise InputError("photo folder not found", photos, "pass the folder holding the photos the cameras belong to")
    index: dict[str, Path] = {}
    for f in sorted(photos.iterdir()):
        if not f.is_file() or f.name.startswith(".") or f.suffix.lower() not in IMAGE_EXTS:
            continue
        key = f.stem.lower()
        if key in index:
            raise InputError(f"two photos share the name {f.stem} ({index[key].name}, {f.name})", photos,
                             "keep one photo per camera in the folder")
        index[key] = f
    return index


def find_photo(index: dict[str, Path], label: str, photos: Path, source: str) -> Path:
    """The photo of a camera labelled ``label`` (with or without an image extension), matched by stem."""
    stem = label
    if Path(label).suffix.lower() in IMAGE_EXTS:
        stem = Path(label).stem
    stem = Path(stem).name  # a label may carry the photo's original folder
    found = index.get(stem.lower())
    if found is None:
        raise InputError(f"no photo for camera {label!r} of {source} (looked for {stem}.* in the folder)", photos,
                         "pass the folder holding the exported photos, named as the cameras are")
    return found


def photo_scale(calib_size: tuple[int, int], photo_size: tuple[int, int], photo: Path) -> tuple[float, float]:
    """(sx, sy) from a calibration resolution to a photo's size; a different aspect ratio is an error (a photo
    cropped or rotated after the alignment has no camera the calibration describes)."""
    (cw, ch), (pw, ph) = calib_size, photo_size
    sx, sy = pw / cw, ph / ch
    if abs(ch * sx - ph) > 1.0:  # a converter rounding the scaled height moves it by under one pixel
        raise InputError(f"photo is {pw}x{ph} but the calibration is {cw}x{ch} (another aspect ratio: "
                         f"{pw / ph:.4f} vs {cw / ch:.4f})", photo,
                         "export the photos uncropped and unrotated, at any scale of the aligned ones")
    return sx, sy


@dataclasses.dataclass
class PosedPhoto:
    """One imported camera: the photo, its pose (world-to-camera, OpenCV axes) and lens at the photo's size."""

    label: str
    photo: Path
    r: np.ndarray
    t: np.ndarray
    lens: LensCamera
    sensor: str = ""


def undistort_photo(src: Path, dst: Path, lens: LensCamera) -> np.ndarray | None:
    """Resample ``src`` through ``lens`` onto its pinhole camera (:meth:`LensCamera.pinhole`), written to ``dst``
    with the source's channels and bit depth (bicubic interpolation of the stored values, clipped to the format's
    range).

    Returns the pixels that saw the photo ((H, W) bool), or None when all did. A pinhole pixel whose ray lands
    outside the photo (along the frame's edges and corners for a pincushion lens: the pinhole camera of the same
    focal length sees further out than the photo) has no value: it is written black and left out of the mask, so
    that the fit and its scoring skip it instead of fitting the black (on the noise-textured sphere of
    benchmarks/camera_import.py, 4.4 dB of held-out PSNR). Kept: the pixels whose source lies between the photo's
    outermost pixel centres (interpolated, not extrapolated; the bicubic taps beyond the edge repeat it)."""
    import cv2
    import OpenImageIO as oiio

    px, spec = read_stored_pixels(src, "photo")
    if (spec.width, spec.height) != (lens.width, lens.height):
        raise StageError(f"photo is {spec.width}x{spec.height}, its camera {lens.width}x{lens.height}", src)
    u, v = np.meshgrid(np.arange(lens.width) + 0.5, np.arange(lens.height) + 0.5)
    xd, yd = lens.distort((u - lens.cx) / lens.fx, (v - lens.cy) / lens.fy)
    # capture pixels (centres at +0.5) -> cv2's (centres at integers)
    map_x = (lens.fx * xd + lens.skew * yd + lens.cx - 0.5).astype(np.float32)
    map_y = (lens.fy * yd + lens.cy - 0.5).astype(np.float32)
    valid = (map_x >= 0) & (map_x <= lens.width - 1) & (map_y >= 0) & (map_y <= lens.height - 1)
    # bicubic: a textured photo resampled bilinearly loses about 4 dB more (PSNR against the pinhole view)
    out = remap_channels(px, map_x, map_y, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
    out[~valid] = 0
    write_stored_pixels(dst, out, oiio.ImageSpec(spec.width, spec.height, spec.nchannels, spec.format),
                        "undistorted photo")
    return None if valid.all() else valid


MeshWriter = Callable[[Path, Path, np.ndarray], None]
"""(source mesh, destination, 4x4 similarity to apply) -> None: the mesh IO lives in a higher layer
(geometry), so the CLI hands its writer in (:func:`texstream.pipelines.cmd_import.transform_mesh_file`)."""


def write_posed_capture(tmp: Path, photos: list[PosedPhoto], *, undistort: bool, copy_mode: str,
                        colocated: float | None, extra: dict, no_flash: str | None = None) -> list[Frame]:
    """Write the photos into ``tmp/images`` (resampled to pinhole, or copied) and ``tmp/capture.json``; an
    undistorted photo with pixels outside the source gets ``tmp/masks/NAME.png`` (nonzero: seen). The photos taken
    with the flash off (``no_flash``, a file-name glob, else their EXIF Flash tag: :mod:`.no_flash`) are marked,
    their flash at intensity 0."""
    marked, no_flash_entry = decide_no_flash({p.photo.name: read_flash_fired(p.photo) for p in photos}, no_flash)
    if marked:
        extra = {**extra, NO_FLASH_KEY: no_flash_entry}
    frames = []
    used: set[str] = set()
    for p in photos:
        name = p.photo.stem + (".png" if undistort and p.lens.has_distortion else p.photo.suffix)
        if name.lower() in used:
            raise InputError(f"two cameras use the photo {p.photo.name}", p.photo, "keep one camera per photo")
        used.add(name.lower())
        rel = Path("images") / name
        mask = None
        if undistort and p.lens.has_distortion:
            seen = undistort_photo(p.photo, tmp / rel, p.lens)
            if seen is not None:  # the pixels outside the photo are no data (undistort_photo)
                mask = str(Path("masks") / (p.photo.stem + ".png"))
                write_image(tmp / mask, seen.astype(np.uint8) * np.uint8(255), bits=8)
            intr = p.lens.pinhole()
        else:
            intr = p.lens.pinhole() if undistort else p.lens.opencv_intrinsics(f"camera {p.label}")
            _copy_file(p.photo, tmp / rel, copy_mode)
        fired = p.photo.name not in marked
        light = None if colocated is None else colocated_light(p.r, p.t, float(colocated), fired=fired)
        saturation = None if p.photo.suffix.lower() in FLOAT_EXTS else 1.0
        fextra = {"label": p.label, **({"sensor": p.sensor} if p.sensor else {}), **({} if fired else {NO_FLASH_KEY: True})}
        frames.append(Frame(file_path=str(rel), R=p.r, t=p.t, intrinsics=intr, light=light, saturation=saturation,
                            mask_path=mask, extra=fextra))
    if any(f.mask_path for f in frames):
        # these masks mark the pixels that have data, not the object: the mesh stage must not carve a hull from them
        extra = {**extra, MASK_KIND_KEY: VALID_PIXELS}
    write_capture(Capture(root=tmp, frames=frames, extra=extra), tmp)
    return frames


def similarity_matrix(rotation: np.ndarray, translation: np.ndarray, scale: float) -> np.ndarray:
    """4x4 [s R | t] (x -> s R x + t)."""
    m = np.eye(4)
    m[:3, :3] = float(scale) * np.asarray(rotation, dtype=np.float64)
    m[:3, 3] = np.asarray(translation, dtype=np.float64)
    return m


def pose_from_camera_to_world(c2w: np.ndarray, where: str, path: Path) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera (R, t) from a 4x4 camera-to-world similarity (OpenCV camera axes); the similarity's scale
    (a chunk's) is divided out of the rotation part, which must then be a rotation."""
    m = np.asarray(c2w, dtype=np.float64)
    a = m[:3, :3]
    s = np.cbrt(np.linalg.det(a))
    if not (np.isfinite(s) and s > 0):
        raise InputError(f"{where}: the camera transform is singular or mirrored", path, "re-export the cameras")
    rot = a / s
    if np.abs(rot.T @ rot - np.eye(3)).max() > 1e-5:
        raise InputError(f"{where}: the camera transform is not a rotation and a scale", path, "re-export the cameras")
    r = rot.T
    return r, -r @ m[:3, 3]


def check_photos_out(out: Path, photos: Path) -> None:
    """The output folder must not be the photo folder (it is replaced as a whole)."""
    if out.resolve() == photos.resolve():
        raise InputError("the output folder is the photo folder", out, "choose another -o folder")


def summary_lines(sensors: dict[str, dict], used: int, skipped: dict[str, list[str]]) -> str:
    """One printable line per sensor and per kind of skipped camera (the import's summary)."""
    lines = [f"sensor {k}: {v['cameras']} camera(s), calibration {v['calibration']}, photos {v['photos']} "
             f"(x{v['scale']:.4g})" for k, v in sensors.items()]
    lines += [f"skipped {len(v)} {k} camera(s): {', '.join(v[:8])}{' ...' if len(v) > 8 else ''}"
              for k, v in skipped.items() if v]
    lines.append(f"{used} camera(s) imported")
    return "\n".join(lines)

