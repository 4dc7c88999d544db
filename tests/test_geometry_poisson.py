"""Screened Poisson from oriented points sampled on known surfaces; too few points; mask trimming."""

from __future__ import annotations

import numpy as np
import pytest

from texstream.geometry.clean import hausdorff_distance, topology
from texstream.geometry.hull import orbit_frames
from texstream.geometry.reconstruct import PoissonConfig, estimate_normals, poisson_reconstruct, trim_by_masks
from texstream.geometry.visibility import depth_maps
from texstream.core.errors import InputError
from test_geometry_clean import icosphere


def sample_surface(mesh, n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Area-uniform random points on a mesh and their face normals."""
    rng = np.random.default_rng(seed)
    a = mesh.face_areas()
    fi = rng.choice(len(a), size=n, p=a / a.sum())
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    bary = np.stack([1 - s, s * (1 - r2), s * r2], axis=1)
    p = np.einsum("ni,nij->nj", bary, mesh.vertices[mesh.faces[fi]])
    return p, mesh.face_normals()[fi]


def test_poisson_sphere_from_points_with_estimated_normals():
    sphere = icosphere(4)
    pts, _ = sample_surface(sphere, 4000)
    cams = np.array([c.center for c in orbit_frames([0, 0, 0], 3.0, n_azimuth=6)])
    n = estimate_normals(pts, cams, 12)
    assert np.mean(np.einsum("ij,ij->i", n, pts) > 0) > 0.99  # oriented outwards
    mesh = poisson_reconstruct(pts, None, cams, PoissonConfig(depth=6, density_quantile=0.0))
    h = hausdorff_distance(mesh, sphere)
    # depth 6 = 64 cells over ~2.2 units: cell 0.034; Poisson smooths within about half a cell
    assert h["mean_fraction"] < 0.005, h
    t = topology(mesh)
    assert t["watertight"] and t["genus"] == 0 and t["signed_volume"] > 0


def test_too_few_points_names_the_fallback():
    pts, nrm = sample_surface(icosphere(2), 50)
    with pytest.raises(InputError, match="--from hull"):
        poisson_reconstruct(pts, nrm)


def test_mask_trim_removes_invented_surface(device):
    # Points on the upper hemisphere only: Poisson invents a lid below; masks of the hemisphere cut it.
    sphere = icosphere(4)
    pts, nrm = sample_surface(sphere, 4000)
    keep = pts[:, 2] > 0
    # scale 1.1: a tight cube keeps the invented lid near the cut (at the default 2.0 it balloons
    # half a radius further, partly where no view sees it to trim)
    mesh = poisson_reconstruct(pts[keep], nrm[keep], None, PoissonConfig(depth=6, scale=1.1, density_quantile=0.0))
    # the true object: the upper half of the sphere
    half = icosphere(4)
    fz = half.vertices[half.faces].mean(axis=1)[:, 2]
    half.faces = half.faces[fz > 0]
    frames = orbit_frames([0, 0, 0], 4.0, n_azimuth=6, elevations_deg=(-40, 0, 40), width=96, height=96)
    masks = [np.isfinite(d) for d in depth_maps(half, frames, device)]
    trimmed = trim_by_masks(mesh, frames, masks, device)
    assert trimmed.n_faces < mesh.n_faces
    # what survives lies above the cut (within ~ a Poisson cell of it)
    assert trimmed.vertices[:, 2].min() > -0.1 and mesh.vertices[:, 2].min() < -0.2
