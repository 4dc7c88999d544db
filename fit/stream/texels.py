"""The texels a streaming fit solves for (:class:`TexelSet`) and the surface derivatives they carry.

Imports only numpy."""

from __future__ import annotations

import dataclasses

import numpy as np


@dataclasses.dataclass
class TexelSet:
    """The texels being fitted (compact: covered atlas texels only) and their grid neighbours.

    Attributes:
        position, normal, tangent, bitangent: (N, 3) float32 surface location space.
        grid_index: (N,) int64 flat index y * width + x of each texel in the atlas.
        neighbors: (N, 4) int32 compact indices of the +x, -x, +y, -y neighbours (-1: none),
            the masked stencil of the Laplacian (Alg. 7).
        width, height: atlas size.
        face_normal: (N, 3) float32 unit normal of each texel's face (None: the shading normal).
        normal_jacobian: (N, 3, 3) float32 derivative of the shading normal along the face, over
            the interpolated normal's length (:func:`surface_derivatives`; None: zero, a flat texel).
            Both serve point sampling (``StreamConfig.photo_sampling``).
        coordinate_gradients: (N, 2, 3) float32 gradients of the texel coordinates along each
            texel's face (:func:`texel_coordinate_gradients`; None: no atlas, e.g. single-view fits).
        grid_source: (H * W,) int64 per atlas texel, the compact texel whose value the renderer
            reads there (itself, or the texel its padding copies), -1 for none (the defaults).
            Both serve the renderer's texture lookup (``StreamConfig.model_lookup``).
    """

    position: np.ndarray
    normal: np.ndarray
    tangent: np.ndarray
    bitangent: np.ndarray
    grid_index: np.ndarray
    neighbors: np.ndarray
    width: int
    height: int
    face_normal: np.ndarray | None = None
    normal_jacobian: np.ndarray | None = None
    coordinate_gradients: np.ndarray | None = None
    grid_source: np.ndarray | None = None

    @property
    def n(self) -> int:
        return int(self.position.shape[0])

    @staticmethod
    def from_grid(covered: np.ndarray, position: np.ndarray, normal: np.ndarray, tangent: np.ndarray,
                  bitangent: np.ndarray, face_normal: np.ndarray | None = None,
                  normal_jacobian: np.ndarray | None = None, coordinate_gradients: np.ndarray | None = None,
                  fill_source: np.ndarray | None = None) -> "TexelSet":
        """Build from (H, W) coverage and (H, W, 3) frames (e.g. a TexelBake or an image grid);
        optional (H, W, 3) face normals, (H, W, 3, 3) normal Jacobians, (H, W, 2, 3) texel
        coordinate gradients and the bake's (H, W) padding sources (``TexelBake.fill_source``;
        see the attributes)."""
        h, w = covered.shape
        flat = np.flatnonzero(covered.reshape(-1))
        compact = -np.ones(h * w, dtype=np.int64)
        compact[flat] = np.arange(flat.size)
        ys, xs = np.divmod(flat, w)
        nb = -np.ones((flat.size, 4), dtype=np.int32)
        for k, (dx, dy) in enumerate(((1, 0), (-1, 0), (0, 1), (0, -1))):
            xx, yy = xs + dx, ys + dy
            inside = (xx >= 0) & (xx < w) & (yy >= 0) & (yy < h)
            nb[inside, k] = compact[yy[inside] * w + xx[inside]]
        def take(a, width=3):
            return None if a is None else np.ascontiguousarray(a.reshape(-1, width)[flat], dtype=np.float32)
        jac = take(normal_jacobian, 9)
        grads = take(coordinate_gradients, 6)
        source = None
        if grads is not None:
            # the renderer reads a padding texel's copy of its fill source (TexelBake.fill_padding)
            src = np.arange(h * w) if fill_source is None else np.asarray(fill_source).reshape(-1)
            source = np.where(src >= 0, compact[np.maximum(src, 0)], -1)
        return TexelSet(take(position), take(normal), take(tangent), take(bitangent), flat, nb, w, h,
                        take(face_normal), None if jac is None else jac.reshape(-1, 3, 3),
                        None if grads is None else grads.reshape(-1, 2, 3), source)


def surface_derivatives(points: np.ndarray, faces: np.ndarray, normals: np.ndarray, face: np.ndarray,
                        bary: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per texel, the unit normal of its face and the Jacobian of its shading normal along the face.

    The shading normal interpolates vertex normals, N(p) = sum_j b_j(p) n_j, which is affine in p
    on a face: N(p + dp) = N(p) + G dp with G = [n1 - n0, n2 - n0] E^+ (E = [p1 - p0, p2 - p0],
    E^+ its pseudo-inverse, so in-plane offsets map to barycentric changes). Returned divided by
    |N(p)|, so normalize(n + G' dp) is the renderer's unit shading normal at p + dp
    (:func:`texstream.render.shading.surface_frame`).

    Args:
        points, faces, normals: the mesh (V, 3), (F, 3) and the (V, 3) vertex normals the texel bake used.
        face: (...,) owning face per texel, -1 for none (zeros returned there).
        bary: (..., 3) barycentrics (b0, b1, b2) of the texel centre in its face.
    Returns:
        face_normal (..., 3) and normal_jacobian (..., 3, 3), float32.
    """
    shape = face.shape
    on = np.flatnonzero(face.reshape(-1) >= 0)  # texels on no face keep zeros: half an atlas is padding
    where, tri, e, inv, good_face = _face_pseudo_inverse(points, faces, face.reshape(-1)[on])
    nv = normals.astype(np.float64)[tri]                     # per face used
    dn = np.stack([nv[:, 1] - nv[:, 0], nv[:, 2] - nv[:, 0]], axis=2)
    jac_face = np.einsum("nkj,nji,nli->nkl", dn, inv, e)     # dn (3x2) @ inv (2x2) @ e^T (2x3)
    b = bary.reshape(-1, 3)[on].astype(np.float64)
    interp = np.einsum("nj,njk->nk", b, nv[where])           # per texel
    length = np.linalg.norm(interp, axis=1)
    jac = jac_face[where] / np.maximum(length, 1e-12)[:, None, None]
    good = good_face[where]
    jac[~good] = 0.0
    fn_face = np.cross(e[:, :, 0], e[:, :, 1])
    fn_face /= np.maximum(np.linalg.norm(fn_face, axis=1, keepdims=True), 1e-300)
    fn = fn_face[where]
    fn[~good] = interp[~good] / np.maximum(length[~good], 1e-12)[:, None]
    fn_out = np.zeros((face.size, 3), np.float32)
    jac_out = np.zeros((face.size, 3, 3), np.float32)
    fn_out[on], jac_out[on] = fn, jac
    return fn_out.reshape(*shape, 3), jac_out.reshape(*shape, 3, 3)


def _face_pseudo_inverse(points: np.ndarray, faces: np.ndarray, face: np.ndarray):
    """Per face that texels of ``face`` (N,) use (computed once a face, not once a texel): ``where`` (N,), each
    texel's row in the per-face arrays (texels without a face, -1, point at face 0's and are masked by the
    callers); the faces' vertex ids (M, 3), edges E = [p1 - p0, p2 - p0] (M, 3, 2), (E^T E)^-1 (M, 2, 2;
    zero where degenerate) and that mask (M,), so that (E^T E)^-1 E^T dp is the barycentric change (b1, b2)
    of an in-plane offset dp."""
    ids = np.maximum(face.reshape(-1), 0)
    present = np.zeros(len(faces), dtype=bool)
    present[ids] = True
    used = np.flatnonzero(present)  # np.unique's sorted ids and inverse, in linear time (it sorted every texel)
    rank = np.cumsum(present) - 1
    where = rank[ids]
    tri = faces[used]
    p = points.astype(np.float64)[tri]                      # (M, 3 vertices, 3)
    e = np.stack([p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]], axis=2)   # (M, 3, 2)
    gram = np.einsum("nki,nkj->nij", e, e)
    det = gram[:, 0, 0] * gram[:, 1, 1] - gram[:, 0, 1] * gram[:, 1, 0]
    good = det > 1e-30 * np.maximum(gram[:, 0, 0] * gram[:, 1, 1], 1e-300)
    inv = np.zeros_like(gram)
    inv[good] = np.linalg.inv(gram[good])
    return where.reshape(-1), tri, e, inv, good


def texel_coordinate_gradients(points: np.ndarray, faces: np.ndarray, uvs: np.ndarray, face: np.ndarray,
                               width: int, height: int) -> np.ndarray:
    """Per texel, the gradients along its face of the continuous texel coordinates (x, y) =
    (u W - 1/2, (1 - v) H - 1/2) (:func:`texstream.render.shading.texel_coords`).

    UVs are affine on a face, so (x, y)(p + dp) = (x, y)(p) + T E^+ dp with T the face's texel
    coordinate edges [t1 - t0, t2 - t0]: what the renderer's texture lookup reads at a point near
    the texel (``StreamConfig.model_lookup``). Returns (..., 2, 3) float32, zero where the face
    is missing or degenerate.
    """
    shape = face.shape
    on = np.flatnonzero(face.reshape(-1) >= 0)
    where, tri, e, inv, good_face = _face_pseudo_inverse(points, faces, face.reshape(-1)[on])
    t = np.asarray(uvs, np.float64)[tri] * np.array([width, -height], np.float64)   # (M, 3 vertices, 2)
    te = np.stack([t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]], axis=2)                   # (M, 2, 2)
    grad_face = np.einsum("nkj,nji,nli->nkl", te, inv, e)                           # T (2x2) inv (2x2) E^T (2x3)
    grad_face[~good_face] = 0.0
    grad = np.zeros((face.size, 2, 3), np.float32)
    grad[on] = grad_face[where]
    return grad.reshape(*shape, 2, 3)
