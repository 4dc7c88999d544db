"""Convert a Middlebury multi-view stereo set (``*_par.txt`` cameras) into a capture folder.

The Middlebury sets (Seitz et al. 2006: temple, dino; full, ring and sparse ring) give one line
per image in ``<set>_par.txt`` after a first line with the count::

    imgname.png k11 k12 k13 k21 k22 k23 k31 k32 k33 r11 r12 r13 r21 r22 r23 r31 r32 r33 t1 t2 t3

The projection of a world point X is K [R | t] X: (R, t) is world-to-camera in OpenCV axes (x right,
y down, looking down +z) with the image origin at the top left and pixel centres at integers, so
only the principal point changes (+0.5, :func:`conventions.opencv_principal_point_to_capture`).
World units are metres. The README beside the images gives a tight bounding box, which is kept in
``capture.json`` (``bounding_box``) and used to clip the masks.

Masks: the objects stand in front of a black backdrop with a dark cloth, so a pixel is object
when its brightest 8-bit channel exceeds ``mask_threshold`` (default 40: the cloth reaches about
65 at places, the lit plaster is mostly above 100), inside the projected bounding box (when
known, grown by ``mask_margin`` pixels), after a 3x3 opening and dropping specks smaller than 1%
of the largest region. The masks are conservative outlines for rejecting background samples,
not mattes.
"""

from __future__ import annotations

import dataclasses
import itertools
import re
import shutil
from pathlib import Path

import numpy as np

from texstream.core.errors import InputError
from texstream.core.config import option, save_config
from texstream.core.outputs import StageResult, atomic_output_dir

from . import conventions
from .capture_json import Capture, Frame, Intrinsics, write_capture
from .imageio import _read_raw, image_size, write_image

STAGE = "import"


@dataclasses.dataclass
class MiddleburyImportConfig:
    """Options for :func:`import_middlebury`."""

    par_file: str | None = option(None, help="camera file inside SRC (default: the only *_par.txt there)")
    make_masks: bool = option(True, help="write object masks by thresholding the black background")
    mask_threshold: int = option(
        40, help="8-bit code above which a pixel's brightest channel counts as object", min=0, max=255)
    mask_clip_to_bbox: bool = option(
        True, help="keep mask pixels only inside the projected README bounding box")
    mask_margin: int = option(4, help="pixels the projected bounding box is grown by before clipping masks",
                              min=0)
    overwrite: bool = option(True, help="replace an existing output folder")


def _find_par_file(src: Path, config: MiddleburyImportConfig) -> Path:
    if config.par_file:
        p = Path(config.par_file)
        p = p if p.is_absolute() else src / p
        if not p.is_file():
            raise InputError("camera file not found", p,
                             "pass --par-file naming a *_par.txt in the source folder")
        return p
    found = sorted(src.glob("*_par.txt"))
    if not found:
        raise InputError("no *_par.txt camera file in the folder", src,
                         "point at a Middlebury set folder (e.g. templeSparseRing) holding <set>_par.txt")
    if len(found) > 1:
        raise InputError(f"several camera files ({', '.join(f.name for f in found)})", src,
                         "choose one with --par-file")
    return found[0]


def parse_par_file(path: str | Path) -> list[tuple[str, np.ndarray, np.ndarray, np.ndarray]]:
    """Parse a Middlebury ``*_par.txt``.

    Returns:
        One (image name, K (3, 3), R (3, 3), t (3,)) per image, in file order; K in the
        Middlebury / OpenCV pixel convention (pixel centres at integers), (R, t) world-to-camera.

    Raises:
        InputError: wrong count, wrong number of values, non-numeric values, non-rotation R.
    """
    path = Path(path)
    lines = [ln.split() for ln in path.read_text().splitlines() if ln.strip()]
    if not lines:
        raise InputError("camera file is empty", path, "use a Middlebury *_par.txt")
    try:
        count = int(lines[0][0])
    except ValueError:
        raise InputError(f"first line {' '.join(lines[0])!r} is not the image count", path,
                         "use a Middlebury *_par.txt (first line: number of images)") from None
    rows = lines[1:]
    if len(rows) != count:
        raise InputError(f"first line says {count} images but {len(rows)} follow", path, "repair the file")
    out = []
    for i, row in enumerate(rows, start=2):
        if len(row) != 22:
            raise InputError(f"line {i} has {len(row)} fields, expected 22 (name + K(9) + R(9) + t(3))", path,
                             "repair the file")
        try:
            v = np.array([float(x) for x in row[1:]], dtype=np.float64)
        except ValueError:
            raise InputError(f"line {i} has a non-numeric value", path, "repair the file") from None
        k, r, t = v[:9].reshape(3, 3), v[9:18].reshape(3, 3), v[18:]
        if not np.all(np.isfinite(v)):
            raise InputError(f"line {i} has a non-finite value", path, "repair the file")
        if not conventions.is_rotation(r, tol=1e-4):
            raise InputError(f"line {i} ({row[0]}): R is not a rotation", path, "repair the file")
        if abs(k[0, 1]) > 1e-9 * abs(k[0, 0]) or not np.allclose(k[2], [0, 0, 1]) or abs(k[1, 0]) > 0:
            raise InputError(f"line {i} ({row[0]}): K has skew or is not [[fx 0 cx] [0 fy cy] [0 0 1]]",
                             path, "texstream's pinhole model has no skew; resample the images first")
        out.append((row[0], k, r, t))
    return out


def parse_readme_bbox(readme: str | Path) -> tuple[np.ndarray, np.ndarray] | None:
    """The "(x y z)\\n(x y z)" bounding box from a Middlebury README, or None when absent."""
    p = Path(readme)
    if not p.is_file():
        return None
    text = p.read_text(errors="replace")
    m = re.search(r"bounding box[^\n]*\n\s*\(([^)]*)\)\s*\n\s*\(([^)]*)\)", text, flags=re.IGNORECASE)
    if not m:
        return None
    try:
        a = np.array([float(x) for x in m.group(1).split()])
        b = np.array([float(x) for x in m.group(2).split()])
    except ValueError:
        return None
    if a.shape != (3,) or b.shape != (3,):
        return None
    return np.minimum(a, b), np.maximum(a, b)


def bbox_corners(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """The 8 corners (8, 3) of an axis-aligned box."""
    return np.array([[(lo, hi)[b][k] for k, b in enumerate(bits)]
                     for bits in itertools.product((0, 1), repeat=3)])


def threshold_mask(rgb8: np.ndarray, threshold: int, hull: np.ndarray | None = None,
                   margin: int = 0) -> np.ndarray:
    """Object mask (H, W) bool from an 8-bit image on a dark background (see the module doc).

    Args:
        rgb8: (H, W, C) uint8 stored codes.
        threshold: code above which the brightest channel counts as object.
        hull: optional (N, 2) pixel points (capture convention); nothing outside their convex hull,
            grown by ``margin`` pixels, is object.
        margin: pixels the hull is grown by.
    """
    import cv2

    m = (rgb8[:, :, :3].max(axis=2) > threshold).astype(np.uint8)
    if hull is not None:
        region = np.zeros_like(m)
        # capture pixel coords have centres at +0.5; cv2 polygon vertices index pixel centres
        cv2.fillConvexPoly(region, cv2.convexHull(np.round(hull - 0.5).astype(np.int32)), 1)
        if margin > 0:
            region = cv2.dilate(region, np.ones((2 * margin + 1, 2 * margin + 1), np.uint8))
        m &= region
    m = cv2.morphologyEx(m, cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
    n, labels, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=8)
    if n <= 1:
        return m.astype(bool)
    areas = stats[1:, cv2.CC_STAT_AREA]
    keep = 1 + np.nonzero(areas >= 0.01 * areas.max())[0]
    return np.isin(labels, keep)


def import_middlebury(src_dir: str | Path, out_dir: str | Path,
                      config: MiddleburyImportConfig | None = None) -> StageResult:
    """Convert a Middlebury set folder into a capture folder.

    Writes ``out_dir/capture.json``, ``images/`` (the PNGs copied byte for byte), ``masks/`` (when
    ``config.make_masks``) and ``import_config.json``, atomically: on any error ``out_dir`` is untouched.
    The lamp of the Middlebury gantry is not calibrated, so frames carry no ``light``; the capture
    says ``"lighting": "fixed unknown lamp"``.

    Args:
        src_dir: folder with ``<set>_par.txt`` and the images (and usually ``README.txt``).
        out_dir: capture folder to create.
        config: options (defaults when None).

    Returns:
        StageResult with the frame count, image size and mask count in its summary.
    """
    config = config or MiddleburyImportConfig()
    src = Path(src_dir)
    if not src.is_dir():
        raise InputError("source folder not found", src, "give the folder holding the *_par.txt and images")
    par = _find_par_file(src, config)
    cams = parse_par_file(par)
    bbox = parse_readme_bbox(src / "README.txt")

    frames: list[Frame] = []
    images: list[tuple[Path, str]] = []
    for name, k, r, t in cams:
        img = src / name
        if not img.is_file():
            raise InputError(f"image {name} listed in {par.name} is missing", img,
                             "restore the image or remove its line")
        w, h, _ = image_size(img)
        cx, cy = conventions.opencv_principal_point_to_capture(k[0, 2], k[1, 2])
        intr = Intrinsics(width=w, height=h, fx=float(k[0, 0]), fy=float(k[1, 1]), cx=float(cx), cy=float(cy))
        rel = f"images/{name}"
        frames.append(Frame(file_path=rel, R=r, t=t, intrinsics=intr))
        images.append((img, rel))

    extra: dict = {"lighting": "fixed unknown lamp",
                   "source": {"format": "middlebury", "folder": str(src.resolve()), "cameras": par.name},
                   "units": "metres"}
    if bbox is not None:
        extra["bounding_box"] = {"min": bbox[0].tolist(), "max": bbox[1].tolist(), "source": "README.txt"}

    out = Path(out_dir)
    n_masks = 0
    with atomic_output_dir(out, overwrite=config.overwrite) as tmp:
        (tmp / "images").mkdir()
        for (img, rel), frame in zip(images, frames):
            px, _ = _read_raw(img)  # decode every image once, so a corrupt one fails here
            shutil.copyfile(img, tmp / rel)  # keep the PNG bytes as they are
            if config.make_masks:
                if px.dtype != np.uint8:
                    raise InputError("mask thresholding expects 8-bit images", img, "pass --no-make-masks")
                hull = None
                if bbox is not None and config.mask_clip_to_bbox:
                    uv, z = conventions.project(bbox_corners(*bbox), frame.R, frame.t, frame.intrinsics.fx,
                                                frame.intrinsics.fy, frame.intrinsics.cx, frame.intrinsics.cy)
                    if np.all(z > 0):  # a box straddling the camera plane projects unbounded: skip clipping
                        hull = uv
                mask = threshold_mask(px, config.mask_threshold, hull, config.mask_margin)
                mrel = f"masks/{Path(rel).stem}.png"
                write_image(tmp / mrel, mask.astype(np.float32))
                frame.mask_path = mrel
                n_masks += 1
        capture = Capture(root=out, frames=frames, extra=extra)
        write_capture(capture, tmp)
        save_config(config, tmp / f"{STAGE}_config.json")

    f0 = frames[0].intrinsics
    return StageResult(output=out, summary={"frames": len(frames), "width": f0.width, "height": f0.height,
                                            "masks": n_masks, "bounding_box": bbox is not None,
                                            "source": str(par)})
