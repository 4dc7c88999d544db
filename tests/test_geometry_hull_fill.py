"""Visual-hull samples as Poisson input where the SfM points leave an object's surface open
(geometry/hull_fill.py), on a sphere seen by the textured-sphere scene's camera rings (5 and 35 degrees
elevation): the points cover only what SfM would triangulate, the upper part."""

from __future__ import annotations

import numpy as np
from test_geometry_clean import icosphere
from texstream.geometry.hull import HullConfig, orbit_frames, visual_hull
from texstream.geometry.hull_fill import hull_fill_samples, poisson_points_with_hull_fill
from texstream.geometry.reconstruct import PoissonConfig, estimate_normals, poisson_reconstruct
from texstream.geometry.visibility import depth_maps


def _rings():
    return orbit_frames([0, 0, 0], 3.2, n_azimuth=12, elevations_deg=(5.0, 35.0), width=128, height=128,
                        fov_deg=45.0, poles=False)


def _upper_points(n=3000, min_latitude_deg=-30.0, seed=0):
    """Unit-sphere points above a latitude, with 0.2% noise (SfM points of the part the rings see well)."""
    rng = np.random.default_rng(seed)
    p = rng.normal(size=(4 * n, 3))
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    p = p[p[:, 2] > np.sin(np.radians(min_latitude_deg))][:n]
    return p * (1 + rng.normal(0, 0.002, (len(p), 1)))


def _mesh(frames, masks, pts, fill: bool, device):
    cfg = HullConfig(resolution=64)
    centres = np.array([f.center for f in frames])
    if fill:
        pts, nrm, rep = poisson_points_with_hull_fill(frames, masks, pts, None, cfg, 2.0, 60.0, device=device)
    else:
        nrm, rep = estimate_normals(pts, centres), {}
    pois = poisson_reconstruct(pts, nrm, centres, PoissonConfig(depth=6, density_quantile=0.0))
    lo, hi = pois.bbox()
    return visual_hull(frames, masks, cfg, device, bounds=(lo, hi), intersect=pois), rep


def test_hull_fill_restores_the_unseen_underside(device):
    sphere = icosphere(4)
    frames = _rings()
    masks = [np.isfinite(d) for d in depth_maps(sphere, frames, device)]
    pts = _upper_points()
    bottom, p99 = {}, {}
    for fill in (False, True):
        mesh, rep = _mesh(frames, masks, pts, fill, device)
        bottom[fill] = float(mesh.vertices[:, 2].min())
        p99[fill] = float(np.quantile(np.abs(np.linalg.norm(mesh.vertices, axis=1) - 1), 0.99))
        if fill:
            # hull samples kept only in the open region below the points, not among them
            assert 0 < rep["kept"] <= rep["far_from_points"] < rep["hull_samples"]
    print(f"bottom z {bottom}, 99th percentile radial error {p99}")
    # Without the fill Poisson closes the open underside far inside the silhouettes (measured: bottom at
    # z = -0.77 against the sphere's -1, 99th percentile radial error 20.6%). With it the bottom is the hull's
    # (measured -1.07: the apex of the silhouette cones from 12 azimuths at 5 degrees elevation, which reach
    # 1/sin(66.8 deg) - 1 = 9% below the sphere for a continuous ring) and the 99th percentile error 2.4%.
    assert bottom[False] > -0.85 and p99[False] > 0.15, (bottom, p99)
    assert -1.09 < bottom[True] < -0.98 and p99[True] < 0.04, (bottom, p99)


def test_samples_seen_well_by_two_cameras_are_left_out(device):
    """A region with no points that two cameras see face-on is not filled from the hull (a concavity the
    hull bridges, or textureless surface): all-around cameras, points removed from one side only."""
    sphere = icosphere(3)
    frames = orbit_frames([0, 0, 0], 3.2, n_azimuth=8, elevations_deg=(-30.0, 0.0, 30.0), width=96, height=96)
    masks = [np.isfinite(d) for d in depth_maps(sphere, frames, device)]
    hull = visual_hull(frames, masks, HullConfig(resolution=48), device)
    pts = _upper_points(min_latitude_deg=-90.0)
    pts = pts[pts[:, 0] < 0.5]  # a cap with no points, facing the cameras on the +x side
    s, _, rep = hull_fill_samples(hull, pts, frames, distance=0.2, max_angle_deg=60.0, device=device)
    assert rep["far_from_points"] > 50  # the cap is open...
    # ...but seen well: the hull does not fill it (measured: 2 of 2,385 open samples kept, 0.1%; the faceted
    # hull's normals leave a few samples seen within 60 degrees by only one camera)
    assert rep["kept"] <= 0.02 * rep["far_from_points"] and len(s) == rep["kept"]
