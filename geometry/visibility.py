"""Visibility support: the mesh BVH (``wp.Mesh``) and per-photo depth maps, built once.

A module-level Warp kernel casts one ray per pixel through the pixel centre (capture convention:
centre of pixel (i, j) at (i + 0.5, j + 0.5)) of a pinhole camera (world-to-camera R, t in OpenCV
axes) and records the camera-space depth Z of the first hit (``inf`` where the ray misses) and the
hit face (-1 on a miss). Lens distortion is not modelled: depth maps are for the undistorted
pinhole camera of each frame (the fit undistorts photos the same way).

Imports only numpy and warp.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import warp as wp

from texstream.render.mesh import SurfaceMesh


@wp.kernel(enable_backward=False)
def _depth_kernel(mesh: wp.uint64, rot: wp.mat33, center: wp.vec3, k: wp.vec4, max_t: float,
                  depth: wp.array2d(dtype=wp.float32), face: wp.array2d(dtype=wp.int32)):
    j, i = wp.tid()  # row, column
    # camera-space ray through the pixel centre (k = fx, fy, cx, cy)
    d_cam = wp.vec3((float(i) + 0.5 - k[2]) / k[0], (float(j) + 0.5 - k[3]) / k[1], 1.0)
    inv_len = 1.0 / wp.length(d_cam)
    d_world = wp.transpose(rot) * (d_cam * inv_len)
    q = wp.mesh_query_ray(mesh, center, d_world, max_t)
    if q.result:
        depth[j, i] = q.t * inv_len  # ray length -> camera-space Z
        face[j, i] = q.face
    else:
        depth[j, i] = wp.inf
        face[j, i] = -1


class Visibility:
    """The BVH of a mesh on one device, and depth / face-id maps for pinhole cameras.

    Args:
        mesh: the surface (world units of the capture frame).
        device: Warp device ("cpu", "cuda:0").
    """

    def __init__(self, mesh: SurfaceMesh, device: str = "cpu"):
        self.device = device
        self.mesh = mesh
        self._points = wp.array(np.asarray(mesh.vertices, np.float32), dtype=wp.vec3, device=device)
        self._indices = wp.array(np.asarray(mesh.faces, np.int32).reshape(-1), dtype=wp.int32, device=device)
        self.wp_mesh = wp.Mesh(points=self._points, indices=self._indices)
        lo, hi = mesh.bbox()
        self._extent = float(np.linalg.norm(hi - lo))
        self._mid = 0.5 * (lo + hi)

    def render(self, frame) -> tuple[np.ndarray, np.ndarray]:
        """Depth and face-id maps of one frame.

        Args:
            frame: a :class:`texstream.capture.capture_json.Frame` (R, t, intrinsics).

        Returns:
            depth (H, W) float32 camera-space Z (world units), ``inf`` where no surface is hit;
            face (H, W) int32 face index, -1 where no surface is hit.
        """
        depth, face = self.render_device(frame)
        return depth.numpy(), face.numpy()

    def render_device(self, frame) -> tuple[wp.array, wp.array]:
        """Like :meth:`render`, but leaves the maps on the device as Warp arrays."""
        intr = frame.intrinsics
        r = np.asarray(frame.R, np.float64)
        c = -r.T @ np.asarray(frame.t, np.float64).reshape(3)
        max_t = float(np.linalg.norm(c - self._mid) + 2.0 * self._extent + 1.0)
        depth = wp.empty((intr.height, intr.width), dtype=wp.float32, device=self.device)
        face = wp.empty((intr.height, intr.width), dtype=wp.int32, device=self.device)
        wp.launch(_depth_kernel, dim=(intr.height, intr.width),
                  inputs=[self.wp_mesh.id, wp.mat33(r.astype(np.float32)), wp.vec3(*c.astype(np.float32)),
                          wp.vec4(intr.fx, intr.fy, intr.cx, intr.cy), max_t],
                  outputs=[depth, face], device=self.device)
        return depth, face


def depth_maps(mesh: SurfaceMesh, capture_frames: Sequence, device: str = "cpu",
               with_faces: bool = False) -> list[np.ndarray] | tuple[list[np.ndarray], list[np.ndarray]]:
    """Per-photo depth maps of a mesh (the BVH is built once for all frames).

    Args:
        mesh: the surface in the capture frame.
        capture_frames: frames with R, t, intrinsics (e.g. ``capture.frames``).
        device: Warp device.
        with_faces: also return the hit-face maps.

    Returns:
        list of (H, W) float32 camera-space depth, ``inf`` where no hit (and the list of (H, W)
        int32 face maps when ``with_faces``).
    """
    vis = Visibility(mesh, device)
    depths, faces = [], []
    for fr in capture_frames:
        d, f = vis.render(fr)
        depths.append(d)
        faces.append(f)
    return (depths, faces) if with_faces else depths


def visible_points(points: np.ndarray, frame, depth: np.ndarray, rel_tol: float = 1e-3,
                   abs_tol: float = 0.0) -> np.ndarray:
    """Which world points a frame sees, by their depth against the frame's depth map.

    Args:
        points: (N, 3) world points (on the surface the depth map was made from).
        frame: the frame (R, t, intrinsics).
        depth: (H, W) depth map of that frame.
        rel_tol, abs_tol: a point is visible when its Z <= depth * (1 + rel_tol) + abs_tol at its
            pixel (the tolerance absorbs float32 ray-casting error and the pixel footprint).

    Returns:
        (N,) bool: in front of the camera, inside the image and not occluded.
    """
    intr = frame.intrinsics
    pc = np.asarray(points, np.float64) @ np.asarray(frame.R).T + np.asarray(frame.t).reshape(1, 3)
    z = pc[:, 2]
    ok = z > 1e-12
    zs = np.where(ok, z, 1.0)
    u = intr.fx * pc[:, 0] / zs + intr.cx
    v = intr.fy * pc[:, 1] / zs + intr.cy
    ok &= (u >= 0) & (u < intr.width) & (v >= 0) & (v < intr.height)
    iu = np.clip(u.astype(np.int64), 0, intr.width - 1)
    iv = np.clip(v.astype(np.int64), 0, intr.height - 1)
    d = depth[iv, iu]
    return ok & (z <= d * (1.0 + rel_tol) + abs_tol)
