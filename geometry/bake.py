"""Texel bake: the surface location space (SLS) of an atlas, one record per texel.

For every texel of a ``width x height`` atlas the bake stores whether its centre lies on the
surface (``covered``), the triangle that owns it, its barycentrics there, and the 3D position,
shading normal and tangent frame at that point. Texels in the padding around charts are filled
from a nearby covered texel (``fill_source``) so that bilinear lookups near chart borders read
values of the same chart instead of the background.

Rasterisation rules (kernel ``_claim_texels``)
    Texel (x, y) has its centre at texel coordinates (x, y) = (u W - 1/2, (1 - v) H - 1/2)
    (:func:`texstream.capture.conventions.texel_center_uv`). A face covers a texel when the centre
    lies inside or on its UV triangle (inclusive test, float64). The edge function of an edge is
    always evaluated from its lower to its higher vertex index and negated as needed, so the two
    faces sharing an edge get exactly opposite values: a centre on a shared edge is covered by
    at least one of them, never by neither. Each covered texel is owned by the lowest face id
    that covers it (``wp.atomic_min``), so ownership is unique and deterministic on every device.

Orphan faces
    A sliver UV triangle may contain no texel centre. With ``claim_orphans`` (default) such a face
    takes the texel nearest its UV centroid, or failing that one within 2 texels, nearest first:
    a free texel, or one whose owner keeps another texel (the fit then has one sample fewer
    there). The texel's barycentrics are clamped onto the face (negative ones set to 0 and the
    rest renormalised), so its position is a point of the face (a face with degenerate UVs gets
    its centroid). Faces still without a texel (every candidate taken) are listed in
    ``TexelBake.faces_without_texels``.

The frame at each texel comes from :func:`texstream.render.shading.surface_frame`, the same
function the renderer and the fit use.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import numpy as np
import warp as wp

from texstream.render.shading import surface_frame
from texstream.core.errors import InputError

from texstream.render.mesh import SurfaceMesh
from .mesh_io import write_npz_atomic

# nothing here is differentiated: skipping Warp's adjoint code generation roughly halves
# compile time
wp.set_module_options({"enable_backward": False})

_NO_OWNER = 2147483647  # int32 max: "unclaimed" for atomic_min


@wp.func
def _orient(ax: wp.float64, ay: wp.float64, bx: wp.float64, by: wp.float64,
            px: wp.float64, py: wp.float64) -> wp.float64:
    """Twice the signed area of (a, b, p)."""
    return (bx - ax) * (py - ay) - (by - ay) * (px - ax)


@wp.func
def _edge(tx: wp.array(dtype=wp.float64), ty: wp.array(dtype=wp.float64), ia: int, ib: int,
          px: wp.float64, py: wp.float64) -> wp.float64:
    """Edge function of the directed edge ia -> ib at p, evaluated in a canonical vertex order
    so the two faces sharing the edge get exactly opposite values (no cracks on shared edges)."""
    if ia < ib:
        return _orient(tx[ia], ty[ia], tx[ib], ty[ib], px, py)
    return -_orient(tx[ib], ty[ib], tx[ia], ty[ia], px, py)


@wp.kernel
def _claim_texels(tx: wp.array(dtype=wp.float64), ty: wp.array(dtype=wp.float64),
                  faces: wp.array(dtype=wp.int32), width: int, height: int,
                  owner: wp.array(dtype=wp.int32)):
    """One thread per face: claim every texel centre inside its UV triangle (lowest face id wins)."""
    f = wp.tid()
    i0 = faces[f * 3 + 0]
    i1 = faces[f * 3 + 1]
    i2 = faces[f * 3 + 2]
    area = _orient(tx[i0], ty[i0], tx[i1], ty[i1], tx[i2], ty[i2])
    if area == wp.float64(0.0):
        return
    s = wp.float64(1.0)
    if area < wp.float64(0.0):
        s = wp.float64(-1.0)
    xmin = wp.max(int(wp.ceil(wp.min(tx[i0], wp.min(tx[i1], tx[i2])))), 0)
    xmax = wp.min(int(wp.floor(wp.max(tx[i0], wp.max(tx[i1], tx[i2])))), width - 1)
    ymin = wp.max(int(wp.ceil(wp.min(ty[i0], wp.min(ty[i1], ty[i2])))), 0)
    ymax = wp.min(int(wp.floor(wp.max(ty[i0], wp.max(ty[i1], ty[i2])))), height - 1)
    zero = wp.float64(0.0)
    for y in range(ymin, ymax + 1):
        py = wp.float64(y)
        for x in range(xmin, xmax + 1):
            px = wp.float64(x)
            e0 = s * _edge(tx, ty, i1, i2, px, py)
            e1 = s * _edge(tx, ty, i2, i0, px, py)
            e2 = s * _edge(tx, ty, i0, i1, px, py)
            if e0 >= zero and e1 >= zero and e2 >= zero:
                wp.atomic_min(owner, y * width + x, f)


@wp.kernel
def _bake_frames(tx: wp.array(dtype=wp.float64), ty: wp.array(dtype=wp.float64),
                 faces: wp.array(dtype=wp.int32), points: wp.array(dtype=wp.vec3),
                 normals: wp.array(dtype=wp.vec3), uvs: wp.array(dtype=wp.vec2),
                 owner: wp.array(dtype=wp.int32), width: int,
                 bary: wp.array(dtype=wp.vec3), position: wp.array(dtype=wp.vec3),
                 normal: wp.array(dtype=wp.vec3), tangent: wp.array(dtype=wp.vec3),
                 bitangent: wp.array(dtype=wp.vec3)):
    """One thread per texel: barycentrics of its centre in its owner face, then the shared frame."""
    k = wp.tid()
    f = owner[k]
    if f < 0:
        return
    px = wp.float64(k % width)
    py = wp.float64(k // width)
    i0 = faces[f * 3 + 0]
    i1 = faces[f * 3 + 1]
    i2 = faces[f * 3 + 2]
    area = _orient(tx[i0], ty[i0], tx[i1], ty[i1], tx[i2], ty[i2])
    if area == wp.float64(0.0):
        # degenerate UV triangle (an orphan claim): use its centroid
        third = 1.0 / 3.0
        pos, uv, n, t, b = surface_frame(points, faces, normals, uvs, f, third, third)
        bary[k] = wp.vec3(third, third, third)
        position[k] = pos
        normal[k] = n
        tangent[k] = t
        bitangent[k] = b
        return
    # b_i = (area of the sub-triangle opposite vertex i) / area, Warp's mesh_query_ray convention.
    b0 = wp.max(_edge(tx, ty, i1, i2, px, py) / area, wp.float64(0.0))
    b1 = wp.max(_edge(tx, ty, i2, i0, px, py) / area, wp.float64(0.0))
    b2 = wp.max(_edge(tx, ty, i0, i1, px, py) / area, wp.float64(0.0))
    sb = b0 + b1 + b2  # 1 up to rounding; clamping above keeps centres on edges on the face
    b0 = b0 / sb
    b1 = b1 / sb
    b2 = b2 / sb
    pos, uv, n, t, b = surface_frame(points, faces, normals, uvs, f, float(b0), float(b1))
    bary[k] = wp.vec3(float(b0), float(b1), float(b2))
    position[k] = pos
    normal[k] = n
    tangent[k] = t
    bitangent[k] = b


@dataclasses.dataclass
class TexelBake:
    """The baked surface location space of a ``width x height`` atlas (row 0 at the top).

    Attributes:
        width: atlas width in texels.
        height: atlas height in texels.
        face: (H, W) int32 owning face id, -1 where the texel centre is on no face.
        bary: (H, W, 3) float32 barycentrics (b0, b1, b2) of the texel centre in ``face``,
            p = b0 p0 + b1 p1 + b2 p2 (Warp ``mesh_query_ray`` convention); 0 where uncovered.
        position: (H, W, 3) float32 world position of the texel centre (scene units).
        normal: (H, W, 3) float32 unit shading normal (interpolated vertex normals).
        tangent: (H, W, 3) float32 unit tangent (dp/du made orthogonal to the normal).
        bitangent: (H, W, 3) float32 unit bitangent, normal x tangent.
        covered: (H, W) bool, ``face >= 0``.
        fill_source: (H, W) int32 flat index ``y * W + x`` of the texel whose value this texel
            holds: itself for covered texels, a covered texel at most ``padding`` texels away
            (chessboard distance) for padding texels, -1 farther away.
        padding: the fill radius in texels used to build ``fill_source``.
        faces_without_texels: (K,) int32 ids of faces that own no texel (UV triangles too small
            to contain a texel centre, or degenerate); their surface is still textured through
            bilinear lookups of neighbouring texels.
    """

    width: int
    height: int
    face: np.ndarray
    bary: np.ndarray
    position: np.ndarray
    normal: np.ndarray
    tangent: np.ndarray
    bitangent: np.ndarray
    covered: np.ndarray
    fill_source: np.ndarray
    padding: int = 2
    faces_without_texels: np.ndarray = dataclasses.field(
        default_factory=lambda: np.zeros(0, dtype=np.int32))

    _ARRAYS = ("face", "bary", "position", "normal", "tangent", "bitangent", "covered", "fill_source",
               "faces_without_texels")

    @property
    def n_covered(self) -> int:
        """Number of covered texels (texels that hold model parameters)."""
        return int(np.count_nonzero(self.covered))

    @property
    def coverage(self) -> float:
        """Fraction of the atlas whose texel centres lie on the surface."""
        return self.n_covered / float(self.width * self.height)

    def fill_padding(self, values: np.ndarray) -> np.ndarray:
        """Copy each padding texel's value from its ``fill_source`` (covered texels unchanged).

        Args:
            values: (H*W, P) or (H, W, P) (or (H*W,) / (H, W)) per-texel values.

        Returns:
            A new array of the same shape; texels with ``fill_source == -1`` keep their values.
        """
        v = np.asarray(values)
        hw = self.width * self.height
        if v.shape[0] == hw:
            flat = v.reshape(hw, -1)
        elif v.shape[:2] == (self.height, self.width):
            flat = v.reshape(hw, -1)
        else:
            raise ValueError(f"values must be (H*W, P) or (H, W, P) with H, W = {self.height}, {self.width}; "
                             f"got {v.shape}")
        src = self.fill_source.reshape(-1)
        out = flat.copy()
        ok = src >= 0
        out[ok] = flat[src[ok]]
        return out.reshape(v.shape)

    def normal_preview(self) -> np.ndarray:
        """(H, W, 3) float32 image in [0, 1]: normals as colours ((n + 1) / 2), padding filled,
        black elsewhere (a chart preview)."""
        img = (self.normal + 1.0) * 0.5
        img = self.fill_padding(img)
        img[self.fill_source < 0] = 0.0
        return img.astype(np.float32)

    def save(self, path: str | os.PathLike) -> None:
        """Write the bake as a compressed ``.npz`` atomically."""
        write_npz_atomic(path, width=np.int64(self.width), height=np.int64(self.height), padding=np.int64(self.padding),
                         **{k: getattr(self, k) for k in self._ARRAYS})

    @classmethod
    def load(cls, path: str | os.PathLike) -> "TexelBake":
        """Read a bake written by :meth:`save`."""
        p = Path(path)
        if not p.is_file():
            raise InputError("texel bake not found", p, "run `texstream atlas` to make it")
        try:
            with np.load(p) as z:
                kw = {k: z[k] for k in cls._ARRAYS}
                bake = cls(width=int(z["width"]), height=int(z["height"]), padding=int(z["padding"]), **kw)
        except (OSError, KeyError, ValueError) as e:
            raise InputError(f"not a texel bake ({e})", p, "re-run `texstream atlas` to rebuild it") from None
        if bake.face.shape != (bake.height, bake.width):
            raise InputError(f"bake arrays have shape {bake.face.shape}, "
                             f"expected {(bake.height, bake.width)}", p, "re-run `texstream atlas` to rebuild it")
        return bake


def _texel_vertex_coords(mesh: SurfaceMesh, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-vertex continuous texel coordinates (centres at integers), float64."""
    uv = np.asarray(mesh.uvs, dtype=np.float64)
    return uv[:, 0] * width - 0.5, (1.0 - uv[:, 1]) * height - 0.5


def claim_texels(mesh: SurfaceMesh, width: int, height: int, device: str = "cpu",
                 claim_orphans: bool = True) -> np.ndarray:
    """(H, W) int32 owning face of every texel (-1 = uncovered); see the module doc for the rule."""
    _check_bake_input(mesh, width, height)
    tx, ty = _texel_vertex_coords(mesh, width, height)
    faces = np.ascontiguousarray(mesh.faces, dtype=np.int32)
    with wp.ScopedDevice(device):
        d_tx = wp.array(tx, dtype=wp.float64)
        d_ty = wp.array(ty, dtype=wp.float64)
        d_faces = wp.array(faces.reshape(-1), dtype=wp.int32)
        owner = wp.full(width * height, _NO_OWNER, dtype=wp.int32)
        wp.launch(_claim_texels, dim=mesh.n_faces, inputs=[d_tx, d_ty, d_faces, width, height, owner])
        face = owner.numpy()
    face[face == _NO_OWNER] = -1
    if claim_orphans:
        _claim_orphans(face, tx, ty, faces, width, height)
    return face.reshape(height, width)


# texel offsets from an orphan's nearest texel, nearest first (ties in a fixed order)
_ORPHAN_OFFSETS = tuple(sorted(((dx, dy) for dy in range(-2, 3) for dx in range(-2, 3)),
                               key=lambda o: (o[0] ** 2 + o[1] ** 2, o[1], o[0])))


def _claim_orphans(face: np.ndarray, tx: np.ndarray, ty: np.ndarray, faces: np.ndarray,
                   width: int, height: int) -> None:
    """Give faces that own no texel a texel near their UV centroid (in place, ``face`` is (H*W,)).

    Tries the nearest texel, then the others within 2 texels, nearest first. A free texel is taken; an owned one only if
    its owner keeps at least one texel after all take-overs of the round.
    """
    px, py = tx[faces], ty[faces]
    cx, cy = px.mean(1), py.mean(1)
    for dx, dy in _ORPHAN_OFFSETS:
        counts = np.bincount(face[face >= 0], minlength=len(faces))
        cand = np.flatnonzero(counts == 0)
        if cand.size == 0:
            return
        x = np.clip(np.floor(cx[cand] + 0.5).astype(np.int64) + dx, 0, width - 1)
        y = np.clip(np.floor(cy[cand] + 0.5).astype(np.int64) + dy, 0, height - 1)
        k = y * width + x
        k_u, first = np.unique(k, return_index=True)  # one orphan per texel (lowest id: cand is sorted)
        o = face[k_u]
        ok = o < 0
        owned = np.flatnonzero(~ok)
        lost = np.bincount(o[owned], minlength=len(faces))
        ok[owned] = counts[o[owned]] - lost[o[owned]] >= 1
        face[k_u[ok]] = cand[first[ok]]


def _check_bake_input(mesh: SurfaceMesh, width: int, height: int) -> None:
    if mesh.uvs is None:
        raise InputError("mesh has no texture coordinates", None,
                         "build an atlas first (texstream atlas, or geometry.atlas.build_atlas)")
    if width < 1 or height < 1:
        raise InputError(f"atlas size must be positive, got {width}x{height}", None, "pass a positive size")


def padding_sources(covered: np.ndarray, padding: int) -> np.ndarray:
    """(H, W) int32 fill source of each texel: own flat index when covered, else the source of a
    covered texel reached by growing the charts ``padding`` rings (4-neighbours before diagonals,
    so the choice is deterministic), else -1."""
    h, w = covered.shape
    src = np.where(covered, np.arange(h * w, dtype=np.int32).reshape(h, w), np.int32(-1))
    shifts = ((0, -1), (0, 1), (-1, 0), (1, 0), (-1, -1), (-1, 1), (1, -1), (1, 1))
    for _ in range(max(int(padding), 0)):
        new = src.copy()
        for dy, dx in shifts:
            nb = np.full_like(src, -1)
            # nb[y, x] = src[y + dy, x + dx] where that neighbour exists
            nb[max(-dy, 0):h - max(dy, 0), max(-dx, 0):w - max(dx, 0)] = \
                src[max(dy, 0):h - max(-dy, 0), max(dx, 0):w - max(-dx, 0)]
            take = (new < 0) & (nb >= 0)
            new[take] = nb[take]
        src = new
    return src


def bake_texels(mesh: SurfaceMesh, width: int, height: int, device: str = "cpu", padding: int = 2,
                claim_orphans: bool = True) -> TexelBake:
    """Bake the surface location space of a UV-mapped mesh into a ``width x height`` atlas.

    Args:
        mesh: triangle mesh with per-vertex ``uvs`` (v up); normals are taken from
            ``mesh.vertex_normals()`` (welded across seams through ``source_vertex``).
        width: atlas width in texels.
        height: atlas height in texels.
        device: Warp device ("cpu", "cuda:0", ...).
        padding: how many texels around the charts get a ``fill_source``.
        claim_orphans: give faces whose UV triangle contains no texel centre the free texel
            nearest their UV centroid (module doc).

    Returns:
        The :class:`TexelBake`.
    """
    face = claim_texels(mesh, width, height, device=device, claim_orphans=claim_orphans).reshape(-1)
    n_tex = width * height
    with wp.ScopedDevice(device):
        tx, ty = _texel_vertex_coords(mesh, width, height)
        d_tx = wp.array(tx, dtype=wp.float64)
        d_ty = wp.array(ty, dtype=wp.float64)
        d_faces = wp.array(np.ascontiguousarray(mesh.faces, dtype=np.int32).reshape(-1), dtype=wp.int32)
        owner = wp.array(face, dtype=wp.int32)
        points = wp.array(np.asarray(mesh.vertices, dtype=np.float32), dtype=wp.vec3)
        normals = wp.array(np.asarray(mesh.vertex_normals(), dtype=np.float32), dtype=wp.vec3)
        uvs = wp.array(np.asarray(mesh.uvs, dtype=np.float32), dtype=wp.vec2)
        outs = [wp.zeros(n_tex, dtype=wp.vec3) for _ in range(5)]
        wp.launch(_bake_frames, dim=n_tex,
                  inputs=[d_tx, d_ty, d_faces, points, normals, uvs, owner, width], outputs=outs)
        bary, position, normal, tangent, bitangent = (o.numpy().reshape(height, width, 3) for o in outs)
    face = face.reshape(height, width)
    covered = face >= 0
    owned = np.zeros(mesh.n_faces, dtype=bool)
    owned[face[covered]] = True
    return TexelBake(width=width, height=height, face=face, bary=bary, position=position, normal=normal,
                     tangent=tangent, bitangent=bitangent, covered=covered,
                     fill_source=padding_sources(covered, padding), padding=int(padding),
                     faces_without_texels=np.flatnonzero(~owned).astype(np.int32))
