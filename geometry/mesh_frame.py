"""A registration brought into a given mesh's frame (``texstream register --align-mesh MESH``).

The similarity of :func:`texstream.geometry.align.align_to_points` (PCA start, trimmed scaled ICP of the
mesh onto the SfM points), inverted, so cameras and points land on the mesh. The registration stage
(calib, below geometry) receives :func:`mesh_alignment` from its caller, which may import both.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from texstream.core.errors import StageError
from texstream.geometry.align import align_to_points
from texstream.geometry.mesh_io import load_mesh, validate_mesh


def mesh_alignment(path: str) -> Callable[[Any, float], dict]:
    """The mesh at ``path`` loaded and checked, as ``align(rec, max_rms_frac)``: :func:`align_to_mesh` onto it
    (``texstream.calib.register.register``'s ``mesh_alignment``, called where it needs the mesh)."""
    mesh = load_mesh(path)
    validate_mesh(mesh, path)

    def align(rec: Any, max_rms_frac: float) -> dict:
        return align_to_mesh(rec, mesh, max_rms_frac)

    return align


def mesh_frame_transform(mesh: Any, points: np.ndarray, seed: int = 0) -> tuple[float, np.ndarray, np.ndarray, dict]:
    """The similarity taking SfM-frame points into a given mesh's frame: x_mesh = s R x + t.

    :func:`texstream.geometry.align.align_to_points` finds the mesh -> points similarity (PCA
    start over the proper axis sign choices, trimmed scaled ICP); this is its inverse. A mesh with
    a symmetry (sphere, surface of revolution) leaves the rotation about it undetermined.

    Args:
        mesh: the given SurfaceMesh (its frame is the target frame).
        points: (N, 3) SfM points, N >= 10.
        seed: unused by the deterministic ICP; kept for a uniform signature with the RANSAC aligner.

    Returns:
        (s, R (3, 3), t (3,), info) with info ``rms_fraction`` (trimmed RMS point-to-mesh-sample
        distance over the points' bbox diagonal), ``rms`` (mesh units) and ``iterations``.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(pts) < 10:
        raise StageError(f"only {len(pts)} SfM point(s) to align to the mesh; at least 10 are needed",
                         fix="register more photos, or use --align-to with known camera centres")
    al = align_to_points(mesh, pts)
    s = 1.0 / al.scale
    r = al.R.T
    t = -s * (r @ al.t)
    return s, r, t, {"rms_fraction": float(al.rms_fraction), "rms": float(al.rms * s), "iterations": int(al.iterations)}


def align_to_mesh(rec: Any, mesh: Any, max_rms_frac: float) -> dict:
    """Bring a reconstruction in place into a mesh's frame (scaled ICP of its points onto the mesh).

    Args:
        rec: pycolmap.Reconstruction (modified in place).
        mesh: SurfaceMesh in the target frame.
        max_rms_frac: accepted trimmed RMS point-to-mesh distance as a fraction of the points' extent.

    Returns:
        dict with ``scale``, ``rms`` (mesh units), ``rms_fraction``, ``points`` (points used).

    Raises:
        StageError: too few points, or the fit's residual above ``max_rms_frac`` (wrong mesh / object).
    """
    import pycolmap

    pts = np.array([p.xyz for p in rec.points3D.values()], dtype=np.float64).reshape(-1, 3)
    s, r, t, info = mesh_frame_transform(mesh, pts)
    if not info["rms_fraction"] <= max_rms_frac:
        raise StageError(f"the SfM points do not fit the mesh (RMS {info['rms_fraction']:.3g} of their extent, "
                         f"accepted {max_rms_frac:g})",
                         fix="check that --align-mesh is this object's mesh, or raise --align-mesh-max-rms")
    rec.transform(pycolmap.Sim3d(s, pycolmap.Rotation3d(r), t))
    return {"scale": float(s), "rms": info["rms"], "rms_fraction": info["rms_fraction"], "points": int(len(pts)),
            "kind": "mesh"}
