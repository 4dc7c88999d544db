"""Light field mapping (LFM) fitted by image streaming (issue 18; Hillesland 2005 sec. 2.4, 5.3-5.6, ch. 7).

The model (Chen et al. 2002): the surface light field f(s, w) of an object under one fixed, unknown
lighting is the view-independent "diffuse" term d(s) plus, per vertex v of the mesh, a *vertex
light field* weighted by v's barycentric hat function and approximated by K terms of surface map
times view map:

    f(s, w) = d(s) + sum_{j = 0..2} sum_{k < K} g_k^{(t, v_j)}(s) h_k^{v_j}(w_{v_j})

for s on face t with vertices v_0..v_2. The surface maps are laid out in the atlas: every covered
texel holds, per vertex of its owner face (a *slot*) and per term, an RGB value. The view maps are
R x R per (vertex, term), over the hemisphere of the vertex's frame (the Nusselt "disk" mapping of
the dissertation or hemi-octahedral), looked up nearest or bilinear. Vertices are welded by
position (an atlas splits them at UV seams), so a view map covers its vertex's whole ring.

The fit (``fit_lfm``): d is the per-texel mean (least-squares constant, PCA-style) or minimum
(NMF-style) of the texel's samples, computed in one streaming pass; then one patch per (vertex,
channel) minimises its vertex light field's squared error over every photo (fit/kernels/lfm.py),
with the view maps' Laplacian on the masked disk stencil. Patches share no parameter, so each
takes its own step and accepts it on its own (Eq. 7.6). Conjugate gradient (Polak-Ribiere+) with
the Hessian step size -g.d / d^T H d is the default (the dissertation's best); L-BFGS per patch
(:class:`PatchLBFGS`), steepest descent and a backtracking step are there to compare. All state is batched on the device; the host waits for
the passes and reads one scalar every ``sync_every`` iterations.

This is an LFM-specific driver, not the per-texel ``fit/optim`` protocol: those optimizers own
(N, n_params) per-texel vectors, LFM's parameters live on slots and vertices with patch sums
through index tables. It reuses the distribution step (fit/kernels/stream.py ``observe``, light
free), the photo set (depth maps, masks) and the trace format of the per-texel fit.

Imports only numpy and warp.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import math
import time

import numpy as np
import warp as wp

from texstream.core.errors import ConfigError, InputError

from texstream.fit.kernels import lfm as LK
from texstream.fit.kernels import lfm_lbfgs as LB
from texstream.fit.kernels import stream
from texstream.fit.optim.lfm_config import LOOKUPS, OPTIMIZERS, VIEW_MAPS, LFMConfig  # noqa: F401  (re-exported)
from texstream.fit.stream.problem import exposure_mean_square


def vertex_frames(normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(tangent, bitangent) of each unit normal: the branchless orthonormal basis of Duff et al. 2017,
    continuous except across n_z = 0 and identical for identical normals."""
    n = np.asarray(normals, np.float64)
    sign = np.where(n[:, 2] >= 0, 1.0, -1.0)
    a = -1.0 / (sign + n[:, 2])
    b = n[:, 0] * n[:, 1] * a
    t = np.stack([1.0 + sign * n[:, 0] ** 2 * a, sign * b, -sign * n[:, 0]], 1)
    bt = np.stack([b, sign + n[:, 1] ** 2 * a, -n[:, 1]], 1)
    return t, bt


def view_mask(res: int, mapping: str) -> np.ndarray:
    """(R * R,) 1 for the view-map texels a lookup can read (the masked disk stencil: texel centres
    within two texel diagonals of the unit disk; every texel for the hemi-octahedral map)."""
    if mapping == "hemioct":
        return np.ones(res * res, np.int32)
    c = (np.arange(res) + 0.5) / res * 2.0 - 1.0
    r = np.hypot(c[None, :], c[:, None])
    return (r <= 1.0 + 2.0 * math.sqrt(2.0) / res).astype(np.int32).reshape(-1)


def view_directions(res: int, mapping: str) -> np.ndarray:
    """(R * R, 3) the local direction at each view-map texel centre (the discrete views of the
    PCA / NMF matrices); disk centres outside the unit disk are pulled onto its rim (horizon)."""
    c = (np.arange(res) + 0.5) / res * 2.0 - 1.0
    u, v = np.meshgrid(c, c)            # row = y (v), column = x (u)
    u, v = u.reshape(-1), v.reshape(-1)
    if mapping == "hemioct":
        px, py = (u + v) / 2.0, (u - v) / 2.0
        z = 1.0 - np.abs(px) - np.abs(py)
        d = np.stack([px, py, np.maximum(z, 0.0)], 1)
    else:
        r = np.hypot(u, v)
        s = np.where(r > 1.0, 1.0 / np.maximum(r, 1e-12), 1.0)
        x, y = u * s, v * s
        d = np.stack([x, y, np.sqrt(np.maximum(1.0 - x * x - y * y, 0.0))], 1)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


@dataclasses.dataclass
class LFMGeometry:
    """Slots, welded vertices, their frames and the ring index table (host arrays; see module doc).

    Attributes:
        slot_vertex: (3N,) welded vertex of each slot 3 s + j (vertex j of texel s's owner face).
        slot_hat: (3N,) the hat function L_j(s): texel s's barycentric j.
        ring_start, ring_slots: the index table: vertex v's ring slots are
            ``ring_slots[ring_start[v]:ring_start[v + 1]]``.
        vpos, vnrm, vtan, vbit: (V, 3) welded vertex positions and frames.
        weld: (n mesh vertices,) welded id of every mesh vertex.
        texel_pos: (N, 3) texel centres (for the renderer's view direction at a point).
    """

    slot_vertex: np.ndarray
    slot_hat: np.ndarray
    ring_start: np.ndarray
    ring_slots: np.ndarray
    vpos: np.ndarray
    vnrm: np.ndarray
    vtan: np.ndarray
    vbit: np.ndarray
    weld: np.ndarray
    texel_pos: np.ndarray

    @property
    def n_texels(self) -> int:
        return int(self.slot_vertex.size // 3)

    @property
    def n_vertices(self) -> int:
        return int(self.vpos.shape[0])

    @staticmethod
    def build(points: np.ndarray, faces: np.ndarray, normals: np.ndarray, texel_face: np.ndarray,
              texel_bary: np.ndarray, texel_pos: np.ndarray) -> "LFMGeometry":
        """From the mesh (points, faces, vertex normals) and each compact texel's owner face,
        barycentrics and position (a TexelBake's ``face``, ``bary``, ``position`` at the texels)."""
        pts = np.asarray(points, np.float64)
        faces = np.asarray(faces, np.int64)
        tf = np.asarray(texel_face, np.int64)
        if tf.size and (tf.min() < 0 or tf.max() >= faces.shape[0]):
            raise InputError("a fitted texel has no owner face", fix="rebuild the atlas bake (texstream atlas)")
        uniq, weld = np.unique(pts, axis=0, return_inverse=True)
        weld = weld.reshape(-1)
        nsum = np.zeros((uniq.shape[0], 3))
        np.add.at(nsum, weld, np.asarray(normals, np.float64))
        length = np.linalg.norm(nsum, axis=1, keepdims=True)
        vnrm = np.where(length > 1e-12, nsum / np.maximum(length, 1e-300), np.array([0.0, 0.0, 1.0]))
        vtan, vbit = vertex_frames(vnrm)
        slot_vertex = weld[faces[tf]].reshape(-1).astype(np.int32)
        hat = np.clip(np.asarray(texel_bary, np.float64).reshape(-1, 3), 0.0, 1.0)
        hat = hat / np.maximum(hat.sum(1, keepdims=True), 1e-300)
        order = np.argsort(slot_vertex, kind="stable").astype(np.int32)
        counts = np.bincount(slot_vertex, minlength=uniq.shape[0])
        start = np.concatenate([[0], np.cumsum(counts)]).astype(np.int32)
        return LFMGeometry(slot_vertex, hat.reshape(-1), start, order, uniq, vnrm, vtan, vbit, weld.astype(np.int32),
                           np.asarray(texel_pos, np.float64))


class TableSamples:
    """Samples given as tables (tests, and the resampled data of the baselines): (P, N, 3) photo
    values ``y`` and (P, N) exposures ``e`` (0 = unobserved), and (P, 3) camera centres."""

    def __init__(self, y: np.ndarray, e: np.ndarray, centers: np.ndarray, device: str):
        self.n_photos, self.n = int(e.shape[0]), int(e.shape[1])
        self.y = wp.array(np.ascontiguousarray(np.asarray(y, np.float64).reshape(-1, 3)), dtype=wp.vec3d, device=device)
        self.e = wp.array(np.ascontiguousarray(np.asarray(e, np.float64).reshape(-1)), dtype=wp.float64, device=device)
        self.centers = np.asarray(centers, np.float64).reshape(-1, 3)
        self.exposures = np.array([float(np.max(r)) if np.any(r > 0) else 1.0 for r in np.asarray(e)])

    def load(self, p: int, obs_y: wp.array, obs_e: wp.array) -> None:
        wp.copy(obs_y, self.y, 0, p * self.n, self.n)
        wp.copy(obs_e, self.e, 0, p * self.n, self.n)

    obs_types = (wp.vec3d, wp.float64)
    """types of the batched passes' observation scratch"""

    def resident(self):
        """(y, e) of every photo on the device, photo p at p * N: the tables themselves."""
        return self.y, self.e

    def cache_bytes(self) -> int:
        return 0

    def load_batch(self, p0: int, count: int, obs_y: wp.array, obs_e: wp.array) -> None:
        """Photos p0 .. p0 + count - 1 into flat (batch x N) scratch, photo b at b * N."""
        wp.copy(obs_y, self.y, 0, p0 * self.n, count * self.n)
        wp.copy(obs_e, self.e, 0, p0 * self.n, count * self.n)


class PhotoSamples:
    """The photos of a :class:`texstream.fit.stream.photo_set.PhotoSet` streamed through the distribution step
    (fit/kernels/stream.py ``observe``, light free, bilinear photo sampling at the texel centre)."""

    def __init__(self, problem, frames):
        """``problem``: a radiance :class:`texstream.fit.stream.problem.StreamProblem` over the texels and
        photos (it holds the texel frames and sample options the distribution step reads)."""
        photos = problem.photos
        if getattr(photos, "streamed", False):
            raise ConfigError(f"the LFM fit keeps every photo on the device, and these stream from "
                              f"{photos.residency} ({photos.residency_reason})",
                              fix="set stream.photo_residency to device and stream.photos_per_window to 0, "
                                  "or fit fewer or smaller photos")
        if problem.cfg.image_precision != "fp32":
            raise ConfigError("the LFM fit reads fp32 photos", fix="set stream.image_precision to fp32")
        self.problem = problem
        self.photos = photos
        self.n_photos = photos.n
        self.n = problem.n
        self.opt = problem.opt
        self.opt.sampling = int(stream.SAMPLING_BILINEAR)
        self.centers = np.array([-(np.asarray(f.R).T @ np.asarray(f.t)) for f in frames], np.float64)
        self.exposures = np.array(photos.exposures, np.float64)
        self.device = problem.device

    def load(self, p: int, obs_y: wp.array, obs_e: wp.array) -> None:
        ph = self.photos
        wp.launch(LK.observe_kernel, dim=self.n, device=self.device,
                  inputs=[self.problem.tex, ph.images, ph.depth, ph.shadow, ph.infos, int(p), self.opt],
                  outputs=[obs_y, obs_e])

    obs_types = (wp.vec3, wp.float32)
    """the distribution step's own precision (exact)"""

    def resident(self):
        """None: the samples are distributed from the photos (see ``LFMConfig.sample_cache``)."""
        return None

    def cache_bytes(self) -> int:
        """Device bytes of every sample in float32, against which ``sample_cache`` auto weighs the photos."""
        return int(self.n_photos) * int(self.n) * 16

    def photo_bytes(self) -> int:
        ph = self.photos
        return int(ph.images.capacity + ph.depth.capacity + ph.shadow.capacity)

    def load_batch(self, p0: int, count: int, obs_y: wp.array, obs_e: wp.array) -> None:
        """Photos p0 .. p0 + count - 1 into flat float32 (batch x N) scratch, photo b at b * N (one launch)."""
        ph = self.photos
        wp.launch(LK.observe_batch_kernel, dim=(count, self.n), device=self.device,
                  inputs=[self.problem.tex, ph.images, ph.depth, ph.shadow, ph.infos, int(p0), self.opt],
                  outputs=[obs_y, obs_e])


@dataclasses.dataclass
class LFMParams:
    """Fitted LFM parameters on the host: diffuse (N, 3), G (3N, K, 3) slots x terms x RGB,
    H (V, K, R * R, 3) view maps."""

    diffuse: np.ndarray
    G: np.ndarray
    H: np.ndarray


_INIT_MIX = np.array([[1.0, 0.7, 0.5, 0.3], [-0.6, 1.0, 0.4, -0.5], [0.3, -0.4, 1.0, 0.6], [0.5, 0.2, -0.3, 1.0]])


def initial_view_maps(n_vertices: int, terms: int, res: int, mapping: str, offset: float = 0.0) -> np.ndarray:
    """(V, K, M, 3) starting view maps: term k is a fixed mix (row k of ``_INIT_MIX``) of u, v,
    u^2 + v^2 - 1/2 and u v over the map (u, v the texel centre's coordinates in [-1, 1]), plus
    ``offset``; zero outside the mask. Not the constant: with the mean subtracted every vertex
    light field is orthogonal to a constant view map, a saddle of the objective (zero gradient).
    With the surface maps at 0 the first gradient moves only the surface maps, onto these."""
    c = (np.arange(res) + 0.5) / res * 2.0 - 1.0
    u, v = np.meshgrid(c, c)
    basis = np.stack([u, v, u * u + v * v - 0.5, u * v]).reshape(4, -1)
    m = view_mask(res, mapping).astype(np.float64)
    h = (_INIT_MIX[:terms] @ basis + offset) * m                               # (K, M)
    return np.broadcast_to(h[None, :, :, None], (n_vertices, terms, res * res, 3)).copy()


CPU_SAMPLE_CACHE_BYTES = 1 << 30
"""``sample_cache`` auto on the CPU: the samples are kept when they take at most this much memory, photos or not.
There the device's memory is the host's and distributing the photos again is most of a pass (projection, depth
test and bilinear taps of every texel in every photo, on one thread): the temple's 12 photos give 105 MB of
samples against 43 MB of photos, which the GPU's rule (no more than the photos) turned down"""


CPU_BATCH_BYTES = 512 << 20
"""the per-photo scratch (slot residuals, gathered view terms) a batch of photos may hold on the CPU, where
``photo_batch`` is 0: each pass then reads the surface maps once per batch, not once per photo. The temple's
LFM validation fit (545,635 texels, 39 MB a photo, 10 photos; 2-core CPU): 64 MiB gave batches of 1 photo,
a gradient pass 0.70 s of CPU time; 512 MiB one batch of 10, 0.51 s, the same sums to the bit (the fit 51 s
of CPU time against 38 s, the same scores)"""


def sample_cache_budget(photo_bytes: int, device: str) -> int:
    """The bytes of samples ``sample_cache`` auto keeps on ``device``: as many as the photos take (a GPU's memory
    is what holds both), at least :data:`CPU_SAMPLE_CACHE_BYTES` on the CPU."""
    return int(photo_bytes) if wp.get_device(device).is_cuda else max(int(photo_bytes), CPU_SAMPLE_CACHE_BYTES)


class LFMProblem:
    """Device buffers and streaming passes of an LFM fit (allocated once; see the module doc)."""

    def __init__(self, geom: LFMGeometry, samples, cfg: LFMConfig, device: str = "cpu", threads: int = 1):
        """``threads``: CPU threads the slot pass and the view-map gather split their texels and vertices over
        (the CPU only; the same values for any count)."""
        cfg.check()
        self.geom, self.samples, self.cfg, self.device = geom, samples, cfg, device
        self.threads = int(threads) if not wp.get_device(device).is_cuda else 1
        self._launched: set[str] = set()  # the passes launched once (see _on_threads)
        self.K, self.R = int(cfg.terms), int(cfg.view_res)
        self.M = self.R * self.R
        self.N, self.V = geom.n_texels, geom.n_vertices
        self.S = 3 * self.N
        self.mapping = 0 if cfg.view_map == "disk" else 1
        self.lookup = 0 if cfg.lookup == "nearest" else 1
        dev = device
        f64 = wp.float64
        self.slot_vertex = wp.array(geom.slot_vertex, dtype=wp.int32, device=dev)
        self.slot_hat = wp.array(geom.slot_hat, dtype=f64, device=dev)
        self.ring_start = wp.array(geom.ring_start, dtype=wp.int32, device=dev)
        self.ring_slots = wp.array(geom.ring_slots, dtype=wp.int32, device=dev)
        self.vpos = wp.array(geom.vpos, dtype=wp.vec3d, device=dev)
        self.vnrm = wp.array(geom.vnrm, dtype=wp.vec3d, device=dev)
        self.vtan = wp.array(geom.vtan, dtype=wp.vec3d, device=dev)
        self.vbit = wp.array(geom.vbit, dtype=wp.vec3d, device=dev)
        self.texel_pos = wp.array(geom.texel_pos, dtype=wp.vec3d, device=dev)
        self.mask_np = view_mask(self.R, cfg.view_map)
        self.mask = wp.array(self.mask_np, dtype=wp.int32, device=dev)
        self.lam = float(cfg.laplacian) * exposure_mean_square(samples)
        lo, hi = (0.0, 1e300) if cfg.bounds == "nonnegative" else (-1e300, 1e300)
        self.lower, self.upper = f64(lo), f64(hi)
        # per-photo scratch and per-slot accumulators
        self.obs_y = wp.zeros(self.N, dtype=wp.vec3d, device=dev)
        self.obs_e = wp.zeros(self.N, dtype=f64, device=dev)
        self.tap_idx = wp.zeros(self.V, dtype=wp.vec4i, device=dev)
        self.tap_w = wp.zeros(self.V, dtype=wp.vec4d, device=dev)
        self.slot_f = wp.zeros(self.S, dtype=wp.vec3d, device=dev)
        self.slot_dhd = wp.zeros(self.S, dtype=wp.vec3d, device=dev)
        self.slot_gn = wp.zeros(self.S, dtype=wp.vec3d, device=dev)
        self.no_G = wp.zeros((1, self.K), dtype=wp.vec3d, device=dev)
        self.no_H = wp.zeros((1, self.M), dtype=wp.vec3d, device=dev)
        self.no_v = wp.zeros(1, dtype=wp.vec3d, device=dev)
        self.diffuse = wp.zeros(self.N, dtype=wp.vec3d, device=dev)
        self.seen = np.zeros(self.N, bool)
        # batched passes: B photos per launch (see fit/kernels/lfm.py), the taps of every photo once;
        # the samples read from the device tables (TableSamples, or the cache), else distributed per batch
        P = int(samples.n_photos)
        cache = samples.cache_bytes() > 0 and (cfg.sample_cache == "on" or (
            cfg.sample_cache == "auto" and samples.cache_bytes() <= sample_cache_budget(samples.photo_bytes(), dev)))
        self.cache_filled = False
        ty, te = samples.obs_types
        obs_bytes = 0 if (cache or samples.resident() is not None) else self.N * (wp.types.type_size_in_bytes(ty)
                                                                                  + wp.types.type_size_in_bytes(te))
        per_photo = obs_bytes + self.S * 24 + self.V * self.K * 24
        budget = (1 << 30) if wp.get_device(dev).is_cuda else CPU_BATCH_BYTES
        auto = int(min(64, max(1, budget // max(per_photo, 1))))
        self.B = int(max(1, min(P, cfg.photo_batch or auto)))
        n_obs = P * self.N if cache else (self.B * self.N if obs_bytes else 1)
        self.batch_y = wp.zeros(n_obs, dtype=ty, device=dev)
        self.batch_e = wp.zeros(n_obs, dtype=te, device=dev)
        self.cache = cache
        self.batch_res = wp.zeros(self.S * self.B, dtype=wp.vec3d, device=dev)
        self.batch_gathered = wp.zeros(self.V * self.K * self.B, dtype=wp.vec3d, device=dev)
        jacobi = cfg.precondition == "jacobi"
        self.batch_gathered_diag = wp.zeros(self.V * self.K * self.B if jacobi else 1, dtype=wp.vec3d, device=dev)
        m = self.mask_np.reshape(self.R, self.R)
        neighbours = np.zeros((self.R, self.R))
        neighbours[:, :-1] += m[:, 1:]
        neighbours[:, 1:] += m[:, :-1]
        neighbours[:-1, :] += m[1:, :]
        neighbours[1:, :] += m[:-1, :]
        # the Laplacian's exact diagonal: lam per masked stencil neighbour of a masked texel
        self.lap_diag = wp.array((self.lam * neighbours * m).reshape(-1), dtype=f64, device=dev)
        self.all_tap_idx = wp.zeros(max(P, 1) * self.V, dtype=wp.vec4i, device=dev)
        self.all_tap_w = wp.zeros(max(P, 1) * self.V, dtype=wp.vec4d, device=dev)
        if P:
            cams = wp.array(np.ascontiguousarray(np.asarray(samples.centers, np.float64).reshape(-1, 3)[:P]),
                            dtype=wp.vec3d, device=dev)
            wp.launch(LK.vertex_taps_all_kernel, dim=(P, self.V), device=dev,
                      inputs=[self.vpos, self.vtan, self.vbit, self.vnrm, cams, self.mapping, self.R, self.lookup],
                      outputs=[self.all_tap_idx, self.all_tap_w])
        self.passes = 0

    # ---- arrays
    def new_G(self, values: np.ndarray | None = None) -> wp.array:
        if values is None:
            return wp.zeros((self.S, self.K), dtype=wp.vec3d, device=self.device)
        return wp.array(np.ascontiguousarray(np.asarray(values, np.float64).reshape(self.S, self.K, 3)),
                        dtype=wp.vec3d, device=self.device)

    def new_H(self, values: np.ndarray | None = None) -> wp.array:
        if values is None:
            return wp.zeros((self.V * self.K, self.M), dtype=wp.vec3d, device=self.device)
        return wp.array(np.ascontiguousarray(np.asarray(values, np.float64).reshape(self.V * self.K, self.M, 3)),
                        dtype=wp.vec3d, device=self.device)

    def new_patch(self, fill: float = 0.0) -> wp.array:
        a = wp.zeros(self.V, dtype=wp.vec3d, device=self.device)
        if fill:
            a.fill_(wp.vec3d(fill, fill, fill))
        return a

    def params(self, G: wp.array, H: wp.array) -> LFMParams:
        return LFMParams(self.diffuse.numpy().copy(), G.numpy().reshape(self.S, self.K, 3).copy(),
                         H.numpy().reshape(self.V, self.K, self.M, 3).copy())

    def _taps(self, p: int) -> None:
        c = self.samples.centers[p]
        wp.launch(LK.vertex_taps_kernel, dim=self.V, device=self.device,
                  inputs=[self.vpos, self.vtan, self.vbit, self.vnrm, wp.vec3d(*c), self.mapping, self.R, self.lookup],
                  outputs=[self.tap_idx, self.tap_w])

    def _resident(self):
        """(y, e) of every photo on the device (photo p at p * N), or None: distribute per batch. The
        sample cache is filled at its first use (a pass's worth of distribution, timed with the fit)."""
        if self.cache:
            if not self.cache_filled:
                self.samples.load_batch(0, self.samples.n_photos, self.batch_y, self.batch_e)
                self.cache_filled = True
            return self.batch_y, self.batch_e
        return self.samples.resident()

    # ---- passes
    def compute_diffuse(self, mode: str | None = None) -> None:
        """The view-independent term d (mean or minimum per texel, ``LFMConfig.diffuse``): one
        streaming pass; also records which texels some photo sees (``seen``)."""
        mode = self.cfg.diffuse if mode is None else mode
        code = 0 if mode == "mean" else 1
        num = wp.zeros(self.N, dtype=wp.vec3d, device=self.device)
        den = wp.zeros(self.N, dtype=wp.float64, device=self.device)
        for p in range(self.samples.n_photos):
            self.samples.load(p, self.obs_y, self.obs_e)
            wp.launch(LK.diffuse_accumulate_kernel, dim=self.N, device=self.device,
                      inputs=[self.obs_y, self.obs_e, code], outputs=[num, den])
        wp.launch(LK.diffuse_finish_kernel, dim=self.N, device=self.device, inputs=[num, den, code],
                  outputs=[self.diffuse])
        self.seen = den.numpy() > 0
        self.passes += 1

    def evaluate(self, G: wp.array, H: wp.array, f: wp.array, grad_G: wp.array | None = None,
                 grad_H: wp.array | None = None, DG: wp.array | None = None, DH: wp.array | None = None,
                 dhd: wp.array | None = None, gn: wp.array | None = None, diag_G: wp.array | None = None,
                 diag_H: wp.array | None = None) -> None:
        """One streaming pass at (G, H): per patch objective ``f`` (V,), with ``grad_G``/``grad_H``
        the gradient, with a direction (DG, DH) the exact d^T H d (``dhd``) and its Gauss-Newton
        part (``gn``) along it, with ``diag_G``/``diag_H`` (and the gradient) the Gauss-Newton
        diagonal of the data term."""
        dev = self.device
        want_grad = grad_G is not None
        want_dhd = DG is not None
        want_diag = diag_G is not None
        if want_diag:
            diag_G.zero_()
            diag_H.zero_()
        xG = diag_G if want_diag else self.no_G
        xH = diag_H if want_diag else self.no_H
        self.slot_f.zero_()
        if want_grad:
            grad_G.zero_()
            grad_H.zero_()
        if want_dhd:
            self.slot_dhd.zero_()
            self.slot_gn.zero_()
        gG = grad_G if want_grad else self.no_G
        gH = grad_H if want_grad else self.no_H
        dG = DG if want_dhd else self.no_G
        dH = DH if want_dhd else self.no_H
        B = self.B
        resident = self._resident()
        for p0 in range(0, self.samples.n_photos, B):
            nb = min(B, self.samples.n_photos - p0)
            if resident is None:
                self.samples.load_batch(p0, nb, self.batch_y, self.batch_e)
                obs_y, obs_e, base = self.batch_y, self.batch_e, 0
            else:
                (obs_y, obs_e), base = resident, p0
            self._on_threads("slot pass", self.N, lambda first, count: wp.launch(
                LK.slot_pass_batch_kernel, dim=count, device=dev,
                inputs=[obs_y, obs_e, base, nb, B, p0, self.diffuse, self.slot_vertex, self.slot_hat, G, H, dG, dH,
                        self.all_tap_idx, self.all_tap_w, self.V, self.K, int(want_grad), int(want_dhd),
                        int(want_diag), first],
                outputs=[self.slot_f, gG, self.slot_dhd, self.slot_gn, self.batch_res, xG]))
            if want_grad:
                self._on_threads("gather", self.V, lambda first, count: wp.launch(
                    LK.view_gather_batch_kernel, dim=(count, nb), device=dev,
                    inputs=[self.ring_start, self.ring_slots, self.batch_res, B, G, self.K, int(want_diag), obs_e,
                            base, self.N, first],
                    outputs=[self.batch_gathered, self.batch_gathered_diag]))
                wp.launch(LK.view_scatter_batch_kernel, dim=self.V * self.K, device=dev,
                          inputs=[self.batch_gathered, nb, B, p0, self.all_tap_idx, self.all_tap_w, self.K, self.V,
                                  int(want_diag), self.batch_gathered_diag],
                          outputs=[grad_H, xH])
        # without a direction the reduction's d^T H d outputs are scratch, allocated once (not per pass)
        if not hasattr(self, "_scratch_dhd"):
            self._scratch_dhd, self._scratch_gn = self.new_patch(), self.new_patch()
        h_out = dhd if want_dhd else self._scratch_dhd
        g_out = gn if want_dhd else self._scratch_gn
        wp.launch(LK.patch_reduce_kernel, dim=self.V, device=dev,
                  inputs=[self.ring_start, self.ring_slots, self.slot_f, self.slot_dhd, self.slot_gn],
                  outputs=[f, h_out, g_out])
        if self.lam > 0:
            wp.launch(LK.laplacian_kernel, dim=self.V, device=dev,
                      inputs=[H, dH, self.mask, self.R, self.K, wp.float64(self.lam), int(want_grad), int(want_dhd)],
                      outputs=[f, gH, h_out, g_out])
        self.passes += 1

    def _on_threads(self, key: str, count: int, launch) -> None:
        """``launch(first, size)`` over ``count`` items, one contiguous range per CPU thread (``threads``): Warp
        runs a CPU kernel on the launching thread and releases the GIL, and each texel (vertex) of the slot pass
        (gather) writes only its own slots (rows), so the ranges give the one launch's values to the last bit.
        The first launch of each ``key`` runs its ranges one after the other: it builds the generic kernel's
        overload for these sample types, which Warp does not do safely from two threads at once (the dino's
        run failed in its launch checks)."""
        edges = np.linspace(0, count, max(1, min(self.threads, count)) + 1).astype(int)
        ranges = [(int(a), int(b - a)) for a, b in zip(edges[:-1], edges[1:]) if b > a]
        if len(ranges) == 1 or key not in self._launched:
            self._launched.add(key)
            for r in ranges:
                launch(*r)
            return
        with concurrent.futures.ThreadPoolExecutor(len(ranges)) as pool:
            list(pool.map(lambda r: launch(*r), ranges))

    def patch_dot(self, aG, bG, aH, bH, out: wp.array) -> None:
        wp.launch(LK.patch_dot_kernel, dim=self.V, device=self.device,
                  inputs=[self.ring_start, self.ring_slots, aG, bG, aH, bH, self.K, self.M], outputs=[out])

    def state_bytes(self) -> int:
        """Device bytes of the problem's own buffers (index tables, frames, d and the per-photo and
        per-slot scratch; not the photos): O(model), independent of the photo count."""
        return sum(int(a.capacity) for a in vars(self).values() if isinstance(a, wp.array))

    def total(self, f: wp.array) -> float:
        """Sum of a per-patch vec3 array (one host read)."""
        if not hasattr(self, "_total"):
            self._total = wp.zeros(1, dtype=wp.float64, device=self.device)
        out = self._total
        wp.launch(LK.sum_vec3_kernel, dim=1, device=self.device, inputs=[f, f.shape[0]], outputs=[out])
        return float(out.numpy()[0])

    def model_error(self, G: wp.array, H: wp.array, view_interp: int = 0) -> dict:
        """Error of the full model (sum of the vertex light fields plus d) on every sample: squared
        error, squared data and sample count summed over photos, texels and channels; the relative
        RMS error, RMS error and sample PSNR (peak 1)."""
        sse = wp.zeros(self.N, dtype=wp.vec3d, device=self.device)
        cnt = wp.zeros(self.N, dtype=wp.float64, device=self.device)
        y2 = 0.0
        for p in range(self.samples.n_photos):
            self.samples.load(p, self.obs_y, self.obs_e)
            wp.launch(LK.sample_kernel, dim=self.N, device=self.device,
                      inputs=[self.obs_y, self.obs_e, self.diffuse, self.slot_vertex, G, H, self.vpos, self.vtan,
                              self.vbit, self.vnrm, self.texel_pos, wp.vec3d(*self.samples.centers[p]), int(view_interp),
                              self.K, self.mapping, self.R, self.lookup], outputs=[sse, cnt])
            y = self.obs_y.numpy()
            y2 += float((y * y).sum())
        s = float(sse.numpy().sum())
        n = float(cnt.numpy().sum()) * 3
        mse = s / max(n, 1.0)
        return {"sse": s, "y2": y2, "samples": n, "relative_rms": math.sqrt(s / max(y2, 1e-300)),
                "rms": math.sqrt(mse), "psnr_db": 10 * math.log10(1.0 / mse) if mse > 0 else float("inf")}


@dataclasses.dataclass
class LFMResult:
    """A fitted LFM model: parameters, per-iteration trace and counts."""

    params: LFMParams
    trace: list
    iterations: int
    passes: int
    fit_s: float
    method: str
    state_bytes: int = 0
    """device bytes of the fit's state: the problem's buffers and the optimizer's model-sized vectors"""


class PatchLBFGS:
    """L-BFGS state of every (vertex, channel) patch on the device (fit/kernels/lfm_lbfgs.py): ring buffers
    of the last ``memory`` (s, y) pairs over the whole parameter vector, with per patch and channel
    the pair count, 1 / s.y per pair and the initial scaling gamma. The two-loop recursion runs as
    2 x memory gathers over the patches (a Python loop over the history's ages, never over patches)."""

    def __init__(self, pr: "LFMProblem", memory: int):
        self.pr, self.m = pr, int(memory)
        dev = pr.device
        self.s_G = wp.zeros((self.m, pr.S, pr.K), dtype=wp.vec3d, device=dev)
        self.y_G = wp.zeros((self.m, pr.S, pr.K), dtype=wp.vec3d, device=dev)
        self.s_H = wp.zeros((self.m, pr.V * pr.K, pr.M), dtype=wp.vec3d, device=dev)
        self.y_H = wp.zeros((self.m, pr.V * pr.K, pr.M), dtype=wp.vec3d, device=dev)
        self.rho = wp.zeros((self.m, pr.V), dtype=wp.vec3d, device=dev)
        self.alpha = wp.zeros((self.m, pr.V), dtype=wp.vec3d, device=dev)
        self.count = wp.zeros(pr.V, dtype=wp.vec3i, device=dev)
        self.gamma = pr.new_patch()
        self.coef = pr.new_patch()
        self.gg = pr.new_patch()

    def reset(self, gG: wp.array, gH: wp.array) -> None:
        """Forget every pair (start, and after the gauge balancing rescaled the parameters); the first
        direction is -g / |g| per patch."""
        pr = self.pr
        self.count.zero_()
        pr.patch_dot(gG, gG, gH, gH, self.gg)
        wp.launch(LB.lbfgs_gamma_start_kernel, dim=pr.V, device=pr.device, inputs=[self.gg], outputs=[self.gamma])

    def push(self, G, TG, gG, tgG, H, TH, gH, tgH, accepted, alpha) -> None:
        """Record the pair of this iteration's accepted trials (before they are adopted)."""
        pr, dev = self.pr, self.pr.device
        wp.launch(LB.lbfgs_push_G_kernel, dim=(pr.S, pr.K), device=dev,
                  inputs=[G, TG, gG, tgG, accepted, self.count, pr.slot_vertex, self.m], outputs=[self.s_G, self.y_G])
        wp.launch(LB.lbfgs_push_H_kernel, dim=(pr.V * pr.K, pr.M), device=dev,
                  inputs=[H, TH, gH, tgH, accepted, self.count, pr.K, self.m], outputs=[self.s_H, self.y_H])
        wp.launch(LB.lbfgs_finish_push_kernel, dim=pr.V, device=dev,
                  inputs=[pr.ring_start, pr.ring_slots, self.s_G, self.s_H, self.y_G, self.y_H, accepted, alpha, pr.K,
                          pr.M, self.m], outputs=[self.count, self.rho, self.gamma])

    def direction(self, gG, gH, DG, DH) -> None:
        """(DG, DH) = -(the L-BFGS inverse Hessian) g per patch: the two-loop recursion."""
        pr, dev, m = self.pr, self.pr.device, self.m
        wp.copy(DG, gG)
        wp.copy(DH, gH)
        for first, ages in ((1, range(m)), (0, range(m - 1, -1, -1))):
            if not first:
                wp.launch(LB.lbfgs_scale_G_kernel, dim=(pr.S, pr.K), device=dev,
                          inputs=[self.gamma, pr.slot_vertex], outputs=[DG])
                wp.launch(LB.lbfgs_scale_H_kernel, dim=(pr.V * pr.K, pr.M), device=dev,
                          inputs=[self.gamma, pr.K, pr.mask], outputs=[DH])
            dot_G, dot_H = (self.s_G, self.s_H) if first else (self.y_G, self.y_H)
            add_G, add_H = (self.y_G, self.y_H) if first else (self.s_G, self.s_H)
            for age in ages:
                wp.launch(LB.lbfgs_coef_kernel, dim=pr.V, device=dev,
                          inputs=[pr.ring_start, pr.ring_slots, dot_G, dot_H, DG, DH, self.count, self.rho, age, m,
                                  pr.K, pr.M, int(not first)], outputs=[self.alpha, self.coef])
                wp.launch(LB.lbfgs_axpy_G_kernel, dim=(pr.S, pr.K), device=dev,
                          inputs=[add_G, self.count, self.coef, age, m, pr.slot_vertex], outputs=[DG])
                wp.launch(LB.lbfgs_axpy_H_kernel, dim=(pr.V * pr.K, pr.M), device=dev,
                          inputs=[add_H, self.count, self.coef, age, m, pr.K], outputs=[DH])
        wp.launch(LB.negate_kernel, dim=(pr.S, pr.K), device=dev, inputs=[DG])
        wp.launch(LB.negate_kernel, dim=(pr.V * pr.K, pr.M), device=dev, inputs=[DH])


def fit_lfm(problem: LFMProblem, max_iterations: int | None = None, time_budget_s: float = 0.0,
            G0: np.ndarray | None = None, H0: np.ndarray | None = None, callback=None,
            snapshot=None, stop=None) -> LFMResult:
    """The streaming fit (CG, SD or L-BFGS, Hessian or backtracking step, per-patch acceptance); computes d
    first when it was not (``problem.compute_diffuse``). ``callback(iteration, objective)`` is
    called at every objective read, then ``snapshot(iteration, G, H)`` with the current device
    parameters (benchmarks score the model there; keep it out of the timing yourself); the fit ends at a read
    where ``stop(iteration, G, H)`` is true (the model choice's candidate that cannot win, fit/models/lfm/fit.py)."""
    pr, cfg, dev = problem, problem.cfg, problem.device
    if not pr.seen.any():
        pr.compute_diffuse()
    t0 = time.perf_counter()
    iters = int(cfg.iterations if max_iterations is None else max_iterations)
    K = pr.K
    G = pr.new_G(G0)
    offset = 2.0 if cfg.bounds == "nonnegative" else 0.0   # keeps the start inside the bounds
    H = pr.new_H(initial_view_maps(pr.V, K, pr.R, cfg.view_map, offset) if H0 is None else H0)
    TG, TH = pr.new_G(), pr.new_H()
    gG, gH, tgG, tgH = pr.new_G(), pr.new_H(), pr.new_G(), pr.new_H()
    # gradient before the step (Polak-Ribiere; L-BFGS keeps its own history)
    oG, oH = (pr.new_G(), pr.new_H()) if cfg.optimizer != "lbfgs" else (None, None)
    DG, DH = pr.new_G(), pr.new_H()
    f, f_trial, dhd, gn = pr.new_patch(), pr.new_patch(), pr.new_patch(), pr.new_patch()
    f_dummy = pr.new_patch()
    slope, alpha, accepted = pr.new_patch(), pr.new_patch(), pr.new_patch()
    scale = pr.new_patch(1.0)
    gg_new, gg_mixed, gg_old, beta = pr.new_patch(), pr.new_patch(), pr.new_patch(), pr.new_patch()
    hessian = int(cfg.step == "hessian")
    lbfgs = PatchLBFGS(pr, cfg.lbfgs_memory) if cfg.optimizer == "lbfgs" else None
    # the backtracking scale grows back to at most 1: the Hessian step, or L-BFGS's quasi-Newton step
    unit_cap = int(hessian or lbfgs is not None)
    variant = -1 if cfg.optimizer == "sd" else (0 if cfg.cg_variant == "pr" else 1)
    shape_G, shape_H = (pr.S, K), (pr.V * K, pr.M)
    # Jacobi: z = P g with P the inverse Gauss-Newton diagonal (fixed between gauge balancings); else z = g
    jacobi = cfg.precondition == "jacobi"
    PG, PH = (pr.new_G(), pr.new_H()) if jacobi else (None, None)
    zG, zH = (pr.new_G(), pr.new_H()) if jacobi else (gG, gH)

    def full_evaluate():
        """Objective and gradient at (G, H); with Jacobi also the preconditioner there."""
        if not jacobi:
            pr.evaluate(G, H, f, gG, gH)
            return
        pr.evaluate(G, H, f, gG, gH, diag_G=PG, diag_H=PH)
        wp.launch(LK.jacobi_G_kernel, dim=shape_G, device=dev, inputs=[PG], outputs=[PG])
        wp.launch(LK.jacobi_H_kernel, dim=shape_H, device=dev, inputs=[PH, pr.lap_diag], outputs=[PH])

    def precondition():
        if jacobi:
            wp.launch(LK.cw_mul_kernel, dim=shape_G, device=dev, inputs=[PG, gG], outputs=[zG])
            wp.launch(LK.cw_mul_kernel, dim=shape_H, device=dev, inputs=[PH, gH], outputs=[zH])

    def first_direction():
        """Steepest descent (CG, SD) or L-BFGS with an empty history (-g / |g|)."""
        if lbfgs is not None:
            lbfgs.reset(gG, gH)
            lbfgs.direction(gG, gH, DG, DH)
            return
        beta.zero_()
        precondition()
        wp.launch(LK.direction_G_kernel, dim=shape_G, device=dev, inputs=[zG, beta, pr.slot_vertex], outputs=[DG])
        wp.launch(LK.direction_H_kernel, dim=shape_H, device=dev, inputs=[zH, beta, K, pr.mask], outputs=[DH])
        pr.patch_dot(gG, zG, gH, zH, gg_old)

    full_evaluate()
    first_direction()
    f0 = pr.total(f)
    trace = []
    _record(trace, 0, 0.0, f0, callback, snapshot, G, H)
    last = f0
    it = 0
    for it in range(1, iters + 1):
        if hessian:
            pr.evaluate(G, H, f_dummy, DG=DG, DH=DH, dhd=dhd, gn=gn)
        pr.patch_dot(gG, DG, gH, DH, slope)
        wp.launch(LK.step_kernel, dim=pr.V, device=dev, inputs=[f, slope, dhd, gn, scale, hessian], outputs=[alpha])
        _trial_point(pr, G, H, DG, DH, alpha, TG, TH)
        pr.evaluate(TG, TH, f_trial, tgG, tgH)
        wp.launch(LK.accept_kernel, dim=pr.V, device=dev, inputs=[f, f_trial, alpha, unit_cap],
                  outputs=[accepted, scale, f])
        if lbfgs is not None:
            lbfgs.push(G, TG, gG, tgG, H, TH, gH, tgH, accepted, alpha)
        else:
            wp.copy(oG, gG)
            wp.copy(oH, gH)
        _adopt_accepted(pr, accepted, (TG, G), (TH, H))  # the parameters, then their gradient
        _adopt_accepted(pr, accepted, (tgG, gG), (tgH, gH))
        if lbfgs is not None:
            lbfgs.direction(gG, gH, DG, DH)
        else:
            precondition()
            pr.patch_dot(gG, zG, gH, zH, gg_new)
            pr.patch_dot(zG, oG, zH, oH, gg_mixed)
            wp.launch(LK.beta_kernel, dim=pr.V, device=dev, inputs=[gg_new, gg_mixed, gg_old, accepted, variant],
                      outputs=[beta])
            wp.launch(LK.direction_G_kernel, dim=shape_G, device=dev, inputs=[zG, beta, pr.slot_vertex], outputs=[DG])
            wp.launch(LK.direction_H_kernel, dim=shape_H, device=dev, inputs=[zH, beta, K, pr.mask], outputs=[DH])
            wp.copy(gg_old, gg_new)
        if it % cfg.sync_every == 0 or it == iters:
            obj = pr.total(f)
            _record(trace, it, time.perf_counter() - t0, obj, callback, snapshot, G, H)
            if last - obj <= cfg.rel_tol * max(abs(last), 1e-300) or (stop is not None and stop(it, G, H)):
                break
            last = obj
            if time_budget_s > 0 and time.perf_counter() - t0 > time_budget_s:
                break
        if cfg.balance_every and it % cfg.balance_every == 0:
            wp.launch(LK.balance_kernel, dim=pr.V, device=dev,
                      inputs=[pr.ring_start, pr.ring_slots, K, pr.M, int(pr.lam > 0)], outputs=[G, H])
            full_evaluate()
            first_direction()
            # the Laplacian is not invariant under the gauge (h / c costs 1 / c^2 of it): E changes with
            # the rescaling, so the stopping test restarts from the balanced objective
            last = pr.total(f)
    if trace[-1]["iteration"] != it:
        trace.append({"iteration": it, "time_s": time.perf_counter() - t0, "objective": pr.total(f)})
    fit_s = time.perf_counter() - t0
    state = [G, H, TG, TH, gG, gH, tgG, tgH, oG, oH, DG, DH] + ([PG, PH, zG, zH] if jacobi else [])
    return LFMResult(pr.params(G, H), trace, it, pr.passes, fit_s, f"stream-{cfg.optimizer}-{cfg.step}",
                     _state_bytes(pr, state, lbfgs))


def _record(trace: list, iteration: int, time_s: float, objective: float, callback, snapshot, G, H) -> None:
    """An objective read: into the trace, to ``callback``, and the parameters to ``snapshot`` (see :func:`fit_lfm`)."""
    trace.append({"iteration": iteration, "time_s": time_s, "objective": objective})
    if callback:
        callback(iteration, objective)
    if snapshot:
        snapshot(iteration, G, H)


def _trial_point(pr: LFMProblem, G, H, DG, DH, alpha, TG, TH) -> None:
    """The trial parameters (TG, TH) = (G, H) + alpha D per patch, clamped to the bounds."""
    wp.launch(LK.trial_G_kernel, dim=(pr.S, pr.K), device=pr.device,
              inputs=[G, DG, alpha, pr.slot_vertex, pr.lower, pr.upper], outputs=[TG])
    wp.launch(LK.trial_H_kernel, dim=(pr.V * pr.K, pr.M), device=pr.device,
              inputs=[H, DH, alpha, pr.K, pr.mask, pr.lower, pr.upper], outputs=[TH])


def _adopt_accepted(pr: LFMProblem, accepted, surface: tuple, view: tuple) -> None:
    """Copy the trial surface maps (``surface`` = (trial, current)) and view maps (``view`` likewise) of the
    patches whose trial step was ``accepted`` into the current ones."""
    wp.launch(LK.adopt_G_kernel, dim=(pr.S, pr.K), device=pr.device, inputs=[surface[0], accepted, pr.slot_vertex],
              outputs=[surface[1]])
    wp.launch(LK.adopt_H_kernel, dim=(pr.V * pr.K, pr.M), device=pr.device, inputs=[view[0], accepted, pr.K],
              outputs=[view[1]])


def _state_bytes(pr: LFMProblem, state: list, lbfgs: PatchLBFGS | None) -> int:
    """Device bytes the fit held: the problem's, the fit's arrays ``state`` (None: not allocated) and the
    L-BFGS history."""
    if lbfgs is not None:
        state = state + [a for a in vars(lbfgs).values() if isinstance(a, wp.array)]
    return pr.state_bytes() + sum(int(a.capacity) for a in state if a is not None)
