"""Visual-hull samples where the SfM points leave an object's surface open, as extra input to Poisson.

Structure from motion finds points only where at least two cameras see texture at a useful angle.
An object's underside, seen by a ring of cameras at low elevation only at grazing angles or not at
all, gets none, and screened Poisson closes the gap with a smooth cap far inside the silhouettes;
intersecting with the visual hull cannot bring it back out. On the synthetic textured sphere
(cameras at 5 and 35 degrees elevation) the cap sat 16% of the diameter inside the true surface
below -60 degrees latitude and 9% between -60 and -30, and the held-out views, which see down to
-67 degrees, showed it (``benchmarks/photos_only_diagnose.py``).

Where no camera sees the surface well, the visual hull is the best estimate of it there is: the
surface lies inside it, and the silhouettes touch it. So :func:`hull_fill_samples` samples the
hull's surface and keeps the samples that are

- farther than ``distance`` from every SfM point (a region the points leave open), and
- seen well (unoccluded, at less than ``max_angle_deg`` between the hull normal and the direction
  to the camera) by fewer than ``min_views`` cameras: a region seen well by two cameras but without
  points is more likely a concavity the hull bridges (its points lie deeper, inside the hull) or
  textureless surface Poisson interpolates well; the hull there would pull Poisson outwards.

The kept samples, with the hull's outward normals, join the SfM points for Poisson; the result is
still intersected with the hull (make_mesh.py).

numpy and warp at module level (through :mod:`.visibility`); scipy inside functions.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from texstream.render.mesh import SurfaceMesh
from .hull import visual_hull
from .reconstruct import estimate_normals
from .scene import point_spacing
from .visibility import depth_maps, visible_points


def sample_surface(mesh: SurfaceMesh, spacing: float, max_samples: int = 200_000,
                   seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """About one area-uniform random sample per ``spacing``^2 of surface: (points (N, 3), unit face normals (N, 3))."""
    rng = np.random.default_rng(seed)
    a = mesh.face_areas()
    n = int(min(max_samples, max(1, round(float(a.sum()) / max(spacing, 1e-12) ** 2))))
    fi = rng.choice(len(a), size=n, p=a / a.sum())
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    bary = np.stack([1 - s, s * (1 - r2), s * r2], axis=1)
    pts = np.einsum("ni,nij->nj", bary, mesh.vertices[mesh.faces[fi]])
    return pts, mesh.face_normals()[fi]


def well_seen_views(points: np.ndarray, normals: np.ndarray, hull: SurfaceMesh, frames: Sequence,
                    max_angle_deg: float, device: str = "cpu") -> np.ndarray:
    """(N,) number of cameras that see each hull point unoccluded by the hull and within ``max_angle_deg``
    of its normal."""
    cos_min = np.cos(np.radians(max_angle_deg))
    count = np.zeros(len(points), np.int32)
    diag = hull.bbox_diagonal()
    for fr, d in zip(frames, depth_maps(hull, frames, device)):
        to_cam = np.asarray(fr.center, np.float64).reshape(1, 3) - points
        cos = np.einsum("ij,ij->i", normals, to_cam) / np.maximum(np.linalg.norm(to_cam, axis=1), 1e-12)
        # the samples lie on the hull the depth maps come from: a tolerance of a thousandth of its size
        count += (visible_points(points, fr, d, rel_tol=1e-3, abs_tol=1e-3 * diag) & (cos >= cos_min))
    return count


def hull_fill_samples(hull: SurfaceMesh, points: np.ndarray, frames: Sequence, distance: float,
                      max_angle_deg: float = 60.0, min_views: int = 2, device: str = "cpu",
                      spacing: float | None = None) -> tuple[np.ndarray, np.ndarray, dict]:
    """Hull surface samples where the SfM points leave the surface open and no two cameras see it well.

    Args:
        hull: the visual hull (outward faces).
        points: (M, 3) SfM points.
        frames: the capture's frames (R, t, intrinsics).
        distance: a sample is in an open region when farther than this from every point.
        max_angle_deg: a camera sees a sample well within this angle of the hull normal.
        min_views: samples seen well by this many cameras or more are left out.
        device: Warp device for the visibility depth maps.
        spacing: sample spacing (default: the points' median nearest-neighbour distance, so the
            samples weigh in Poisson about as densely as the points do).

    Returns:
        (samples (K, 3), outward normals (K, 3), report) with the counts and the parameters.
    """
    from scipy.spatial import cKDTree

    p = np.asarray(points, np.float64).reshape(-1, 3)
    tree = cKDTree(p)
    if spacing is None:
        d1, _ = tree.query(p, k=2, workers=-1)  # every core: the same distances
        spacing = float(np.median(d1[:, 1]))
    samples, normals = sample_surface(hull, spacing)
    far = tree.query(samples, workers=-1)[0] > distance
    views = np.zeros(len(samples), np.int32)
    views[far] = well_seen_views(samples[far], normals[far], hull, frames, max_angle_deg, device)
    keep = far & (views < min_views)
    report = {"hull_samples": len(samples), "far_from_points": int(far.sum()), "kept": int(keep.sum()),
              "spacing": spacing, "distance": float(distance), "max_angle_deg": float(max_angle_deg),
              "min_views": int(min_views)}
    return samples[keep], normals[keep], report


def poisson_points_with_hull_fill(frames: Sequence, masks: Sequence[np.ndarray], points: np.ndarray,
                                  normals: np.ndarray | None, hull_config, distance_factor: float,
                                  max_angle_deg: float, normal_neighbours: int = 12, device: str = "cpu",
                                  bounds: tuple[np.ndarray, np.ndarray] | None = None,
                                  ) -> tuple[np.ndarray, np.ndarray, dict]:
    """The SfM points (with normals, estimated when missing) plus the hull samples of
    :func:`hull_fill_samples`, for screened Poisson.

    Args:
        frames, masks: the capture's frames and object masks (the visual hull's input).
        points, normals: SfM points (M, 3) and their outward normals, or None to estimate them.
        hull_config: :class:`texstream.geometry.hull.HullConfig`.
        distance_factor: open region: farther from every point than this many times the points' spacing
            (:func:`texstream.geometry.scene.point_spacing`, the median 8th-neighbour distance).
        max_angle_deg, device: see :func:`hull_fill_samples`.
        normal_neighbours: neighbours for PCA normals when ``normals`` is None.
        bounds: the object's box for the hull grid, or None (from the cameras).

    Returns:
        (points, normals, report): the SfM points first, then the kept hull samples.
    """
    p = np.asarray(points, np.float64).reshape(-1, 3)
    centres = np.array([np.asarray(f.center, np.float64).reshape(3) for f in frames])
    n = estimate_normals(p, centres, normal_neighbours) if normals is None else np.asarray(normals, np.float64)
    hull = visual_hull(frames, masks, hull_config, device, bounds=bounds)
    dist = distance_factor * point_spacing(p)
    s, sn, report = hull_fill_samples(hull, p, frames, dist, max_angle_deg, device=device)
    report["distance_factor"] = float(distance_factor)
    return np.vstack([p, s]), np.vstack([n, sn]), report
