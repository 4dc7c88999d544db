"""Where the cameras are, which way the surface faces them, and its topology: checks and fixes for SfM meshes.

- :func:`classify_capture`: a *scene* (the cameras stand inside the points' robust extent, or above
  the footprint of a flat point cloud: outdoor, room, aerial captures) or an *object* (the cameras
  on a ring or dome outside it: turntable captures). Screened Poisson closes every surface; for a
  scene that closed surface is a balloon around the cameras, so scene meshes are cropped to the
  points' robust bounding box (:func:`robust_box`) and trimmed to where points are
  (:func:`trim_far_from_points`).
- :func:`camera_facing`: rays from each camera through a grid of pixels (Warp ``mesh_query_ray``);
  a ray that first hits a face from behind sees its back. :func:`orient_to_cameras` flips every
  connected component that cameras see mostly from behind; :func:`check_facing` raises StageError
  when too many rays still hit back faces.
- :func:`cameras_enclosed`: which camera centres the surface encloses (generalised winding number
  above 1/2): an object mesh must enclose none.
- :func:`genus_by_component`: genus from the Euler characteristic of each connected component,
  with its boundary loops: ``genus = (2 - V + E - F - loops) / 2``.

numpy and warp at module level; scipy inside functions.
"""

from __future__ import annotations

import dataclasses
from typing import Sequence

import numpy as np
import warp as wp

from texstream.core.errors import StageError

from texstream.render.mesh import SurfaceMesh


def robust_box(points: np.ndarray, percentile: float = 2.0, margin: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """The box between the ``percentile`` and ``100 - percentile`` percentiles of the points on each axis,
    grown on every side by ``margin`` times its diagonal (outliers do not stretch it)."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    lo = np.percentile(p, percentile, axis=0)
    hi = np.percentile(p, 100.0 - percentile, axis=0)
    pad = margin * float(np.linalg.norm(hi - lo))
    return lo - pad, hi + pad


# cameras whose mean unit direction from the points' centre is at least this long stand on one side of them:
# an arc of 130 degrees at the points' height gives 0.8 (sin(x) / x at half the arc), a full ring about 0, a
# dome from 0 to 90 degrees of elevation 0.5, the synthetic facade's 70-degree street arc 0.95
ONE_SIDED = 0.8


@dataclasses.dataclass
class CaptureKind:
    """What :func:`classify_capture` decided, and from which numbers."""

    kind: str  # "scene" or "object"
    reason: str
    cameras_in_box: float  # fraction of cameras inside the points' robust box
    cameras_over_footprint: float  # fraction above the footprint of the two major axes (flat clouds)
    flatness: float  # smallest over middle principal extent of the points
    box_lo: list
    box_hi: list
    one_side: float = 0.0  # length of the mean unit direction from the points' centre to the cameras

    def to_json(self) -> dict:
        return dataclasses.asdict(self)


def classify_capture(points: np.ndarray, camera_centers: np.ndarray, percentile: float = 2.0,
                     margin: float = 0.05) -> CaptureKind:
    """Scene (cameras inside the points' extent) or object (cameras on a ring outside it).

    A capture is a scene when at least half the cameras stand inside the points' robust box
    (:func:`robust_box`), or when the points are flat (smallest principal extent under half the
    middle one: ground, facade) and at least half the cameras stand over their footprint (aerial
    captures above the box), or when every camera looks from one side (:data:`ONE_SIDED`: a facade from
    the street; closing the surface behind the points would only invent a back). Otherwise it is an object.
    """
    p = np.asarray(points, np.float64).reshape(-1, 3)
    c = np.asarray(camera_centers, np.float64).reshape(-1, 3)
    lo, hi = robust_box(p, percentile, margin)
    in_box = float(np.mean(np.all((c >= lo) & (c <= hi), axis=1))) if len(c) else 0.0
    core = p[np.all((p >= lo) & (p <= hi), axis=1)]
    if len(core) < 4:
        core = p
    mu = np.median(core, axis=0)
    _, _, vt = np.linalg.svd(core - mu, full_matrices=False)
    q = (core - mu) @ vt.T
    qlo = np.percentile(q, percentile, axis=0)
    qhi = np.percentile(q, 100.0 - percentile, axis=0)
    ext = np.maximum(qhi - qlo, 1e-12)
    flat = float(ext[2] / ext[1])
    qc = (c - mu) @ vt.T
    over = float(np.mean(np.all((qc[:, :2] >= qlo[:2]) & (qc[:, :2] <= qhi[:2]), axis=1))) if len(c) else 0.0
    n = len(c)
    # one-sidedness: the mean of the unit directions from the points' centre to the cameras (1: all cameras in
    # one direction; a full ring about 0, a ring 30 degrees up 0.5)
    toward = c - mu
    toward /= np.maximum(np.linalg.norm(toward, axis=1, keepdims=True), 1e-12)
    one_side = float(np.linalg.norm(toward.mean(axis=0))) if n else 0.0
    if in_box >= 0.5:
        kind = "scene"
        reason = (f"{round(in_box * n)} of {n} cameras stand inside the SfM points' robust bounding box "
                  f"(percentiles {percentile:g}-{100 - percentile:g} + {100 * margin:g}% margin): a scene around the "
                  "cameras; the Poisson surface is cropped to that box and trimmed to the points")
    elif flat < 0.5 and over >= 0.5:
        kind = "scene"
        reason = (f"the SfM points are flat (smallest principal extent {flat:.2f} of the middle one) and "
                  f"{round(over * n)} of {n} cameras stand over their footprint: a scene seen from above; the "
                  "Poisson surface is cropped to the points' robust box and trimmed to the points")
    elif one_side >= ONE_SIDED:
        kind = "scene"
        reason = (f"the {n} cameras all look from one side (mean direction from the points' centre to them "
                  f"{one_side:.2f} long, {ONE_SIDED:g} or more: a facade or a relief seen from the street, not an "
                  "object seen from round it); the Poisson surface is cropped to the points' robust box and trimmed "
                  "to the points rather than closed behind them")
    else:
        kind = "object"
        reason = (f"{n - round(in_box * n)} of {n} cameras stand outside the SfM points' robust bounding box "
                  f"(percentiles {percentile:g}-{100 - percentile:g} + {100 * margin:g}% margin): an object seen "
                  "from around it; its closed surface must not enclose any camera")
    return CaptureKind(kind, reason, in_box, over, flat, lo.tolist(), hi.tolist(), one_side)


def _compact(mesh: SurfaceMesh, keep_faces: np.ndarray) -> SurfaceMesh:
    f = mesh.faces[keep_faces]
    used = np.zeros(mesh.n_vertices, bool)
    used[f.reshape(-1)] = True
    remap = np.cumsum(used) - 1
    return SurfaceMesh(mesh.vertices[used], remap[f].astype(np.int32))


def crop_to_box(mesh: SurfaceMesh, lo: np.ndarray, hi: np.ndarray) -> SurfaceMesh:
    """The faces whose vertices all lie inside the box [lo, hi]."""
    inside = np.all((mesh.vertices >= np.asarray(lo)) & (mesh.vertices <= np.asarray(hi)), axis=1)
    return _compact(mesh, inside[mesh.faces].all(axis=1))


def point_spacing(points: np.ndarray, k: int = 8) -> float:
    """The points' typical spacing: the median distance to the k-th nearest neighbour."""
    from scipy.spatial import cKDTree

    p = np.asarray(points, np.float64).reshape(-1, 3)
    k = int(min(k, len(p) - 1))
    if k < 1:
        return 0.0
    d, _ = cKDTree(p).query(p, k=k + 1, workers=-1)  # every core: the same distances
    return float(np.median(d[:, k]))


def trim_far_from_points(mesh: SurfaceMesh, points: np.ndarray, max_distance: float) -> SurfaceMesh:
    """The faces whose vertices all lie within ``max_distance`` of some point (Poisson invents surface
    where there are none: over the sky, across the gaps between objects, around the cameras)."""
    from scipy.spatial import cKDTree

    d, _ = cKDTree(np.asarray(points, np.float64).reshape(-1, 3)).query(mesh.vertices, workers=-1)
    near = d <= max_distance
    return _compact(mesh, near[mesh.faces].all(axis=1))


@wp.func
def _first_hit(mesh: wp.uint64, rot: wp.mat33, center: wp.vec3, k: wp.vec4, x: float, y: float, max_t: float):
    d = wp.transpose(rot) * wp.normalize(wp.vec3((x - k[2]) / k[0], (y - k[3]) / k[1], 1.0))
    q = wp.mesh_query_ray(mesh, center, d, max_t)
    face = int(-1)
    t = max_t
    side = int(0)
    if q.result:
        face = q.face
        t = q.t
        side = 1
        if wp.dot(wp.mesh_eval_face_normal(mesh, q.face), d) >= 0.0:
            side = -1
    return face, t, side


@wp.kernel(enable_backward=False)
def _facing_kernel(mesh: wp.uint64, rot: wp.mat33, center: wp.vec3, k: wp.vec4, nu: int, nv: int, w: float,
                   h: float, max_t: float, face: wp.array(dtype=wp.int32), side: wp.array(dtype=wp.int32)):
    tid = wp.tid()
    j = tid / nu
    i = tid - j * nu
    x = (float(i) + 0.5) * w / float(nu)
    y = (float(j) + 0.5) * h / float(nv)
    f0, t0, s0 = _first_hit(mesh, rot, center, k, x, y, max_t)
    face[tid] = f0
    side[tid] = s0


@dataclasses.dataclass
class Facing:
    """Camera rays against a mesh: per face, how many rays hit its front and its back."""

    front: np.ndarray  # (F,) int
    back: np.ndarray  # (F,) int
    rays: int

    @property
    def hits(self) -> int:
        return int(self.front.sum() + self.back.sum())

    @property
    def back_fraction(self) -> float:
        """Fraction of the rays that hit the mesh whose first hit is a back face (0 when none hit)."""
        return float(self.back.sum()) / self.hits if self.hits else 0.0

    def to_json(self) -> dict:
        return {"rays": self.rays, "hits": self.hits, "back_hits": int(self.back.sum()),
                "back_fraction": round(self.back_fraction, 6),
                "faces_seen": int(np.count_nonzero(self.front + self.back)),
                "faces_seen_from_behind_mostly": int(np.count_nonzero(self.back > self.front))}


def camera_facing(mesh: SurfaceMesh, frames: Sequence, device: str = "cpu", rays: int = 48) -> Facing:
    """Cast ``rays`` rays along the longer image side (a regular grid of pixel centres) from every camera.

    Args:
        mesh: the surface (faces counter-clockwise seen from their front).
        frames: frames with R, t, intrinsics (world-to-camera, OpenCV axes).
        device: Warp device.
        rays: grid size along the longer image side.

    Returns:
        :class:`Facing` with per-face front and back hit counts.
    """
    nf = mesh.n_faces
    front = np.zeros(nf, np.int64)
    back = np.zeros(nf, np.int64)
    if nf == 0 or not len(frames):
        return Facing(front, back, 0)
    wm = wp.Mesh(points=wp.array(np.asarray(mesh.vertices, np.float32), dtype=wp.vec3, device=device),
                 indices=wp.array(np.asarray(mesh.faces, np.int32).reshape(-1), dtype=wp.int32, device=device))
    lo, hi = mesh.bbox()
    total = 0
    for fr in frames:
        intr = fr.intrinsics
        s = rays / max(intr.width, intr.height)
        nu, nv = max(1, round(intr.width * s)), max(1, round(intr.height * s))
        r = np.asarray(fr.R, np.float64)
        c = -r.T @ np.asarray(fr.t, np.float64).reshape(3)
        max_t = float(np.linalg.norm(c - 0.5 * (lo + hi)) + 2.0 * np.linalg.norm(hi - lo) + 1.0)
        face = wp.empty(nu * nv, dtype=wp.int32, device=device)
        side = wp.empty(nu * nv, dtype=wp.int32, device=device)
        wp.launch(_facing_kernel, dim=nu * nv,
                  inputs=[wm.id, wp.mat33(r.astype(np.float32)), wp.vec3(*c.astype(np.float32)),
                          wp.vec4(intr.fx, intr.fy, intr.cx, intr.cy), nu, nv, float(intr.width),
                          float(intr.height), max_t], outputs=[face, side], device=device)
        f, sd = face.numpy(), side.numpy()
        hit = f >= 0
        np.add.at(front, f[hit & (sd > 0)], 1)
        np.add.at(back, f[hit & (sd < 0)], 1)
        total += nu * nv
    return Facing(front, back, total)


def face_components(mesh: SurfaceMesh) -> np.ndarray:
    """(F,) connected-component label of each face (faces sharing a vertex are connected)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    nf = mesh.n_faces
    if nf == 0:
        return np.zeros(0, np.int64)
    g = coo_matrix((np.ones(3 * nf), (np.repeat(np.arange(nf), 3), mesh.faces.reshape(-1))),
                   shape=(nf, mesh.n_vertices)).tocsr()
    _, labels = connected_components(g @ g.T, directed=False)
    return labels


def orient_to_cameras(mesh: SurfaceMesh, frames: Sequence, device: str = "cpu",
                      rays: int = 48) -> tuple[SurfaceMesh, dict]:
    """Flip every connected component whose faces the camera rays hit more often from behind.

    The components should be coherently oriented already (``clean_mesh`` re-orients them); this
    decides each one's side by what the cameras see rather than by its signed volume, which is
    meaningless for the open surfaces of a scene.

    Returns:
        The mesh (normals recomputed when any component flipped) and a report:
        ``{"before": Facing json, "after": ..., "components": C, "flipped_components": k}``.
    """
    before = camera_facing(mesh, frames, device, rays)
    labels = face_components(mesh)
    nc = int(labels.max()) + 1 if len(labels) else 0
    fr = np.bincount(labels, weights=before.front, minlength=nc)
    bk = np.bincount(labels, weights=before.back, minlength=nc)
    flip_comp = bk > fr
    rep = {"before": before.to_json(), "components": nc, "flipped_components": int(flip_comp.sum())}
    if not flip_comp.any():
        rep["after"] = rep["before"]
        return mesh, rep
    faces = mesh.faces.copy()
    sel = flip_comp[labels]
    faces[sel] = faces[sel][:, ::-1]
    out = SurfaceMesh(mesh.vertices, faces).with_normals()
    # the flipped faces swap their front and back counts: no second ray cast needed
    after = Facing(np.where(sel, before.back, before.front), np.where(sel, before.front, before.back), before.rays)
    rep["after"] = after.to_json()
    return out, rep


def check_facing(facing: Facing, max_back_fraction: float, path=None, what: str = "the mesh") -> None:
    """Raise StageError when more than ``max_back_fraction`` of the camera rays hit back faces, or none hit."""
    if facing.hits == 0:
        raise StageError(f"no camera ray hits {what} ({facing.rays} rays): it is not where the cameras look", path,
                         "check the capture's poses, or give --matrix for a scanned mesh")
    if facing.back_fraction > max_back_fraction:
        raise StageError(f"{100 * facing.back_fraction:.1f}% of the camera rays that hit {what} hit the back of a face "
                         f"(allowed {100 * max_back_fraction:g}%): the surface faces away from the cameras that see it "
                         "(a closed balloon around the cameras, or inconsistent orientation)", path,
                         "use --scene-kind scene for captures taken from inside the scene, or --from hull with masks")


def winding_numbers(mesh: SurfaceMesh, points: np.ndarray) -> np.ndarray:
    """Generalised winding number of the mesh at each point (1 inside a closed outward mesh, 0 outside;
    -1 inside an inward one), by summing signed solid angles (Van Oosterom and Strackee)."""
    q = np.asarray(points, np.float64).reshape(-1, 3)
    tri = mesh.vertices[mesh.faces]
    out = np.zeros(len(q))
    for i, p in enumerate(q):
        a, b, c = tri[:, 0] - p, tri[:, 1] - p, tri[:, 2] - p
        la, lb, lc = (np.linalg.norm(x, axis=1) for x in (a, b, c))
        num = np.einsum("ij,ij->i", a, np.cross(b, c))
        den = (la * lb * lc + np.einsum("ij,ij->i", a, b) * lc + np.einsum("ij,ij->i", b, c) * la
               + np.einsum("ij,ij->i", c, a) * lb)
        out[i] = np.arctan2(num, den).sum() / (2.0 * np.pi)
    return out


def cameras_enclosed(mesh: SurfaceMesh, camera_centers: np.ndarray) -> np.ndarray:
    """(C,) bool: camera centres inside the surface (|winding number| > 1/2, either orientation)."""
    if mesh.n_faces == 0 or not len(camera_centers):
        return np.zeros(len(camera_centers), bool)
    return np.abs(winding_numbers(mesh, camera_centers)) > 0.5


def genus_by_component(mesh: SurfaceMesh) -> dict:
    """Genus of each connected component from its Euler characteristic and boundary loops.

    ``genus = (2 - (V - E + F) - loops) / 2`` per component (exact for 2-manifolds; for others a
    number to compare, flagged by ``"two_manifold": False``).

    Returns:
        ``{"total": sum of genera, "max", "components", "per_component": [g, ...] (largest first,
        at most 20), "boundary_loops", "two_manifold"}``.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    f = np.asarray(mesh.faces, np.int64)
    if len(f) == 0:
        return {"total": 0, "max": 0, "components": 0, "per_component": [], "boundary_loops": 0, "two_manifold": True}
    labels = face_components(mesh)
    nc = int(labels.max()) + 1
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    e_lab = np.tile(labels, 3)
    key = e[:, 0] * mesh.n_vertices + e[:, 1]
    uk, first, count = np.unique(key, return_index=True, return_counts=True)
    manifold = bool(count.max() <= 2)
    n_e = np.bincount(e_lab[first], minlength=nc)
    used = np.unique(f.reshape(-1))
    v_lab = np.full(mesh.n_vertices, -1)
    v_lab[f.reshape(-1)] = np.repeat(labels, 3)
    n_v = np.bincount(v_lab[used], minlength=nc)
    n_f = np.bincount(labels, minlength=nc)
    # boundary loops: connected pieces of the graph of edges used by one face
    be = e[first[count == 1]]
    loops = np.zeros(nc, np.int64)
    if len(be):
        bv = np.unique(be.reshape(-1))
        idx = np.searchsorted(bv, be)
        g = coo_matrix((np.ones(len(be)), (idx[:, 0], idx[:, 1])), shape=(len(bv), len(bv)))
        nb, bl = connected_components(g, directed=False)
        loop_comp = np.zeros(nb, np.int64)
        loop_comp[bl] = v_lab[bv]
        loops = np.bincount(loop_comp, minlength=nc)
    chi = n_v - n_e + n_f
    genus = (2 - chi - loops) // 2
    order = np.argsort(-n_f)
    return {"total": int(genus.sum()), "max": int(genus.max()), "components": nc,
            "per_component": [int(genus[i]) for i in order[:20]], "boundary_loops": int(loops.sum()),
            "two_manifold": manifold}


def drop_enclosed_components(mesh: SurfaceMesh) -> tuple[SurfaceMesh, int]:
    """Remove connected components that lie inside another component (every vertex with |winding
    number| > 1/2 with respect to the rest of the surface): shells no camera can see, e.g. a pocket
    Poisson closes inside an object's body. Returns (the mesh, the number of components removed)."""
    labels = face_components(mesh)
    if len(labels) == 0 or labels.max() == 0:
        return mesh, 0
    faces = np.asarray(mesh.faces)
    drop = np.zeros(len(faces), bool)
    removed = 0
    for c in range(int(labels.max()) + 1):
        own = labels == c
        rest = SurfaceMesh(mesh.vertices, faces[~own & ~drop])
        verts = np.unique(faces[own])
        if rest.n_faces and np.all(np.abs(winding_numbers(rest, mesh.vertices[verts])) > 0.5):
            drop |= own
            removed += 1
    if not removed:
        return mesh, 0
    keep = faces[~drop]
    used, inverse = np.unique(keep, return_inverse=True)
    return dataclasses.replace(mesh, vertices=mesh.vertices[used], faces=inverse.reshape(-1, 3),
                               normals=None if mesh.normals is None else mesh.normals[used],
                               uvs=None if mesh.uvs is None else mesh.uvs[used]), removed
