"""Bring a given mesh into the capture frame: coarse Sim3 from principal axes, then scaled ICP.

The target is the capture's SfM points (noisy, partial, in an arbitrary scale). The coarse step
matches centroids, RMS radii and principal axes (the four proper sign choices of the axes are all
tried); ICP then refines a similarity transform (Umeyama) on trimmed nearest-neighbour pairs from
every target point to points sampled on the mesh.

numpy / scipy only.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from texstream.render.mesh import SurfaceMesh


@dataclasses.dataclass
class Alignment:
    """A similarity transform x' = scale * R @ x + t, and how well it fits.

    Attributes:
        matrix: (4, 4) the same transform as a homogeneous matrix.
        rms: RMS distance of the kept (trimmed) target points to the transformed mesh samples.
        rms_fraction: ``rms`` over the target's bbox diagonal.
        iterations: ICP iterations run.
    """

    scale: float
    R: np.ndarray
    t: np.ndarray
    rms: float
    rms_fraction: float
    iterations: int

    @property
    def matrix(self) -> np.ndarray:
        m = np.eye(4)
        m[:3, :3] = self.scale * self.R
        m[:3, 3] = self.t
        return m

    def apply(self, points: np.ndarray) -> np.ndarray:
        return self.scale * np.asarray(points) @ self.R.T + self.t


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool = True) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity (s, R, t) with dst ~ s R src + t (Umeyama 1991). src, dst: (N, 3)."""
    ms, md = src.mean(axis=0), dst.mean(axis=0)
    a, b = src - ms, dst - md
    cov = b.T @ a / len(src)
    u, d, vt = np.linalg.svd(cov)
    sgn = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        sgn[2, 2] = -1
    r = u @ sgn @ vt
    var = (a * a).sum() / len(src)
    s = float(np.trace(np.diag(d) @ sgn) / var) if with_scale and var > 0 else 1.0
    return s, r, md - s * r @ ms


def sample_mesh(mesh: SurfaceMesh, n: int, seed: int = 0) -> np.ndarray:
    """(n, 3) area-uniform random points on the mesh (plus its vertices are not included)."""
    rng = np.random.default_rng(seed)
    a = mesh.face_areas()
    fi = rng.choice(len(a), size=n, p=a / a.sum())
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    bary = np.stack([1 - s, s * (1 - r2), s * r2], axis=1)
    return np.einsum("ni,nij->nj", bary, mesh.vertices[mesh.faces[fi]])


def _pca(p: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    c = p.mean(axis=0)
    q = p - c
    _, vecs = np.linalg.eigh(q.T @ q)
    return c, vecs[:, ::-1], float(np.sqrt((q * q).sum(axis=1).mean()))


def align_to_points(mesh: SurfaceMesh, points: np.ndarray, iterations: int = 40, trim: float = 0.9,
                    samples: int = 20000, with_scale: bool = True) -> Alignment:
    """Similarity transform taking ``mesh`` onto ``points`` (coarse PCA Sim3, then trimmed ICP).

    Args:
        mesh: the given mesh (any frame and scale).
        points: (N, 3) target points (SfM points of the capture).
        iterations: ICP iterations per start.
        trim: fraction of nearest-neighbour pairs kept (drops SfM outliers and unmatched parts).
        samples: points sampled on the mesh for matching.
        with_scale: estimate scale (off when the mesh is known to be metric like the capture).

    Returns:
        The best :class:`Alignment` over the coarse starts.
    """
    from scipy.spatial import cKDTree

    tgt = np.asarray(points, np.float64)
    src = sample_mesh(mesh, samples)
    cs, axs, rs = _pca(src)
    ct, axt, rt = _pca(tgt)
    diag = float(np.linalg.norm(tgt.max(axis=0) - tgt.min(axis=0)))
    best: Alignment | None = None
    for signs in ((1, 1, 1), (1, -1, -1), (-1, 1, -1), (-1, -1, 1)):
        r = axt @ np.diag(signs) @ axs.T
        s = rt / rs if with_scale else 1.0
        t = ct - s * r @ cs
        cur = Alignment(s, r, t, np.inf, np.inf, 0)
        for it in range(iterations):
            moved = cur.apply(src)
            dist, idx = cKDTree(moved).query(tgt)
            keep = dist <= np.quantile(dist, trim)
            s, r, t = umeyama(src[idx[keep]], tgt[keep], with_scale)
            rms = float(np.sqrt((dist[keep] ** 2).mean()))
            converged = abs(cur.rms - rms) < 1e-7 * diag
            cur = Alignment(s, r, t, rms, rms / diag if diag > 0 else np.inf, it + 1)
            if converged:
                break
        moved = cur.apply(src)
        dist, _ = cKDTree(moved).query(tgt)
        cur.rms = float(np.sqrt((np.sort(dist)[: max(1, int(trim * len(dist)))] ** 2).mean()))
        cur.rms_fraction = cur.rms / diag if diag > 0 else np.inf
        if best is None or cur.rms < best.rms:
            best = cur
    assert best is not None
    return best


def transform_mesh(mesh: SurfaceMesh, matrix: np.ndarray) -> SurfaceMesh:
    """Mesh with vertices mapped by a 4x4 similarity (normals rotated; faces flipped if det < 0)."""
    m = np.asarray(matrix, np.float64)
    v = mesh.vertices @ m[:3, :3].T + m[:3, 3]
    faces = mesh.faces if np.linalg.det(m[:3, :3]) > 0 else mesh.faces[:, ::-1].copy()
    normals = None
    if mesh.normals is not None:
        n = mesh.normals @ np.linalg.inv(m[:3, :3])  # inverse transpose
        normals = n / np.linalg.norm(n, axis=1, keepdims=True)
    return dataclasses.replace(mesh, vertices=v, faces=faces, normals=normals)
