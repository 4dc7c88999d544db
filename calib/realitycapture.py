"""RealityCapture / RealityScan cameras (XMP sidecars, ``xcr:`` namespace) -> a capture folder.

``texstream import realitycapture XMP_FOLDER PHOTOS -o OUT``: one ``NAME.xmp`` per photo (Alignment > Export >
Registration > Metadata (XMP)), in PHOTOS or in a folder of their own; the photo is found by the XMP's name.

The conventions. RealityCapture's support article "RealityCapture XMP Camera Math" (its opening, the part we
could read) gives the pose and the frame of the image coordinates; the rest comes from public XMP readers and
writers, and is NOT verified against a file RealityCapture wrote:

- ``xcr:Rotation``: 3x3 row-major world-to-camera rotation R; ``xcr:Position``: the camera centre C in world
  coordinates, so t = -R C (the article: x = [R | t] X). Camera axes: x right, y down, z forward (OpenCV;
  camorph reads them so).
- intrinsics in units of the image's larger side (the article: image coordinates in <-0.5, 0.5>): focal length
  ``f = FocalLength35mm / 36`` of it (nerfstudio's and EasyVolcap's readers), the principal point
  ``(PrincipalPointU, PrincipalPointV)`` an offset from the image centre in the same unit (camorph and a
  Meshroom XMP reader; EasyVolcap's writer divides V by the height instead, which differs for V on non-square
  photos): ``fx = fy = f * max(w, h)``, ``cx = w / 2 + U * max(w, h)``, ``cy = h / 2 + V * max(w, h)``. Being
  relative, they hold for the photos at any export size.
- ``xcr:DistortionModel`` / ``xcr:DistortionCoeficients`` (sic): six slots ``k1 k2 k3 k4 t1 t2`` on the
  normalized coordinates x/z, y/z. ``brown3`` (k1..k3), ``brown4`` (k1..k4), ``brown3t2`` / ``brown4t2`` (with
  tangential terms), ``perspective`` (none). Like Metashape, the photogrammetric Brown order puts t1 on x's
  (r2 + 2 x^2) term: **OpenCV p1 = t2, p2 = t1** (EasyVolcap's and camorph's converters swap them so).
- ``xcr:Skew`` other than 0, ``xcr:AspectRatio`` other than 1 and the ``division`` model with a nonzero
  coefficient are refused: their exact use is not documented where we could read it.
- An XMP without ``Rotation`` or ``Position`` (a calibration-only sidecar, or a camera that did not align) is
  skipped with a printed line. ``xcr:Coordinates`` (absolute or relative) and ``xcr:PosePrior`` are recorded;
  every camera of one export is taken in the one frame its positions are written in.

The "Internal/External camera parameters" CSV (``#name,x,y,alt,heading,pitch,roll,f,px,py,...``) is refused with
a pointer to the XMP export: its Euler-angle order and the unit of px, py are not documented (nerfstudio's reader
guesses both), so cameras read from it could be wrong without any sign.
"""

from __future__ import annotations

import dataclasses
import os
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from texstream.capture.conventions import is_rotation
from texstream.capture.imageio import image_size
from texstream.core.config import option, save_config
from texstream.core.errors import InputError
from texstream.core.outputs import StageResult, atomic_output_dir

from .no_flash import NO_FLASH_HELP
from .posed_import import (LensCamera, PosedPhoto, check_photos_out, find_photo, photo_index, summary_lines,
                           write_posed_capture)

XCR = "http://www.capturingreality.com/ns/xcr/1.1#"
FIX_EXPORT = "export the registration from RealityCapture as Metadata (XMP) with poses"
DISTORTION_MODELS = ("perspective", "brown3", "brown4", "brown3t2", "brown4t2", "division")


@dataclasses.dataclass
class RealityCaptureImportConfig:
    """Options of ``texstream import realitycapture``."""

    undistort: bool = option(True, help="resample the photos onto pinhole cameras through the exact lens model "
                                        "(the fit renders pinhole cameras); off: copy them and keep the distortion "
                                        "in capture.json (OpenCV k1 k2 p1 p2 k3)")
    copy_mode: str = option("copy", help="how photos that need no resampling reach the capture folder",
                            choices=("copy", "hardlink", "symlink"))
    colocated_light: float | None = option(None, help="photos lit by a flash at the camera: its intensity (a point "
                                                      "light at each camera centre, in the export's world units)",
                                                      min=1e-12)
    no_flash: str | None = option(None, help=NO_FLASH_HELP + " (calib/no_flash.py); those photos' flash gets "
                                  "intensity 0")
    overwrite: bool = option(True, help="replace an existing output folder")


def _fields(path: Path) -> dict[str, str]:
    """The xcr: values of an XMP, whether written as attributes of rdf:Description or as child elements."""
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as e:
        raise InputError(f"not a readable XMP file ({e})", path, FIX_EXPORT) from None
    out: dict[str, str] = {}
    for el in root.iter():
        for k, v in el.attrib.items():
            if k.startswith("{" + XCR + "}"):
                out[k[len(XCR) + 2:]] = v
        if el.tag.startswith("{" + XCR + "}") and el.text and el.text.strip():
            out[el.tag[len(XCR) + 2:]] = el.text.strip()
    if not out:
        raise InputError("has no RealityCapture (xcr:) camera fields", path, FIX_EXPORT)
    return out


def _floats(fields: dict, key: str, n: int | None, path: Path, default: str | None = None) -> np.ndarray:
    text = fields.get(key, default)
    if text is None:
        raise InputError(f"lacks xcr:{key}", path, FIX_EXPORT)
    try:
        v = np.array([float(x) for x in text.replace(",", " ").split()], dtype=np.float64)
    except ValueError:
        v = np.zeros(0)
    if (n is not None and v.size != n) or v.size == 0 or not np.all(np.isfinite(v)):
        raise InputError(f"xcr:{key} {text!r} is not {n or 'some'} finite number(s)", path, FIX_EXPORT)
    return v


def xmp_lens(fields: dict, width: int, height: int, path: Path) -> LensCamera:
    """The lens of one XMP on a ``width`` x ``height`` photo (module doc)."""
    skew = float(_floats(fields, "Skew", 1, path, "0")[0])
    aspect = float(_floats(fields, "AspectRatio", 1, path, "1")[0])
    if skew != 0.0 or abs(aspect - 1.0) > 1e-9:
        raise InputError(f"xcr:Skew {skew:g} / xcr:AspectRatio {aspect:g}: only skew 0 and aspect ratio 1 are "
                         "supported", path, "align with square pixels and no skew (the RealityCapture defaults)")
    model = fields.get("DistortionModel", "perspective").strip().lower()
    if model not in DISTORTION_MODELS:
        raise InputError(f"xcr:DistortionModel {model!r} is not one of {', '.join(DISTORTION_MODELS)}", path,
                         "choose a Brown model in RealityCapture's alignment settings and export again")
    c = np.zeros(6)
    if "DistortionCoeficients" in fields:
        v = _floats(fields, "DistortionCoeficients", None, path)
        c[:min(6, v.size)] = v[:6]
    if model == "division":
        if np.any(c != 0):
            raise InputError("the division distortion model is not supported", path,
                             "choose a Brown model in RealityCapture's alignment settings and export again")
        c[:] = 0
    # what each model uses of the six slots k1 k2 k3 k4 t1 t2
    used = {"perspective": 0, "division": 0, "brown3": 3, "brown4": 4}.get(model)
    if used is not None:
        c[used:] = 0
    elif model == "brown3t2":
        c[3] = 0
    scale = max(width, height)
    f = float(_floats(fields, "FocalLength35mm", 1, path)[0]) / 36.0 * scale
    if not f > 0:
        raise InputError("xcr:FocalLength35mm is not positive", path, FIX_EXPORT)
    u0 = float(_floats(fields, "PrincipalPointU", 1, path, "0")[0])
    v0 = float(_floats(fields, "PrincipalPointV", 1, path, "0")[0])
    return LensCamera(width=width, height=height, fx=f, fy=f, cx=width / 2 + u0 * scale, cy=height / 2 + v0 * scale,
                      k1=c[0], k2=c[1], k3=c[2], k4=c[3], p1=c[5], p2=c[4])  # OpenCV p1 = t2, p2 = t1


def xmp_pose(fields: dict, path: Path) -> tuple[np.ndarray, np.ndarray] | None:
    """World-to-camera (R, t) of an XMP, or None when it carries no pose."""
    if "Rotation" not in fields or "Position" not in fields:
        return None
    r = _floats(fields, "Rotation", 9, path).reshape(3, 3)
    if not is_rotation(r, tol=1e-5):
        raise InputError("xcr:Rotation is not a rotation matrix", path, FIX_EXPORT)
    c = _floats(fields, "Position", 3, path)
    return r, -r @ c


def _refuse_csv(src: Path) -> None:
    if src.is_file() and src.suffix.lower() in (".csv", ".txt"):
        raise InputError("RealityCapture's CSV camera export is not supported (its rotation order and principal "
                         "point units are not documented)", src,
                         "export the registration as Metadata (XMP) and pass the folder of .xmp files")


def import_realitycapture(xmps: str | os.PathLike, photos: str | os.PathLike, out: str | os.PathLike,
                          config: RealityCaptureImportConfig | None = None, log=print) -> StageResult:
    """RealityCapture XMP sidecars and their photos -> a capture folder (module doc for the conventions).

    Args:
        xmps: a folder of ``NAME.xmp`` files (it may be the photo folder) or one .xmp file.
        photos: the folder holding the photos (any extension; ``NAME.*`` for ``NAME.xmp``).
        out: the capture folder to write (atomically): capture.json, images/, import_config.json.
        config: options.
        log: where the notes on skipped cameras and the summary go.
    """
    cfg = config or RealityCaptureImportConfig()
    src, photo_dir, out = Path(xmps), Path(photos), Path(out)
    _refuse_csv(src)
    if src.is_dir():
        files = sorted(f for f in src.iterdir() if f.is_file() and f.suffix.lower() == ".xmp")
    elif src.is_file() and src.suffix.lower() == ".xmp":
        files = [src]
    else:
        raise InputError("no RealityCapture XMP file or folder", src, "pass the folder of .xmp files RealityCapture wrote")
    if not files:
        raise InputError("the folder holds no .xmp files", src, FIX_EXPORT)
    check_photos_out(out, photo_dir)
    index = photo_index(photo_dir)
    posed, skipped, kinds = [], {"without a pose": []}, {}
    sizes: dict[str, int] = {}
    for f in files:
        fields = _fields(f)
        pose = xmp_pose(fields, f)
        if pose is None:
            skipped["without a pose"].append(f.stem)
            log(f"realitycapture: {f.name} skipped (no xcr:Rotation / xcr:Position: not aligned)")
            continue
        photo = find_photo(index, f.stem, photo_dir, f.name)
        w, h, _ = image_size(photo)
        lens = xmp_lens(fields, w, h, f)
        posed.append(PosedPhoto(label=f.stem, photo=photo, r=pose[0], t=pose[1], lens=lens,
                                sensor=fields.get("CalibrationGroup", "")))
        sizes[f"{w}x{h}"] = sizes.get(f"{w}x{h}", 0) + 1
        key = (fields.get("DistortionModel", "perspective"), fields.get("Coordinates", "?"),
               fields.get("PosePrior", "?"))
        kinds[key] = kinds.get(key, 0) + 1
    if not posed:
        raise InputError("none of the XMP files carries a camera pose", src, FIX_EXPORT)
    extra = {"source": {"format": "realitycapture", "xmp": str(src.resolve()), "photos": str(photo_dir.resolve())},
             "intrinsics_source": "realitycapture", "undistorted": bool(cfg.undistort),
             "xmp_kinds": [{"distortion_model": k[0], "coordinates": k[1], "pose_prior": k[2], "cameras": n}
                           for k, n in kinds.items()]}
    with atomic_output_dir(out, overwrite=cfg.overwrite) as tmp:
        write_posed_capture(tmp, posed, undistort=cfg.undistort, copy_mode=cfg.copy_mode,
                            colocated=cfg.colocated_light, extra=extra, no_flash=cfg.no_flash)
        save_config(cfg, tmp / "import_config.json")
    groups = {f"{m} ({c} coordinates)": {"cameras": n, "calibration": "relative (XMP)", "photos": ", ".join(sizes),
                                         "scale": 1.0} for (m, c, _), n in kinds.items()}
    log(summary_lines(groups, len(posed), skipped))
    return StageResult(output=out, summary={"cameras": len(posed), "without_pose": len(skipped["without a pose"]),
                                            "skipped": skipped, "photo_sizes": sizes, "kinds": extra["xmp_kinds"],
                                            "undistorted": bool(cfg.undistort)})
