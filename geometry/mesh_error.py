"""How far a made mesh lies from the true surface, both ways, as fractions of the truth's size.

Each mesh is sampled uniformly by area (``samples`` points, seeded) and each sample's distance to the
nearest point of the other mesh's triangles is its error (a BVH query, :func:`.reconstruct.point_surface_distance`).
Distances to the triangles rather than to the other mesh's samples (a k-d tree of samples) have no
sampling floor: two coincident surfaces measure zero, not a third of the sample spacing.

- ``made_to_true``: accuracy (is what was made on the true surface?), the samples of the made mesh;
- ``true_to_made``: completeness (is the true surface covered?), the samples of the truth. A truth
  larger than what the cameras see (the far ground of a scene) is cropped to the seen part first
  (:func:`crop_mesh`).

numpy at module level.
"""

from __future__ import annotations

import numpy as np

from texstream.render.mesh import SurfaceMesh
from .reconstruct import point_surface_distance


def sample_surface(mesh: SurfaceMesh, count: int, seed: int = 0) -> np.ndarray:
    """``count`` points uniformly distributed by area over the mesh's faces."""
    v = np.asarray(mesh.vertices, np.float64)
    f = np.asarray(mesh.faces, np.int64)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    rng = np.random.default_rng(seed)
    face = rng.choice(len(f), size=int(count), p=area / area.sum())
    r1, r2 = rng.random(count), rng.random(count)
    s = np.sqrt(r1)
    w0, w1, w2 = 1 - s, s * (1 - r2), s * r2
    return a[face] * w0[:, None] + b[face] * w1[:, None] + c[face] * w2[:, None]


def crop_mesh(mesh: SurfaceMesh, lo: np.ndarray, hi: np.ndarray) -> SurfaceMesh:
    """The faces whose centroid lies inside the box [lo, hi] (vertices kept as they are)."""
    cen = mesh.vertices[mesh.faces].mean(axis=1)
    keep = np.all((cen >= np.asarray(lo)) & (cen <= np.asarray(hi)), axis=1)
    return SurfaceMesh(mesh.vertices, mesh.faces[keep])


def _stats(d: np.ndarray, scale: float) -> dict:
    return {"median": float(np.median(d) / scale), "p90": float(np.percentile(d, 90) / scale),
            "mean": float(np.mean(d) / scale)}


def mesh_error(made: SurfaceMesh, truth: SurfaceMesh, samples: int = 100000, seed: int = 0,
               scale: float | None = None, device: str = "cpu") -> dict:
    """Distances between the made mesh and the truth, both ways (module doc), divided by ``scale`` (default: the
    truth's bounding-box diagonal).

    Returns:
        ``{"made_to_true": {median, p90, mean}, "true_to_made": {...}, "scale", "samples"}``.
    """
    if scale is None:
        lo, hi = truth.bbox()
        scale = float(np.linalg.norm(hi - lo))
    d_mt = point_surface_distance(sample_surface(made, samples, seed), truth, device)
    d_tm = point_surface_distance(sample_surface(truth, samples, seed + 1), made, device)
    return {"made_to_true": _stats(d_mt, scale), "true_to_made": _stats(d_tm, scale), "scale": scale,
            "samples": int(samples)}
