"""Screened Poisson surface reconstruction of oriented points (pymeshlab), trimmed by density and masks.

Points without normals (SfM points) get PCA normals from their neighbours, oriented towards the
nearest camera that looks at them. Poisson closes every surface, so the result is trimmed: faces
whose vertices have low Poisson density (few samples nearby: the invented parts) are removed, and
faces that project outside the object mask of any camera that sees them are removed too.

pymeshlab and scipy are imported inside the functions; warp at module level (a distance kernel).
"""

from __future__ import annotations

import dataclasses
import os
from typing import Sequence

import numpy as np
import warp as wp

from texstream.core.errors import InputError, StageError
from texstream.core.config import option

from texstream.render.mesh import SurfaceMesh
from .clean import signed_volume
from .visibility import depth_maps, visible_points


@dataclasses.dataclass
class PoissonConfig:
    """Screened Poisson options."""

    depth: int = option(8, help="octree depth (resolution 2^depth over the points' bounding cube)")
    scale: float = option(2.0, help="bounding cube size over the points' extent (room for the surface to close "
                                    "where the points stop: at 1.1 the temple's unseen base ran into the cube "
                                    "wall and stayed open)")
    point_weight: float = option(4.0, help="screening weight: how closely the surface interpolates the points")
    samples_per_node: float = option(1.5, help="minimum points per octree node (higher: smoother, for noisy points)")
    normal_neighbours: int = option(12, help="neighbours for PCA normals when the points have none")
    density_quantile: float = option(0.02, help="remove vertices whose Poisson density is below this quantile "
                                                "(0: no density trim)")
    min_points: int = option(200, help="fewest points Poisson is attempted with")
    threads: int = option(1, help="Poisson solver threads (on 2 cores, 1 was 3x faster than 2)")


def read_points(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray | None]:
    """Points (N, 3) and normals (N, 3) or None from a PLY/OBJ point cloud (pymeshlab)."""
    import pymeshlab as ml

    ms = ml.MeshSet()
    try:
        ms.load_new_mesh(str(path))
    except ml.PyMeshLabException as e:
        raise InputError(f"cannot read points ({e})", path, "write the points as PLY") from None
    m = ms.current_mesh()
    p = np.asarray(m.vertex_matrix(), np.float64)
    # pymeshlab fills normals it was not given; trust them only when the PLY declares nx
    head = open(path, "rb").read(4096)
    has_n = head.startswith(b"ply") and b"property float nx" in head or b"property double nx" in head
    n = np.asarray(m.vertex_normal_matrix(), np.float64) if has_n else None
    if n is not None and (n.shape != p.shape or not np.all(np.isfinite(n)) or np.all(np.abs(n) < 1e-12)):
        n = None
    return p, n


def estimate_normals(points: np.ndarray, camera_centers: np.ndarray | None, k: int = 12,
                     view_dirs: np.ndarray | None = None) -> np.ndarray:
    """PCA normals of a point cloud, oriented towards the nearest camera (outwards for SfM points).

    Args:
        points: (N, 3).
        camera_centers: (C, 3) camera centres, or None to orient away from the centroid.
        k: neighbours.
        view_dirs: (N, 3) directions from each point towards the cameras that observed it (e.g.
            the mean over its SfM track); when given they orient the normals instead of the
            nearest camera (which can lie behind a thin part of the object).

    Returns:
        (N, 3) unit normals.
    """
    from scipy.spatial import cKDTree

    p = np.asarray(points, np.float64)
    k = int(min(max(k, 3), len(p)))
    _, idx = cKDTree(p).query(p, k=k)
    nb = p[idx] - p[idx].mean(axis=1, keepdims=True)
    cov = np.einsum("nki,nkj->nij", nb, nb)
    _, vecs = np.linalg.eigh(cov)
    n = vecs[:, :, 0]  # smallest-eigenvalue direction
    if view_dirs is not None:
        to_cam = np.asarray(view_dirs, np.float64).reshape(-1, 3)
    elif camera_centers is not None and len(camera_centers):
        cc = np.asarray(camera_centers, np.float64)
        _, ci = cKDTree(cc).query(p)
        to_cam = cc[ci] - p
    else:
        to_cam = p - p.mean(axis=0)
    n *= np.where(np.einsum("ij,ij->i", n, to_cam) < 0, -1.0, 1.0)[:, None]
    return n


def poisson_reconstruct(points: np.ndarray, normals: np.ndarray | None = None,
                        camera_centers: np.ndarray | None = None, config: PoissonConfig | None = None,
                        path: str | os.PathLike | None = None) -> SurfaceMesh:
    """Screened Poisson surface of oriented points, trimmed by Poisson density.

    Args:
        points: (N, 3) world points.
        normals: (N, 3) outward normals, or None to estimate them (see :func:`estimate_normals`).
        camera_centers: (C, 3) for orienting estimated normals.
        config: options.
        path: the points' file, for messages.

    Returns:
        The reconstructed surface (outward faces).

    Raises:
        InputError: too few points (the message names the fallbacks: the visual hull or a given mesh).
        StageError: Poisson produced nothing.
    """
    import pymeshlab as ml

    cfg = config or PoissonConfig()
    p = np.asarray(points, np.float64).reshape(-1, 3)
    p_ok = np.all(np.isfinite(p), axis=1)
    p = p[p_ok]
    if len(p) < cfg.min_points:
        raise InputError(f"only {len(p)} points for Poisson reconstruction (need at least {cfg.min_points})", path,
                         "use the visual hull ('texstream mesh CAPTURE --from hull', needs masks) or give a "
                         "scanned mesh ('--from scan.obj'); or register more photos for more SfM points")
    if normals is None:
        n = estimate_normals(p, camera_centers, cfg.normal_neighbours)
    else:
        n = np.asarray(normals, np.float64).reshape(-1, 3)[p_ok]
    ms = ml.MeshSet()
    ms.add_mesh(ml.Mesh(vertex_matrix=p, v_normals_matrix=n))
    ms.generate_surface_reconstruction_screened_poisson(depth=int(cfg.depth), scale=float(cfg.scale),
                                                        pointweight=float(cfg.point_weight),
                                                        samplespernode=float(cfg.samples_per_node),
                                                        threads=int(cfg.threads), preclean=True)
    m = ms.current_mesh()
    if m.face_number() == 0:
        raise StageError("Poisson reconstruction produced no surface", path,
                         "check the point normals, or use '--from hull' or '--from scan.obj'")
    v = np.asarray(m.vertex_matrix(), np.float64)
    f = np.asarray(m.face_matrix(), np.int32)
    if cfg.density_quantile > 0:
        # pymeshlab stores the Poisson sample density as vertex quality
        q = np.asarray(m.vertex_scalar_array(), np.float64)
        keep_v = q >= np.quantile(q, cfg.density_quantile)
        f = f[keep_v[f].all(axis=1)]
    mesh = _compact(SurfaceMesh(v, f))

    if signed_volume(mesh.vertices, mesh.faces) < 0:
        mesh = SurfaceMesh(mesh.vertices, mesh.faces[:, ::-1].copy())
    return mesh


def trim_by_masks(mesh: SurfaceMesh, frames: Sequence, masks: Sequence[np.ndarray], device: str = "cpu",
                  min_votes: int = 1) -> SurfaceMesh:
    """Remove faces whose centroid lands outside the object mask in ``min_votes`` or more views that see it.

    Visibility is by ray-cast depth maps (:mod:`.visibility`), so a face hidden in a view is not
    judged by that view's mask.
    """
    cen = mesh.vertices[mesh.faces].mean(axis=1)
    depths = depth_maps(mesh, frames, device)
    outside_votes = np.zeros(len(cen), np.int32)
    diag = mesh.bbox_diagonal()
    for fr, d, m in zip(frames, depths, masks):
        vis = visible_points(cen, fr, d, rel_tol=1e-3, abs_tol=1e-3 * diag)
        intr = fr.intrinsics
        pc = cen @ np.asarray(fr.R).T + np.asarray(fr.t).reshape(1, 3)
        z = np.where(pc[:, 2] > 0, pc[:, 2], 1.0)
        u = np.clip((intr.fx * pc[:, 0] / z + intr.cx).astype(np.int64), 0, intr.width - 1)
        v = np.clip((intr.fy * pc[:, 1] / z + intr.cy).astype(np.int64), 0, intr.height - 1)
        outside_votes += (vis & ~np.asarray(m, bool)[v, u]).astype(np.int32)
    return _compact(SurfaceMesh(mesh.vertices, mesh.faces[outside_votes < min_votes]))


def _compact(mesh: SurfaceMesh) -> SurfaceMesh:
    used = np.zeros(mesh.n_vertices, bool)
    used[mesh.faces.reshape(-1)] = True
    remap = np.cumsum(used) - 1
    return SurfaceMesh(mesh.vertices[used], remap[mesh.faces].astype(np.int32))


@wp.kernel(enable_backward=False)
def _point_distance_kernel(mesh: wp.uint64, points: wp.array(dtype=wp.vec3), max_dist: float,
                           out: wp.array(dtype=wp.float32)):
    i = wp.tid()
    q = wp.mesh_query_point_no_sign(mesh, points[i], max_dist)
    if q.result:
        out[i] = wp.length(wp.mesh_eval_position(mesh, q.face, q.u, q.v) - points[i])
    else:
        out[i] = max_dist


def point_surface_distance(points: np.ndarray, mesh: SurfaceMesh, device: str = "cpu") -> np.ndarray:
    """Distance from each point to the nearest point of a triangle mesh (BVH query in Warp).

    Args:
        points: (N, 3) world points.
        mesh: the surface.
        device: Warp device.

    Returns:
        (N,) distances in world units (capped at 10x the mesh's bounding-box diagonal).
    """
    p = np.asarray(points, np.float32).reshape(-1, 3)
    wm = wp.Mesh(points=wp.array(np.asarray(mesh.vertices, np.float32), dtype=wp.vec3, device=device),
                 indices=wp.array(np.asarray(mesh.faces, np.int32).reshape(-1), dtype=wp.int32, device=device))
    out = wp.empty(len(p), dtype=wp.float32, device=device)
    far = 10.0 * max(mesh.bbox_diagonal(), float(np.ptp(p, axis=0).max()) if len(p) else 0.0, 1e-12)
    wp.launch(_point_distance_kernel, dim=len(p), inputs=[wm.id, wp.array(p, dtype=wp.vec3, device=device), far],
              outputs=[out], device=device)
    return out.numpy().astype(np.float64)
