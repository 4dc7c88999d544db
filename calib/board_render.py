"""Synthetic board photos with known intrinsics, distortion and poses (ground truth for calibration tests).

Each output pixel is traced back exactly: undistort its pixel coordinate (iterative inverse of
OpenCV's distortion model), intersect the camera ray with the board plane z = 0, and sample the
flat board image there. Rendering is supersampled to antialias edges (a real lens/sensor blurs
them too, and sub-pixel corner refinement needs smooth edges).
"""

from __future__ import annotations

import numpy as np


def undistort_normalized(uv: np.ndarray, k: np.ndarray, dist: np.ndarray, iters: int = 30) -> np.ndarray:
    """Invert OpenCV's distortion: pixel coords (N, 2) (centres at integers) -> normalized (N, 2).

    Fixed-point iteration as in OpenCV's ``undistortPoints`` but with more iterations so the
    rendered ground truth is exact to ~1e-6 px for moderate distortion.
    """
    d = np.zeros(5)
    d[: len(np.ravel(dist))] = np.ravel(dist)[:5]
    k1, k2, p1, p2, k3 = d
    xd = (uv[:, 0] - k[0, 2]) / k[0, 0]
    yd = (uv[:, 1] - k[1, 2]) / k[1, 1]
    x, y = xd.copy(), yd.copy()
    for _ in range(iters):
        r2 = x * x + y * y
        radial = 1 + k1 * r2 + k2 * r2 * r2 + k3 * r2 ** 3
        dx = 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        dy = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        x = (xd - dx) / radial
        y = (yd - dy) / radial
    return np.stack([x, y], 1)


def camera_rays(k: np.ndarray, dist: np.ndarray, image_size: tuple[int, int], supersample: int = 2) -> np.ndarray:
    """Normalized undistorted coordinates (H*s, W*s, 2) of the sub-pixel samples of a camera (reuse per view)."""
    w, h = image_size
    s = supersample
    offs = (np.arange(s) + 0.5) / s - 0.5
    xs = (np.arange(w)[:, None] + offs[None, :]).reshape(-1)
    ys = (np.arange(h)[:, None] + offs[None, :]).reshape(-1)
    gx, gy = np.meshgrid(xs, ys)
    uv = np.stack([gx.ravel(), gy.ravel()], 1)
    return undistort_normalized(uv, k, dist).reshape(h * s, w * s, 2)


def render_board_view(board_img: np.ndarray, board_size: tuple[float, float], rays: np.ndarray,
                      rvec: np.ndarray, tvec: np.ndarray, supersample: int = 2, background: int = 128) -> np.ndarray:
    """Render a flat board seen by a distorted pinhole camera.

    Args:
        board_img: (Hb, Wb) uint8 image of the board; its full extent covers ``board_size``.
        board_size: (width, height) of the board in world units; board point (X, Y, 0) maps to
            board-image pixel (X / width * Wb, Y / height * Hb) (edges, not centres).
        rays: :func:`camera_rays` of the camera (K in OpenCV convention, distortion, size, supersampling).
        rvec, tvec: board-to-camera pose (Rodrigues vector, translation).
        supersample: the ``supersample`` the rays were made with.
        background: grey level where the board is absent.

    Returns:
        (H, W) uint8 image.
    """
    import cv2

    hs, ws = rays.shape[:2]
    xn = rays.reshape(-1, 2)
    r = cv2.Rodrigues(np.asarray(rvec, dtype=np.float64))[0]
    t = np.asarray(tvec, dtype=np.float64).reshape(3)
    # Ray X_c = s * (x, y, 1); board frame X_b = R^T (X_c - t); solve z_b = 0 for s.
    d = np.concatenate([xn, np.ones((len(xn), 1))], 1)
    rt = r.T
    db = d @ rt.T
    ob = -rt @ t
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = -ob[2] / db[:, 2]
    pb = ob[None, :] + lam[:, None] * db
    hb, wb = board_img.shape[:2]
    mx = (pb[:, 0] / board_size[0] * wb - 0.5).astype(np.float32)
    my = (pb[:, 1] / board_size[1] * hb - 0.5).astype(np.float32)
    bad = ~(lam > 0)
    mx[bad] = -1e6
    my[bad] = -1e6
    big = cv2.remap(board_img, mx.reshape(hs, ws), my.reshape(hs, ws), cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_CONSTANT, borderValue=background)
    return cv2.resize(big, (ws // supersample, hs // supersample), interpolation=cv2.INTER_AREA)
