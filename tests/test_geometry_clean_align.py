"""Coarse Sim3 + ICP alignment of a mesh to partial, noisy points in another frame and scale."""

from __future__ import annotations

import numpy as np

from texstream.geometry.align import align_to_points, sample_mesh, transform_mesh
from test_geometry_clean import icosphere


def _rot(axis, deg):
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    th = np.radians(deg)
    return np.eye(3) + np.sin(th) * k + (1 - np.cos(th)) * k @ k


def test_icp_recovers_similarity_from_partial_noisy_points():
    # an asymmetric body (stretched sphere with a bump) so the pose is unique
    m = icosphere(3)
    v = m.vertices * [2.0, 1.0, 0.6]
    v[:, 0] += 0.4 * np.exp(-((v[:, 1] - 0.5) ** 2 + v[:, 2] ** 2) * 8)
    mesh = type(m)(v, m.faces)
    s_true, r_true, t_true = 3.0, _rot([1, 2, 3], 25.0), np.array([5.0, -2.0, 1.0])
    rng = np.random.default_rng(1)
    pts = sample_mesh(mesh, 3000, seed=5)
    pts = pts[pts[:, 2] > -0.3]  # partial: the underside was not reconstructed
    pts = s_true * pts @ r_true.T + t_true
    pts += rng.normal(scale=0.01, size=pts.shape)  # SfM noise, ~0.2% of the diagonal
    pts = np.concatenate([pts, rng.uniform(-5, 10, size=(40, 3))])  # outliers
    al = align_to_points(mesh, pts, samples=8000)
    # scale and rotation within what 0.01 noise on ~2500 points allows (measured ~1e-3)
    assert abs(al.scale / s_true - 1) < 0.01
    assert np.degrees(np.arccos(np.clip((np.trace(al.R.T @ r_true) - 1) / 2, -1, 1))) < 1.0
    moved = transform_mesh(mesh, al.matrix)
    ref = s_true * mesh.vertices @ r_true.T + t_true
    assert np.abs(moved.vertices - ref).max() < 0.05 * np.linalg.norm(np.ptp(ref, axis=0))
