"""Ground-truth geometry with its shading normals turned (fit/common/shading_normals.py's test and benchmark): the
true surface with normals a few degrees off, as a decimated or smoothed scan, or a mesh from photos, has them."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np

from texstream.geometry.bake import TexelBake, bake_texels
from texstream.geometry.mesh_io import load_mesh, save_mesh


def smooth_turn(mesh, max_degrees: float) -> np.ndarray:
    """``mesh``'s unit vertex normals turned by a smooth field of its positions (a few low-frequency waves), at most
    ``max_degrees``."""
    n = np.asarray(mesh.vertex_normals(), np.float64)
    p = np.asarray(mesh.vertices, np.float64) / np.asarray(mesh.vertices).std()
    field = np.stack([np.sin(3 * p[:, 1] + 1), np.cos(2 * p[:, 2]), np.sin(2.5 * p[:, 0] + 2)], axis=1)
    field -= n * np.sum(field * n, axis=1, keepdims=True)
    field *= math.radians(max_degrees) / np.linalg.norm(field, axis=1).max()
    return (n + field) / np.linalg.norm(n + field, axis=1, keepdims=True)


def random_turn(mesh, median_degrees: float, seed: int = 0) -> np.ndarray:
    """``mesh``'s unit vertex normals turned at random, welded vertex by welded vertex, ``median_degrees`` median."""
    n = np.asarray(mesh.vertex_normals(), np.float64)
    key = mesh.weld_key()
    field = np.random.default_rng(seed).normal(size=(int(key.max()) + 1, 3))[key]
    field -= n * np.sum(field * n, axis=1, keepdims=True)
    field *= math.radians(median_degrees) / np.median(np.linalg.norm(field, axis=1))
    turned = n + field
    return turned / np.linalg.norm(turned, axis=1, keepdims=True)


def geometry_with_normals(geometry: str | Path, normals: np.ndarray, out: str | Path, device: str = "cpu") -> Path:
    """An atlas folder ``out``: ``geometry``'s mesh.obj with ``normals`` and its bake at the same size made again
    (the texels' normals interpolate the new ones)."""
    geometry, out = Path(geometry), Path(out)
    out.mkdir(parents=True, exist_ok=True)
    save_mesh(out / "mesh.obj", dataclasses.replace(load_mesh(geometry / "mesh.obj"), normals=normals))
    bake = TexelBake.load(geometry / "bake.npz")
    bake_texels(load_mesh(out / "mesh.obj"), bake.width, bake.height, device=device).save(out / "bake.npz")
    return out
