"""Camera poses aimed at a point (the synthetic cameras', the shadow cameras', tests' views): numpy only,
so the capture conventions (:mod:`texstream.capture.conventions`, which re-exports these) load no Warp."""

from __future__ import annotations

import numpy as np


def look_at_w2c(eye: np.ndarray, target: np.ndarray, up: np.ndarray = (0.0, 0.0, 1.0)) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera (R, t), OpenCV axes, for a camera at ``eye`` looking at ``target``."""
    eye = np.asarray(eye, dtype=np.float64)
    fwd = np.asarray(target, dtype=np.float64) - eye
    fwd /= np.linalg.norm(fwd)
    up = np.asarray(up, dtype=np.float64)
    if abs(np.dot(fwd, up / np.linalg.norm(up))) > 0.999:
        up = np.array([0.0, 1.0, 0.0]) if abs(fwd[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    right = np.cross(fwd, up)
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)
    r = np.stack([right, down, fwd], axis=0)
    return r, -r @ eye


def look_at_w2c_batch(eyes: np.ndarray, target: np.ndarray, up: np.ndarray = (0.0, 0.0, 1.0)) -> tuple[np.ndarray, np.ndarray]:
    """:func:`look_at_w2c` for (N, 3) eyes at once: (N, 3, 3) rotations and (N, 3) translations (the
    same construction and fallback up vector, equal to float64 rounding)."""
    eyes = np.asarray(eyes, dtype=np.float64).reshape(-1, 3)
    fwd = np.asarray(target, dtype=np.float64).reshape(-1, 3) - eyes
    fwd /= np.linalg.norm(fwd, axis=1, keepdims=True)
    up = np.asarray(up, dtype=np.float64)
    ups = np.broadcast_to(up, fwd.shape).copy()
    near = np.abs(fwd @ (up / np.linalg.norm(up))) > 0.999
    ups[near] = np.where(np.abs(fwd[near, 1:2]) < 0.9, [0.0, 1.0, 0.0], [1.0, 0.0, 0.0])
    right = np.cross(fwd, ups)
    right /= np.linalg.norm(right, axis=1, keepdims=True)
    down = np.cross(fwd, right)
    r = np.stack([right, down, fwd], axis=1)
    return r, -np.einsum("nij,nj->ni", r, eyes)
