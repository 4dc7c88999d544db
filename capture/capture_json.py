"""The capture folder: ``capture.json`` beside ``images/`` (and optional ``masks/``).

``capture.json`` is a nerfstudio ``transforms.json``: intrinsics at the top level or per frame
(``fl_x, fl_y, cx, cy, w, h, camera_model`` and OpenCV distortion ``k1 k2 k3 k4 p1 p2``),
``frames[*].file_path`` relative to the folder and ``frames[*].transform_matrix`` camera-to-world
in OpenGL axes. texstream adds optional per-frame fields (DESIGN.md):

- ``light``: ``{"type": "point", "position": [x,y,z], "intensity": [r,g,b]}`` or
  ``{"type": "directional", "direction": [x,y,z], "intensity": [r,g,b]}``
- ``exposure``: linear scale, pixel = exposure * radiance (default 1)
- ``mask_path``: mask image, nonzero = object (default none); when the top-level ``mask_kind`` is
  ``"valid_pixels"`` (photos undistorted by an import) nonzero means only "this pixel has data": the fit and
  stereo use such masks, the visual hull does not (:func:`masks_are_silhouettes`)
- ``saturation``: pixel value at or above which a sample is clipped (default none)
- ``no_flash``: true for a photo taken with the flash off (a flash/no-flash pair's second photo, issue 39): the
  stages that put the flash at the camera give it intensity 0, so it sees the room's light alone
  (:func:`flash_fired`)

and an optional top-level ``response``: the inverse response of the 8- and 16-bit photos (code value to linear
radiance, from a colour checker; :mod:`texstream.capture.response`); absent, they are decoded as sRGB.

Unknown keys are kept and written back, so nerfstudio's own fields survive a round trip.
Conventions are in :mod:`texstream.capture.conventions`. This module imports only numpy (OpenImageIO only when
:meth:`Capture.within_mask` reads a mask, inside capture/imageio.py).
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Any

import numpy as np

from texstream.core.errors import InputError
from texstream.core.outputs import read_json, write_json_atomic

from .conventions import c2w_gl_to_w2c_cv, camera_center, is_rotation, w2c_cv_to_c2w_gl
from .imageio import read_mask
from .response import RESPONSE_KEY, PhotoResponse, response_from_json

CAPTURE_FILE = "capture.json"
NO_FLASH_KEY = "no_flash"
"""a frame's field marking a photo taken with the flash off (module doc)"""
MASK_KIND_KEY = "mask_kind"
VALID_PIXELS = "valid_pixels"
_INTRINSIC_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h")
_DIST_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")
CAMERA_MODELS = ("PINHOLE", "SIMPLE_PINHOLE", "OPENCV", "SIMPLE_RADIAL", "RADIAL", "OPENCV_FISHEYE")
"""the camera models a capture may name (read case-insensitively); another (nerfstudio's EQUIRECTANGULAR, ...)
would be read as a pinhole camera and fitted wrong, so it is refused"""
MAX_IMAGE_SIDE = 1 << 20
"""the largest w or h accepted (a million pixels a side: above any camera; a larger value is a broken file)"""


@dataclasses.dataclass
class Intrinsics:
    """Pinhole intrinsics in the capture pixel convention (pixel centres at +0.5)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    camera_model: str = "PINHOLE"
    distortion: dict[str, float] = dataclasses.field(default_factory=dict)

    @property
    def is_pinhole(self) -> bool:
        return all(abs(v) == 0.0 for v in self.distortion.values())

    def matrix(self) -> np.ndarray:
        """3x3 K in the capture convention."""
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])

    def to_json(self) -> dict:
        d = {"camera_model": self.camera_model, "fl_x": self.fx, "fl_y": self.fy, "cx": self.cx,
             "cy": self.cy, "w": int(self.width), "h": int(self.height)}
        d.update({k: float(v) for k, v in self.distortion.items()})
        return d


@dataclasses.dataclass
class Light:
    """A point or directional light (see conventions)."""

    type: str
    intensity: np.ndarray
    position: np.ndarray | None = None
    direction: np.ndarray | None = None

    @staticmethod
    def point(position, intensity) -> "Light":
        return Light("point", _vec3(intensity), position=_vec3(position))

    @staticmethod
    def directional(direction, intensity) -> "Light":
        d = _vec3(direction)
        if not np.linalg.norm(d) > 0:
            raise ValueError(f"direction {direction!r} has zero length")
        return Light("directional", _vec3(intensity), direction=d / np.linalg.norm(d))

    def to_json(self) -> dict:
        d: dict[str, Any] = {"type": self.type, "intensity": [float(x) for x in self.intensity]}
        if self.type == "point":
            d["position"] = [float(x) for x in self.position]
        else:
            d["direction"] = [float(x) for x in self.direction]
        return d


@dataclasses.dataclass
class Frame:
    """One photo: its file, pose (world-to-camera R, t in OpenCV axes), intrinsics and light."""

    file_path: str
    R: np.ndarray
    t: np.ndarray
    intrinsics: Intrinsics
    light: Light | None = None
    exposure: float = 1.0
    mask_path: str | None = None
    saturation: float | None = None
    extra: dict = dataclasses.field(default_factory=dict)

    @property
    def center(self) -> np.ndarray:
        return camera_center(self.R, self.t)

    @property
    def name(self) -> str:
        return Path(self.file_path).stem


@dataclasses.dataclass
class Capture:
    """A posed capture: frames plus the folder they live in."""

    root: Path
    frames: list[Frame]
    extra: dict = dataclasses.field(default_factory=dict)

    def image_path(self, frame: Frame) -> Path:
        return self.root / frame.file_path

    def mask_path(self, frame: Frame) -> Path | None:
        return None if frame.mask_path is None else self.root / frame.mask_path

    def within_mask(self, frame: Frame, mask: np.ndarray) -> np.ndarray:
        """``mask`` (a render's foreground, bool) where ``frame``'s mask file says object, when it has one: the
        pixels a render is scored on (fit, eval, report)."""
        path = self.mask_path(frame)
        if path is None or not path.exists():
            return mask
        return mask & read_mask(path, mask.shape)

    @property
    def has_lights(self) -> bool:
        return bool(self.frames) and all(f.light is not None for f in self.frames)

    @property
    def response(self) -> PhotoResponse | None:
        """The integer photos' response (``extra["response"]``, kept there so that every stage copying a
        capture's extra keeps it), or None: sRGB."""
        d = self.extra.get(RESPONSE_KEY)
        return None if d is None else response_from_json(d, self.root / CAPTURE_FILE)


def _vec3(v) -> np.ndarray:
    a = np.asarray(v, dtype=np.float64).reshape(-1)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise ValueError(f"expected 3 finite numbers, got {v!r}")
    return a


def _number(v: Any) -> float:
    """float(v), or NaN when v is not a number (so callers report it as bad input)."""
    if isinstance(v, bool):
        return float("nan")
    try:
        return float(v)
    except (TypeError, ValueError):
        return float("nan")


def _intrinsics_from(d: dict, fallback: Intrinsics | None, where: str, path: Path) -> Intrinsics:
    present = [k for k in _INTRINSIC_KEYS if k in d]
    if not present and fallback is not None:
        return fallback
    base = fallback.to_json() if fallback is not None else {}
    merged = {**base, **{k: d[k] for k in (*_INTRINSIC_KEYS, *_DIST_KEYS, "camera_model") if k in d}}
    missing = [k for k in _INTRINSIC_KEYS if k not in merged]
    if missing:
        raise InputError(f"{where} lacks intrinsics field(s) {missing}", path,
                         "give fl_x, fl_y, cx, cy, w, h at the top level or in every frame")
    values = {k: _number(merged[k]) for k in (*_INTRINSIC_KEYS, *_DIST_KEYS) if k in merged}
    bad = [k for k, v in values.items() if not np.isfinite(v)]
    if bad:
        listed = ", ".join(f"{k}={merged[k]!r}" for k in bad)
        raise InputError(f"{where} has non-numeric or non-finite intrinsics {listed}", path, "write finite numbers")
    size = [k for k in ("w", "h") if not (values[k] == int(values[k]) and 0 < values[k] <= MAX_IMAGE_SIDE)]
    if size or not (values["fl_x"] > 0 and values["fl_y"] > 0):
        wrong = ", ".join(f"{k}={merged[k]!r}" for k in size + [k for k in ("fl_x", "fl_y") if not values[k] > 0])
        raise InputError(f"{where} has non-positive or invalid {wrong}: w and h must be whole numbers in "
                         f"1..{MAX_IMAGE_SIDE}, fl_x and fl_y positive", path, "check the intrinsics")
    default_model = "OPENCV" if any(k in merged for k in _DIST_KEYS) else "PINHOLE"
    model = merged.get("camera_model", default_model)
    if not isinstance(model, str) or model.upper() not in CAMERA_MODELS:
        raise InputError(f"{where} camera_model {model!r} is not one of {list(CAMERA_MODELS)}", path,
                         "undistort the photos to a pinhole camera, or write one of these models")
    return Intrinsics(width=int(values["w"]), height=int(values["h"]), fx=values["fl_x"], fy=values["fl_y"],
                      cx=values["cx"], cy=values["cy"], camera_model=model.upper(),
                      distortion={k: values[k] for k in _DIST_KEYS if k in values})


def _light_from(d: Any, where: str, path: Path) -> Light:
    try:
        kind = d["type"]
        if kind == "point":
            return Light.point(d["position"], d["intensity"])
        if kind == "directional":
            return Light.directional(d["direction"], d["intensity"])
    except (KeyError, TypeError, ValueError) as e:
        raise InputError(f"{where} has a malformed light ({e!r})", path,
                         'use {"type": "point", "position": [..], "intensity": [r,g,b]}') from None
    raise InputError(f"{where} light type {kind!r} is not 'point' or 'directional'", path,
                     "use a point or directional light")


_LAST_ROW = np.array([0.0, 0.0, 0.0, 1.0])


def read_capture(folder: str | os.PathLike) -> Capture:
    """Read ``capture.json`` (or a nerfstudio ``transforms.json``) from a folder or file path.

    Raises:
        InputError: missing file or field, non-rigid transform, bad light; the message names the file.
    """
    p = Path(folder)
    if p.is_dir():
        path = p / CAPTURE_FILE
        if not path.exists() and (p / "transforms.json").exists():
            path = p / "transforms.json"
    else:
        path = p
    data = read_json(path, what="capture file")
    if not isinstance(data, dict) or not isinstance(data.get("frames"), list):
        raise InputError("has no 'frames' list", path, "write a nerfstudio transforms.json with frames")
    if not data["frames"]:
        raise InputError("has an empty 'frames' list", path, "add at least one frame")
    top = None
    if any(k in data for k in _INTRINSIC_KEYS):
        top = _intrinsics_from(data, None, "top level", path)
    frames = []
    for i, fd in enumerate(data["frames"]):
        where = f"frames[{i}]"
        if not isinstance(fd, dict) or "file_path" not in fd:
            raise InputError(f"{where} lacks 'file_path'", path, "give each frame its image path")
        for key in ("file_path", "mask_path"):
            value = fd.get(key)
            if not (isinstance(value, str) and value.strip()) and (key == "file_path" or value is not None):
                raise InputError(f"{where} {key} {value!r} is not a path", path,
                                 f"write the {'image' if key == 'file_path' else 'mask'} path relative to the folder")
        if "transform_matrix" not in fd:
            raise InputError(f"{where} lacks 'transform_matrix'", path, "give each frame a 4x4 camera-to-world matrix")
        try:
            m = np.asarray(fd["transform_matrix"], dtype=np.float64)
        except (TypeError, ValueError):
            m = np.zeros(0)
        if m.shape not in ((4, 4), (3, 4)) or not np.all(np.isfinite(m)):
            raise InputError(f"{where} transform_matrix is not a finite 4x4 matrix", path, "write a 4x4 camera-to-world matrix")
        if m.shape == (4, 4) and np.abs(m[3] - _LAST_ROW).max() > 1e-6:
            raise InputError(f"{where} transform_matrix last row is {m[3].tolist()}, not [0, 0, 0, 1]", path,
                             "write a rigid 4x4 camera-to-world matrix")
        if not is_rotation(m[:3, :3], tol=1e-3):
            raise InputError(f"{where} transform_matrix is not a rigid transform (rotation part not orthonormal with det +1)",
                             path, "remove scale/shear from the camera-to-world matrix")
        r, t = c2w_gl_to_w2c_cv(m)
        intr = _intrinsics_from(fd, top, where, path)
        light = _light_from(fd["light"], where, path) if fd.get("light") is not None else None
        exposure = _number(fd.get("exposure", 1.0))
        if not (np.isfinite(exposure) and exposure > 0):
            raise InputError(f"{where} exposure {fd.get('exposure')!r} is not a positive number", path,
                             "use a positive linear scale")
        sat = fd.get("saturation")
        if sat is not None and not np.isfinite(_number(sat)):
            raise InputError(f"{where} saturation {sat!r} is not a number", path,
                             "give the pixel value at which the camera clips, or leave it out")
        known = {"file_path", "transform_matrix", "light", "exposure", "mask_path", "saturation",
                 *_INTRINSIC_KEYS, *_DIST_KEYS, "camera_model"}
        frames.append(Frame(file_path=str(fd["file_path"]), R=r, t=t, intrinsics=intr, light=light,
                            exposure=exposure, mask_path=fd.get("mask_path"),
                            saturation=None if sat is None else float(sat),
                            extra={k: v for k, v in fd.items() if k not in known}))
    extra = {k: v for k, v in data.items() if k != "frames" and k not in (*_INTRINSIC_KEYS, *_DIST_KEYS, "camera_model")}
    if extra.get(RESPONSE_KEY) is not None:
        response_from_json(extra[RESPONSE_KEY], path)  # bad values fail here, naming the file, not in a reader
    return Capture(root=path.parent, frames=frames, extra=extra)


def capture_to_json(capture: Capture) -> dict:
    """The JSON document for a capture; shared intrinsics go to the top level (nerfstudio style)."""
    intr0 = capture.frames[0].intrinsics.to_json() if capture.frames else {}
    shared = all(f.intrinsics.to_json() == intr0 for f in capture.frames)
    doc: dict[str, Any] = dict(capture.extra)
    if shared:
        doc.update(intr0)
    frames = []
    for f in capture.frames:
        fd: dict[str, Any] = {"file_path": f.file_path,
                              "transform_matrix": w2c_cv_to_c2w_gl(f.R, f.t).tolist()}
        if not shared:
            fd.update(f.intrinsics.to_json())
        if f.light is not None:
            fd["light"] = f.light.to_json()
        if f.exposure != 1.0:
            fd["exposure"] = float(f.exposure)
        if f.mask_path is not None:
            fd["mask_path"] = f.mask_path
        if f.saturation is not None:
            fd["saturation"] = float(f.saturation)
        fd.update(f.extra)
        frames.append(fd)
    doc["frames"] = frames
    return doc


def write_capture(capture: Capture, folder: str | os.PathLike | None = None) -> Path:
    """Write ``capture.json`` atomically into ``folder`` (default: ``capture.root``)."""
    root = Path(folder) if folder is not None else capture.root
    path = root / CAPTURE_FILE
    write_json_atomic(path, capture_to_json(capture))
    return path


def flash_fired(frame: Frame) -> bool:
    """Whether the camera's flash fired for this photo (False: a frame marked ``no_flash``, module doc)."""
    return frame.extra.get(NO_FLASH_KEY) is not True


def no_flash_frames(frames: list[Frame]) -> list[Frame]:
    """The frames taken with the flash off."""
    return [f for f in frames if not flash_fired(f)]


def masks_are_silhouettes(capture: "Capture") -> bool:
    """Whether the capture's masks outline the object (a visual hull may be carved from them), not merely the
    pixels that have data (``mask_kind`` ``valid_pixels``, module doc)."""
    return capture.extra.get(MASK_KIND_KEY) != VALID_PIXELS


def split_holdout(frames: list, every: int) -> tuple[list, list]:
    """(fitted, held out): every ``every``-th frame (the 8th, 16th, ... for 8) is held out; 0 = none.
    The one rule the fit, its evaluation and the photometric refinement hold photos out by."""
    if every <= 0:
        return list(frames), []
    held = [f for i, f in enumerate(frames) if i % every == every - 1]
    return [f for i, f in enumerate(frames) if i % every != every - 1], held
