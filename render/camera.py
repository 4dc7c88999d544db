"""The camera every kernel reads, and the host side that fills it for a set of photos.

- :class:`ImageInfo`: the one camera struct (pose, pinhole intrinsics, size, light, exposure,
  shadow camera) of the renderer, the depth maps, the fit and the photometric refinement;
- :class:`PhotoFrame`: one photo's camera and light on the host (from a capture.json frame);
- :func:`image_infos` fills every photo's :class:`ImageInfo` (camera, light, shadow camera, crop) in
  one numpy structured array and :func:`struct_array` uploads it in one copy, so a set-up makes no
  host round trip per photo; :func:`pinhole_camera` fills one for a single view;

Conventions (OpenCV camera axes, pixel centres at +0.5, lights) are in
:mod:`texstream.capture.conventions`. Imports only numpy, warp and texstream.core.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import warp as wp

from texstream.core.errors import InputError
from texstream.render.pose import look_at_w2c_batch


@wp.struct
class ImageInfo:
    """A photo's camera as every kernel reads it (float32, world units): world-to-camera pose (OpenCV
    axes, x_cam = rot x_world + trans), camera centre, pinhole intrinsics in pixels (capture convention:
    pixel centres at +0.5) and size; the photo's light (``light_kind`` one of the ``LIGHT_*`` of
    :mod:`texstream.render.shading`), exposure and saturation; and the shadow camera aimed from its
    light (``sh_*``, :func:`image_infos`).

    The one declaration of a camera in texstream: the renderer (:mod:`texstream.render.kernels`), the
    depth and shadow maps (:mod:`texstream.render.visibility`), the fit's passes and the photometric
    refinement all take it. A kernel that needs only the pinhole part reads only those fields
    (:func:`pinhole_camera` fills them)."""

    rot: wp.mat33
    trans: wp.vec3
    center: wp.vec3
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    exposure: float
    saturation: float
    light_kind: int
    light_vec: wp.vec3
    light_intensity: wp.vec3
    has_shadow: int
    sh_rot: wp.mat33
    sh_trans: wp.vec3
    sh_fx: float
    sh_fy: float
    sh_cx: float
    sh_cy: float
    sh_ortho: int
    sh_size: int
    depth_is_mask: int
    """1: the photo has no geometry (single-view fits, fit/common/single_view.py); its depth map
    holds 1 where the photo may be sampled and 0 where masked, and the depth test becomes a mask
    test at the nearest pixel. 0 (the default of a zeroed struct): the depth test above."""


def pinhole_camera(R, t, fx: float, fy: float, cx: float, cy: float, width: int, height: int) -> ImageInfo:
    """One view's :class:`ImageInfo` with its pose, pinhole intrinsics and size set (float32; the
    rest zero: no light, no shadow camera)."""
    cam = ImageInfo()
    cam.rot = wp.mat33(*np.asarray(R, dtype=np.float32).reshape(-1))
    cam.trans = wp.vec3(*np.asarray(t, dtype=np.float32).reshape(3))
    cam.fx, cam.fy, cam.cx, cam.cy = float(fx), float(fy), float(cx), float(cy)
    cam.width, cam.height = int(width), int(height)
    return cam


@dataclasses.dataclass
class PhotoFrame:
    """One photo's camera on the host (what :func:`image_infos` reads): pose (world-to-camera, OpenCV
    axes), intrinsics, light.

    ``light_kind`` is "point", "directional" or "none" (fixed, unknown lighting: only the radiance
    model fits such photos; ``light_vec`` and ``light_intensity`` are then zero)."""

    R: np.ndarray
    t: np.ndarray
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    light_kind: str
    light_vec: np.ndarray
    light_intensity: np.ndarray
    exposure: float = 1.0
    saturation: float = math.inf

    @staticmethod
    def from_capture_frame(frame) -> "PhotoFrame":
        """From a :class:`texstream.capture.capture_json.Frame` (no distortion); a frame without a
        light becomes light_kind "none" (the radiance model's; reflectance models refuse it in
        :class:`StreamProblem`)."""
        intr = frame.intrinsics
        if not intr.is_pinhole:
            raise InputError(f"frame {frame.file_path} has lens distortion", fix="undistort the photos first (texstream register undistorts)")
        if frame.light is None:
            kind, lv, li = "none", np.zeros(3), np.zeros(3)
        else:
            kind = frame.light.type
            lv = np.asarray(frame.light.position if kind == "point" else frame.light.direction, float)
            li = np.asarray(frame.light.intensity, float)
        return PhotoFrame(frame.R, frame.t, intr.fx, intr.fy, intr.cx, intr.cy, intr.width, intr.height,
                          kind, lv, li,
                          float(frame.exposure), math.inf if frame.saturation is None else float(frame.saturation))


LIGHT_KINDS = {"point": 0, "directional": 1, "none": 2}  # render/shading.py LIGHT_*

# shadow cameras are aimed at the bounding sphere from the light (fit/stream/photo_set.py PhotoSet)
_SHADOW_INSIDE = 1.05    # a point light closer than this many radii from the centre gets no shadow map
_SHADOW_FOV_PAD = 1.05   # half-angle padding of a point light's frustum around the sphere
_SHADOW_ORTHO_SPAN = 2.2  # an orthographic (directional) map spans this many radii


def image_infos(frames, crops: np.ndarray | None, center: np.ndarray | None, radius: float,
                shadow_size: int) -> np.ndarray:
    """Every photo's kernel constants as a numpy structured array of ``ImageInfo.numpy_dtype()``.

    Args:
        frames: the photos' :class:`PhotoFrame`s.
        crops: (n, 4) int (x0, y0, width, height) of each photo's stored crop (None: whole photos).
            The camera becomes the crop's: cx, cy less x0, y0 in float32 (exact: an integer taken
            from a float32 of larger magnitude), width and height the crop's.
        center, radius: the object's bounding sphere, where shadow cameras aim (None: no maps).
        shadow_size: shadow map side (0: no shadow cameras).
    """
    n = len(frames)
    a = np.zeros(n, dtype=ImageInfo.numpy_dtype())
    if n == 0:
        return a
    f32 = np.float32
    bad = sorted({fr.light_kind for fr in frames} - set(LIGHT_KINDS))
    if bad:
        raise InputError(f"light kind {bad[0]!r} unknown", fix=f"use one of {sorted(LIGHT_KINDS)}")
    R = np.array([np.asarray(fr.R, np.float64) for fr in frames]).reshape(n, 3, 3)
    t = np.array([np.asarray(fr.t, np.float64) for fr in frames]).reshape(n, 3)
    a["rot"] = R.astype(f32)
    a["trans"] = t.astype(f32)
    a["center"] = (-np.einsum("nji,nj->ni", R, t)).astype(f32)   # camera centre -R^T t
    a["light_vec"] = np.array([np.asarray(fr.light_vec, np.float64) for fr in frames]).reshape(n, 3).astype(f32)
    a["light_intensity"] = np.array([np.asarray(fr.light_intensity, np.float64)
                                     for fr in frames]).reshape(n, 3).astype(f32)
    a["light_kind"] = [LIGHT_KINDS[fr.light_kind] for fr in frames]
    a["fx"] = [fr.fx for fr in frames]
    a["fy"] = [fr.fy for fr in frames]
    a["cx"] = [fr.cx for fr in frames]
    a["cy"] = [fr.cy for fr in frames]
    a["width"] = [fr.width for fr in frames]
    a["height"] = [fr.height for fr in frames]
    a["exposure"] = [fr.exposure for fr in frames]
    a["saturation"] = [min(fr.saturation, 3.0e38) for fr in frames]
    if crops is not None:
        crop_infos(a, crops)
    if shadow_size > 0 and center is not None and n:
        _shadow_cameras(a, frames, np.asarray(center, np.float64), radius, shadow_size)
    return a


def crop_infos(a: np.ndarray, crops: np.ndarray) -> None:
    """Make records of :func:`image_infos` the cameras of the photos' crops (n, 4) (x0, y0, width,
    height): cx, cy less x0, y0 in float32, exact (an integer taken from a float32 of larger
    magnitude), and the crop's size."""
    a["cx"] -= crops[:, 0].astype(np.float32)
    a["cy"] -= crops[:, 1].astype(np.float32)
    a["width"], a["height"] = crops[:, 2], crops[:, 3]


def struct_array(records: np.ndarray, dtype, device: str) -> wp.array:
    """A Warp array of structs from a numpy structured array of ``dtype.numpy_dtype()``, one memory
    copy (``wp.array`` of a structured array converts record by record, ~70 us each)."""
    out = wp.empty(len(records), dtype=dtype, device=device)
    if len(records):
        records = np.ascontiguousarray(records)
        view = wp.array(ptr=records.ctypes.data, shape=(len(records),), dtype=dtype, device="cpu")
        wp.copy(out, view)
        wp.synchronize_device(device)  # ``records`` may go once the copy has read it
    return out


def _shadow_cameras(a: np.ndarray, frames, center: np.ndarray, radius: float, size: int) -> None:
    """Aim each photo's shadow-map camera from its light at the object's bounding sphere (records of
    :func:`image_infos`): perspective from a point light, orthographic along a directional one;
    has_shadow stays 0 for no light, for a light of intensity 0 (a no-flash photo: it lights nothing, and its
    samples skip the light's tests, fit/kernels/stream.py ``observe_with_unlit_func``: no map to render) and for a
    point light inside the bounds (no frustum covers it)."""
    r = max(radius, 1e-9)
    kinds = np.array([fr.light_kind for fr in frames])
    kinds[[not np.any(np.asarray(fr.light_intensity, float)) for fr in frames]] = "none"
    light = np.array([np.asarray(fr.light_vec, float) for fr in frames], np.float64).reshape(-1, 3)
    point, directional = kinds == "point", kinds == "directional"
    dist = np.linalg.norm(light - center, axis=1)
    point &= dist > _SHADOW_INSIDE * r
    eye = light.copy()
    d = light[directional] / np.linalg.norm(light[directional], axis=1, keepdims=True)
    eye[directional] = center - 3.0 * r * d
    has = point | directional
    if not has.any():
        return
    rot, trans = look_at_w2c_batch(eye[has], center)
    with np.errstate(divide="ignore", invalid="ignore"):
        half = np.arcsin(np.minimum(r / dist, 0.999)) * _SHADOW_FOV_PAD
        f = np.where(point, 0.5 * size / np.tan(half), size / (_SHADOW_ORTHO_SPAN * r))
    a["has_shadow"][has] = 1
    a["sh_rot"][has] = rot.astype(np.float32)
    a["sh_trans"][has] = trans.astype(np.float32)
    a["sh_fx"][has] = a["sh_fy"][has] = f[has]
    a["sh_cx"][has] = a["sh_cy"][has] = 0.5 * size
    a["sh_ortho"][has] = directional[has]
    a["sh_size"][has] = size
