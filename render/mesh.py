"""The in-memory triangle mesh every stage passes around.

UVs are per vertex (vertices are split along UV seams, as xatlas and glTF do); ``source_vertex``
maps each vertex back to the welded input vertex so seams can be stitched. numpy only.
"""

from __future__ import annotations

import dataclasses

import numpy as np


@dataclasses.dataclass
class SurfaceMesh:
    """A triangle mesh.

    Attributes:
        vertices: (V, 3) float64 positions (world units of the capture frame).
        faces: (F, 3) int32 vertex indices, counter-clockwise seen from outside.
        normals: (V, 3) float64 unit vertex normals, or None (computed on demand).
        uvs: (V, 2) float64 texture coordinates in [0, 1]^2 (v up), or None.
        source_vertex: (V,) int32 index of the welded vertex each vertex came from, or None.
    """

    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray | None = None
    uvs: np.ndarray | None = None
    source_vertex: np.ndarray | None = None

    @property
    def n_vertices(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def n_faces(self) -> int:
        return int(self.faces.shape[0])

    def bbox(self) -> tuple[np.ndarray, np.ndarray]:
        return self.vertices.min(axis=0), self.vertices.max(axis=0)

    def bbox_diagonal(self) -> float:
        lo, hi = self.bbox()
        return float(np.linalg.norm(hi - lo))

    def face_normals(self) -> np.ndarray:
        """(F, 3) unit face normals (zero for degenerate faces)."""
        v = self.vertices[self.faces]
        n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
        ln = np.linalg.norm(n, axis=1, keepdims=True)
        return np.divide(n, ln, out=np.zeros_like(n), where=ln > 0)

    def face_areas(self) -> np.ndarray:
        v = self.vertices[self.faces]
        return 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)

    def vertex_normals(self) -> np.ndarray:
        """Area-weighted vertex normals, accumulated over welded vertices so seams share normals."""
        if self.normals is not None:
            return self.normals
        v = self.vertices[self.faces]
        fn = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])  # length = 2 * area
        key = self.source_vertex if self.source_vertex is not None else np.arange(self.n_vertices)
        nk = int(key.max()) + 1 if key.size else 0
        acc = np.zeros((nk, 3))
        for c in range(3):
            np.add.at(acc, key[self.faces[:, c]], fn)
        n = acc[key]
        ln = np.linalg.norm(n, axis=1, keepdims=True)
        return np.divide(n, ln, out=np.tile([0.0, 0.0, 1.0], (len(n), 1)), where=ln > 0)

    def weld_key(self) -> np.ndarray:
        """(V,) int64 compact index of the welded vertex each vertex belongs to: ``source_vertex`` when the mesh
        has it (an atlas splits vertices along UV seams), else vertices at equal positions."""
        if self.source_vertex is not None:
            key = np.asarray(self.source_vertex, np.int64)
        else:
            key = np.unique(np.asarray(self.vertices), axis=0, return_inverse=True)[1]
        return np.unique(key.reshape(-1), return_inverse=True)[1].reshape(-1).astype(np.int64)

    def with_normals(self) -> "SurfaceMesh":
        return dataclasses.replace(self, normals=self.vertex_normals())
