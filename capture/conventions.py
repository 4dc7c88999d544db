"""Coordinate, pixel and colour conventions, written once.

World and camera frames
    ``capture.json`` follows nerfstudio's ``transforms.json``: ``transform_matrix`` is the 4x4
    camera-to-world matrix in OpenGL camera axes (x right, y up, camera looks down -z).
    Inside texstream (projection, rendering, fitting) cameras are world-to-camera rigid
    transforms ``x_cam = R @ x_world + t`` in OpenCV axes (x right, y down, camera looks down +z),
    as in COLMAP and OpenCV. The two differ by flipping the camera's y and z axes.

Pixels
    Continuous pixel coordinates put the centre of pixel (column i, row j) at (i + 0.5, j + 0.5),
    as COLMAP and nerfstudio do; ``cx, cy`` are in these coordinates (the image centre of a
    W x H image is (W/2, H/2)). OpenCV and Middlebury matrices put pixel centres at integers:
    add 0.5 to their cx, cy (:func:`opencv_principal_point_to_capture`).
    Projection (pinhole): u = fx * X/Z + cx, v = fy * Y/Z + cy with (X, Y, Z) in OpenCV camera axes.

Images and colour
    Arrays are (H, W, C) float32, row 0 at the top. Values are linear radiance scaled by the
    frame's ``exposure`` (pixel = exposure * radiance). 8-bit files are sRGB-encoded and decoded
    to linear on read; 16-bit integer and float files (EXR, HDR, float TIFF) are linear.

Texture atlas
    UVs are in [0, 1]^2 with v up (OBJ / glTF-after-flip convention: v = 0 is the bottom row of the
    texture image). Texel (column x, row y) of a W x H atlas, row 0 at the top of the image, has its
    centre at u = (x + 0.5) / W, v = 1 - (y + 0.5) / H.

Lights
    ``point``: ``position`` (world) and ``intensity`` (RGB radiant intensity): irradiance at a
    surface point is intensity * cos(theta_i) / r^2. ``directional``: ``direction`` is the
    direction the light travels (Mitsuba's convention; the surface-to-light vector is
    -direction), irradiance = intensity * cos(theta_i).

Reflectance
    Parameter maps hold BRDF values (1/sr) as in the Lafortune model of the seed (Eq. 2.12):
    outgoing radiance = f_r * irradiance, so a Lambertian texel with parameter rho_d under a
    directional light of intensity E shows rho_d * cos(theta_i) * E. (Diffuse albedo in the
    usual sense is pi * rho_d; the glTF export converts.)
"""

from __future__ import annotations

import numpy as np

# camera poses live in the render layer (the shadow cameras use them); here for the conventions' users
from texstream.render.pose import look_at_w2c, look_at_w2c_batch  # noqa: F401

# Flip between OpenGL camera axes (nerfstudio) and OpenCV camera axes (COLMAP / texstream).
GL_TO_CV = np.diag([1.0, -1.0, -1.0])


def c2w_gl_to_w2c_cv(c2w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """nerfstudio camera-to-world (OpenGL axes, 4x4 or 3x4) -> (R, t) world-to-camera, OpenCV axes."""
    c2w = np.asarray(c2w, dtype=np.float64)
    r_c2w = c2w[:3, :3] @ GL_TO_CV
    center = c2w[:3, 3]
    r = r_c2w.T
    t = -r @ center
    return r, t


def w2c_cv_to_c2w_gl(r: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(R, t) world-to-camera in OpenCV axes -> 4x4 nerfstudio camera-to-world in OpenGL axes."""
    r = np.asarray(r, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64).reshape(3)
    c2w = np.eye(4)
    c2w[:3, :3] = r.T @ GL_TO_CV
    c2w[:3, 3] = -r.T @ t
    return c2w


def camera_center(r: np.ndarray, t: np.ndarray) -> np.ndarray:
    """World position of the camera centre for world-to-camera (R, t)."""
    return -np.asarray(r).T @ np.asarray(t).reshape(3)


def opencv_principal_point_to_capture(cx: float, cy: float) -> tuple[float, float]:
    """OpenCV / Middlebury principal point (pixel centres at integers) -> capture convention."""
    return cx + 0.5, cy + 0.5


def project(points: np.ndarray, r: np.ndarray, t: np.ndarray, fx: float, fy: float,
            cx: float, cy: float) -> tuple[np.ndarray, np.ndarray]:
    """Pinhole projection of world points (N, 3) -> pixel coords (N, 2) and depth Z (N,)."""
    pc = np.asarray(points, dtype=np.float64) @ np.asarray(r).T + np.asarray(t).reshape(1, 3)
    z = pc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = np.stack([fx * pc[:, 0] / z + cx, fy * pc[:, 1] / z + cy], axis=1)
    return uv, z


def is_rotation(r: np.ndarray, tol: float = 1e-4) -> bool:
    """True when r is a proper rotation (orthonormal, det +1) to tol."""
    r = np.asarray(r, dtype=np.float64)
    if r.shape != (3, 3) or not np.isfinite(r).all():
        return False
    # plain array arithmetic: a capture of thousands of frames checks one per frame
    det = (r[0, 0] * (r[1, 1] * r[2, 2] - r[1, 2] * r[2, 1]) - r[0, 1] * (r[1, 0] * r[2, 2] - r[1, 2] * r[2, 0])
           + r[0, 2] * (r[1, 0] * r[2, 1] - r[1, 1] * r[2, 0]))
    return bool(np.abs(r.T @ r - _EYE3).max() <= tol and abs(det - 1.0) < tol)


_EYE3 = np.eye(3)


def texel_center_uv(x: np.ndarray, y: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """UV of texel centres (see the module doc)."""
    return (np.asarray(x) + 0.5) / width, 1.0 - (np.asarray(y) + 0.5) / height


def uv_to_texel(u: np.ndarray, v: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Continuous texel coordinates (x, y) of UVs, texel centres at integers (for bilinear lookup)."""
    return np.asarray(u) * width - 0.5, (1.0 - np.asarray(v)) * height - 0.5
