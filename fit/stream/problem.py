"""Host side of the streaming fit: texels, photos on the device, and the evaluation passes.

A :class:`StreamProblem` owns every device buffer the passes need, allocated once. Each pass
(:meth:`StreamProblem.evaluate` or :meth:`StreamProblem.evaluate_lm`) streams all photos through
:mod:`texstream.fit.kernels.stream` and leaves per-texel objective, gradient and curvature on the
device. Imports only numpy and warp (plus numpy-only spine modules).
"""

from __future__ import annotations

import collections
import concurrent.futures
import contextlib
import dataclasses
import math
import sys
import threading
import time

import numpy as np
import warp as wp

from texstream.core.config import option
from texstream.core.errors import ConfigError, InputError
from texstream.core.progress import say

from texstream.fit.kernels import optim_kernels as K
from texstream.fit.kernels import stream
from texstream.fit.kernels.lafortune_grad import param_types
from texstream.render.shading import SHADOW_EPS_REL
from texstream.render.visibility import depth_maps_kernel, masked_depth_kernel, shadow_maps_kernel
from texstream.render.layout import ModelLayout
from texstream.fit.stream.photo_stream import (PhotoCache, PhotoFiles, PhotoLoader, WindowSlots, choose_residency,
                           crop_boxes, keep_maps_on_device, to_half_kernel, wait, window_size)
from texstream.render.camera import ImageInfo, PhotoFrame, crop_infos, image_infos, struct_array

PRECISIONS = {"fp16": wp.float16, "fp32": wp.float32, "fp64": wp.float64}
MAX_LAUNCH_THREADS = 1 << 30
"""threads per depth- or shadow-map launch: larger sets launch in chunks of photos (a launch's size must
stay within Warp's 32-bit bounds; 10,000 shadow maps of 512x512 are 2.6 G threads)"""
UPLOAD_CHUNK_BYTES = 64 << 20
"""photo bytes per pinned upload chunk at set-up, for photo files: large transfers (PCIe runs near its peak
from a few MiB), and enough photos in flight to keep the decoding workers busy"""
ARRAY_UPLOAD_CHUNK_BYTES = 16 << 20
"""the same for photos given as arrays (host copies, a dozen photos of 430x430 a chunk): pinned memory takes
time to allocate in proportion to its size (4 buffers of 16 MiB in 0.04 s, of 64 MiB in 0.15 s on the
two-H200 machine), and copy threads need few photos in flight"""
UPLOAD_SLOTS = 2
"""pinned host buffers the set-up's upload cycles through (:func:`_upload_in_chunks`): the chunks of all slots
but one are being cropped while the oldest is copied to its device (4 were no faster on a two-H200 host,
and each buffer costs ~7 ms to pin)"""
UPLOAD_SWITCH_INTERVAL_S = 1e-4
"""the interpreter's thread switch interval while the upload runs (sys.setswitchinterval; the default is 5 ms):
the thread issuing the copies takes the GIL back after every Warp call, between the crop threads' numpy
calls, and with the default it waited for it"""


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
    where, tri, e, inv, good_face = _face_pseudo_inverse(points, faces, face)
    nv = normals.astype(np.float64)[tri]                     # per face used
    dn = np.stack([nv[:, 1] - nv[:, 0], nv[:, 2] - nv[:, 0]], axis=2)
    jac_face = np.einsum("nkj,nji,nli->nkl", dn, inv, e)     # dn (3x2) @ inv (2x2) @ e^T (2x3)
    b = bary.reshape(-1, 3).astype(np.float64)
    interp = np.einsum("nj,njk->nk", b, nv[where])           # per texel
    length = np.linalg.norm(interp, axis=1)
    jac = jac_face[where] / np.maximum(length, 1e-12)[:, None, None]
    good = good_face[where] & (face.reshape(-1) >= 0)
    jac[~good] = 0.0
    fn_face = np.cross(e[:, :, 0], e[:, :, 1])
    fn_face /= np.maximum(np.linalg.norm(fn_face, axis=1, keepdims=True), 1e-300)
    fn = fn_face[where]
    fn[~good] = interp[~good] / np.maximum(length[~good], 1e-12)[:, None]
    return fn.reshape(*shape, 3).astype(np.float32), jac.reshape(*shape, 3, 3).astype(np.float32)


def _face_pseudo_inverse(points: np.ndarray, faces: np.ndarray, face: np.ndarray):
    """Per face that texels of ``face`` use (computed once a face, not once a texel): ``where`` (N,), each
    flattened texel's row in the per-face arrays (texels without a face, -1, point at face 0's and are masked
    by the callers); the faces' vertex ids (M, 3), edges E = [p1 - p0, p2 - p0] (M, 3, 2), (E^T E)^-1 (M, 2, 2;
    zero where degenerate) and that mask (M,), so that (E^T E)^-1 E^T dp is the barycentric change (b1, b2)
    of an in-plane offset dp."""
    used, where = np.unique(np.maximum(face.reshape(-1), 0), return_inverse=True)
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
    where, tri, e, inv, good_face = _face_pseudo_inverse(points, faces, face)
    t = np.asarray(uvs, np.float64)[tri] * np.array([width, -height], np.float64)   # (M, 3 vertices, 2)
    te = np.stack([t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]], axis=2)                   # (M, 2, 2)
    grad_face = np.einsum("nkj,nji,nli->nkl", te, inv, e)                           # T (2x2) inv (2x2) E^T (2x3)
    grad_face[~good_face] = 0.0
    grad = grad_face[where]
    grad[face.reshape(-1) < 0] = 0.0
    return grad.reshape(*shape, 2, 3).astype(np.float32)




def no_light_error(n_unlit: int, n_total: int, kind: str) -> InputError:
    """The error for a reflectance model fitted to photos without a known light."""
    return InputError(f"{n_unlit} of {n_total} photos have no light, and the {kind} model needs a known light "
                      "per photo (capture.json frames' 'light')",
                      fix="use --model radiance (view-independent radiance under the photos' fixed lighting), "
                          "or add a point or directional 'light' to every frame of capture.json")


FP32_SAFE_TOLERANCE = 5e-6
"""relative error of a texel's error sum E that the automatic choice allows a plain float32 accumulation: half
of issue 20's 1e-5, a margin for sign mixes and term orders the study did not try (the float32 error grows
about linearly with the photo count there, so this is also about a factor 2 in photos)"""
FP32_SAFE_PHOTOS = 1000
"""the largest photo count per texel (3 channel terms each) at which every all-positive error sum of the
summation study (benchmarks/summation.py, benchmarks/results/summation_cpu) stayed within
:data:`FP32_SAFE_TOLERANCE` summed naively in float32, one photo after another as a CPU pass does (a GPU pass
splits the photos into groups, shorter chains: it is safer still)"""


@dataclasses.dataclass
class StreamConfig:
    """Numerical and streaming options of the evaluation passes."""

    accumulate: str = option("auto", "accumulator and compute precision of the passes: auto picks fp32 up to "
                                      f"{FP32_SAFE_PHOTOS:,} photos and fp64 above (where the summation study found "
                                      "fp32 sums of the error outside 5e-6 relative; docs/numerics.md)",
                             choices=("auto", "fp32", "fp64"))
    storage: str = option("fp32", "parameter storage precision", choices=("fp16", "fp32", "fp64"))
    image_precision: str = option("fp32", "photo storage on the device (fp16 halves the streamed bytes)",
                                  choices=("fp32", "fp16"))
    kahan: bool = option(False, "Kahan-compensated sums of objective and gradient over photos (seed Alg. 14)")
    residual_space: str = option("radiance", "fit pixel values (radiance) or divide out E cos (reflectance, the "
                                             "seed's choice)", choices=("radiance", "reflectance"))
    cos_light_min: float = option(0.1, "reject samples lit more grazingly than this cosine (the seed's 0.1)",
                                  min=0.0, max=1.0)
    cos_view_min: float = option(0.05, "reject samples seen more grazingly than this cosine", min=0.0, max=1.0)
    depth_tol: float = option(0.01, "visibility test tolerance, as a fraction of the camera distance", min=0.0)
    shadow_tol: float = option(0.01, "shadow test tolerance, as a fraction of the light distance", min=0.0)
    shadow_map_size: int = option(512, "shadow map side per photo (0: no cast-shadow rejection, no traced shadow "
                                       "rays)", min=0)
    photo_sampling: str = option("filtered", "how a texel samples a photo: filtered (the photo's bilinear filter "
                                             "applied to the model too, at each tap's surface point: highlights a "
                                             "few pixels wide stay sharp; 4 model evaluations per sample), point "
                                             "(nearest pixel) or bilinear (the seed's: the filter at the texel "
                                             "centre's projection)", choices=("filtered", "point", "bilinear"))
    model_lookup: str = option("texel", "the model a sample sees near its texel: texel (the texel's own, the "
                                        "seed's) or bilinear (the renderer's texture lookup, neighbours held "
                                        "between refreshes: exact at material edges; needs filtered sampling "
                                        "and an atlas)", choices=("texel", "bilinear"))
    tap_geometry: str = option("plane", "where filtered sampling evaluates a tap: plane (the texel's face plane "
                                        "to first order) or mesh (the tap's pixel ray traced to the mesh, with "
                                        "the renderer's normal, UV and shadow; a ray query per tap)",
                               choices=("plane", "mesh"))
    groups: int = option(0, "photo groups per pass, parallelism over photos (0: automatic)", min=0)
    photos_per_window: int = option(0, "photos on the device at once when streaming (0: all when they fit, else "
                                       "sized from the memory available); a positive value with photo_residency "
                                       "auto streams in windows", min=0)
    photo_residency: str = option("auto", "where the photos live: device (all on the device), host (all in pinned "
                                          "host memory, uploaded a window per pass), disk (decoded from the "
                                          "capture's files a window per pass, depth and shadow maps recomputed per "
                                          "window), or auto (the first that fits half the memory available and "
                                          "memory_limit_mb; printed, and recorded in model.json's photos)",
                                  choices=("auto", "device", "host", "disk"))
    memory_limit_mb: float = option(0.0, "cap on the memory the photos and their maps may take on the device "
                                         "and in host memory (0: half of what is available)", min=0.0)
    crop_photos: bool = option(True, "store each photo cropped to the object's footprint (the mesh's projected "
                                     "bounding box plus 3 px): only pixels a texel can see; results equal the "
                                     "uncropped photos' to float rounding of the projection")
    decode_threads: int = option(0, "threads (or worker processes) that decode and crop photos (0: 4 threads, at "
                                    "most the CPU count; for files under worker processes one process per CPU up "
                                    "to 16)", min=0)
    photo_decoder: str = option("auto", "what decodes photo files: threads of the fitting process, worker "
                                        "processes (no lock shared with the fit; same bytes), or auto (processes "
                                        "under the texstream command with 16 or more CPUs, else threads)",
                                choices=("auto", "threads", "processes"))
    photo_cache: str = option("auto", "decoded photos cached beside the capture (CAPTURE/.texstream-cache: the "
                                      "cropped photos in the image precision; the same values, so the same "
                                      "fit), read instead of decoding again by later passes and later fits "
                                      "of the same photos, crops and precision. auto: written when photos "
                                      "stream from disk (by the first pass), read whenever ready; on: also "
                                      "written by fits with the photos on the device (in the background, "
                                      "for repeated fits of one capture); off: never read or written",
                              choices=("auto", "on", "off"))
    tiles: int = option(0, "split the atlas's texels into this many tiles of consecutive texels, each fitted over "
                           "only the photos that see it (fit/tiles.py; the untiled fit's result: texels are fitted "
                           "independently, LM's smoothness by a halo exchange; the Laplacian penalty, bilinear "
                           "model_lookup and global line search are refused); 0: one tile per device, i.e. "
                           "untiled on one device", min=0)
    devices: str = option("", "comma-separated devices that share the fit (e.g. cuda:0,cuda:1; empty: the fit's "
                              "device), as device_split says; several devices need photo_residency device")
    device_split: str = option("tiles", "how several devices share the fit: tiles (each fits tiles of texels "
                                        "over every photo that sees them, one thread per device; fit/tiles.py) "
                                        "or photos (each holds a run of the photos, built on it at once, and "
                                        "streams them over every texel; the first device, the fit's, adds "
                                        "their sums each pass and steps every texel; fit/photo_split.py)",
                               choices=("tiles", "photos"))
    tile_backend: str = option("threads", "where the tiles run: threads (one per device in this process) or ray "
                                          "(one Ray actor per tile; needs texstream[distributed] and the photos "
                                          "as files on storage every Ray worker reads)", choices=("threads", "ray"))
    cuda_block_dim: int = option(128, "threads per CUDA block of the accumulation kernels (128 fits three blocks "
                                      "per SM at the register cap; docs/gpu-performance.md)", min=32, max=1024)
    cuda_max_registers: int = option(-1, "registers per CUDA thread of the accumulation kernels: 0 uncapped, -1 "
                                         "168 for layouts of at most 9 parameters (docs/gpu-performance.md)",
                                     min=-1)

def resolve_accumulate(accumulate: str, photos: int) -> str:
    """The accumulate precision a pass uses: "fp32" or "fp64" as given; "auto": fp32 up to
    :data:`FP32_SAFE_PHOTOS` photos, fp64 above (every pass kind honours it, LM's too, unlike Kahan)."""
    if accumulate in ("fp32", "fp64"):
        return accumulate
    if accumulate == "auto":
        return "fp32" if photos <= FP32_SAFE_PHOTOS else "fp64"
    raise ConfigError(f"accumulate precision {accumulate!r} unknown", fix="use auto, fp32 or fp64")


def _vec_types(acc: str, n_params: int):
    """(scalar, parameter vector, parameter matrix) types of the accumulate precision."""
    scalars = {"fp64": wp.float64, "fp32": wp.float32}
    if acc not in scalars:
        raise ConfigError(f"accumulate precision {acc!r} unknown", fix="use fp32 or fp64")
    return (scalars[acc], *param_types(n_params, scalars[acc]))


_MESH_BUILD_LOCK = threading.Lock()


def build_mesh(points: wp.array, indices: wp.array) -> wp.Mesh:
    """A ``wp.Mesh`` (its BVH built on the points' device), one build at a time in this process, finished
    before the next starts. Warp sorts during a build in a temporary buffer shared by the builds on a
    device, held in a table without a lock: two threads building at once (the photo split's parts, one per
    thread) corrupted each other's BVH, which showed as illegal memory accesses or a set-up that never
    ended."""
    with _MESH_BUILD_LOCK:
        mesh = wp.Mesh(points=points, indices=indices)
        wp.synchronize_device(points.device)
    return mesh


class PhotoSet:
    """Photos, depth maps and shadow maps where the passes read them: on the device, in (pinned)
    host memory uploaded a window per pass, or decoded from the capture's files a window per pass
    (``residency``; ``StreamConfig.photo_residency``). Set-up makes no host round trip per photo:
    per-photo constants in one array, photos uploaded in chunks through pinned buffers, depth and
    shadow maps in one launch over photos x pixels (fit/photo_stream.py)."""

    def __init__(self, frames: list[PhotoFrame], images, mesh_points: np.ndarray | None,
                 mesh_faces: np.ndarray | None, masks: list[np.ndarray | None] | None = None,
                 config: StreamConfig | None = None, device: str = "cpu", mesh_normals: np.ndarray | None = None,
                 mesh_uvs: np.ndarray | None = None, defer_upload: bool = False):
        """``images``: a list of (H, W, >=3) linear arrays, or a :class:`~texstream.fit.stream.photo_stream.PhotoFiles`
        to read them from (masks then come from its mask paths). ``mesh_points=None`` (no geometry:
        single-view fits, fit/photometric_stereo.py) builds no depth or shadow maps: each photo's depth
        map holds its mask (1 = sample, 0 = masked) and ``ImageInfo.depth_is_mask`` tells the kernels
        to test only that. Per-vertex ``mesh_normals`` and ``mesh_uvs`` serve traced taps
        (``StreamConfig.tap_geometry``).

        ``timings`` records the set-up's phases in seconds (upload, depth_maps, shadow_maps, other;
        each phase ends with a device synchronisation so the figures are its own).

        ``defer_upload`` (photos resident on the device): the device buffers only, with the loader kept
        open; :func:`upload_photo_sets` fills them together with other devices' sets (the photo split)."""
        self.mesh_normals = self.mesh_uvs = None
        self.frames = list(frames)
        """the photos' :class:`PhotoFrame`s (a tile's actor builds its own set from them, fit/tiles_ray.py)"""
        self.source = images if isinstance(images, PhotoFiles) else None
        """the photos' files when given as a PhotoFiles (paths only: nothing decoded is held), else None"""
        self.light_kinds = [fr.light_kind for fr in frames]
        """per photo "point", "directional" or "none" (checked against the model by StreamProblem)"""
        self.exposures = [float(fr.exposure) for fr in frames]
        self.timings = {"upload": 0.0, "depth_maps": 0.0, "shadow_maps": 0.0, "other": 0.0}
        self.crops = None
        """(n, 4) int64 (x0, y0, width, height) of each photo's stored crop (None: whole photos)"""
        self.cache_to_write = self.cache_writer = None  # photo_cache on: _write_cache_from_device
        self.device = device
        self.n = len(frames)
        if self.n == 0 or len(images) != self.n:
            raise InputError("no photos to fit", fix="give a capture with at least one photo")
        if mesh_points is None:
            return self._init_without_mesh(frames, images, masks, config, device)
        t_start = time.perf_counter()
        cfg = config or StreamConfig()
        self.files = isinstance(images, PhotoFiles)
        self.mesh_arrays = (mesh_points, mesh_faces, mesh_normals, mesh_uvs)
        """the mesh as given (another process builds the same set from them, fit/tiles_ray.py)"""
        self.mesh = build_mesh(wp.array(np.asarray(mesh_points, np.float32), dtype=wp.vec3, device=device),
                               wp.array(np.asarray(mesh_faces, np.int32).reshape(-1), dtype=wp.int32, device=device))
        if mesh_normals is not None and mesh_uvs is not None:
            self.mesh_normals = wp.array(np.asarray(mesh_normals, np.float32), dtype=wp.vec3, device=device)
            self.mesh_uvs = wp.array(np.asarray(mesh_uvs, np.float32), dtype=wp.vec2, device=device)
        lo, hi = mesh_points.min(axis=0), mesh_points.max(axis=0)
        self.center = 0.5 * (lo + hi)
        self.radius = 0.5 * float(np.linalg.norm(hi - lo))
        self.shadow_eps = SHADOW_EPS_REL * max(2.0 * self.radius, 1e-12)  # the renderer's (render/renderer.py)
        ssize = int(cfg.shadow_map_size)
        self.shadow_side = max(ssize, 2)
        self.sizes = sizes = np.array([[fr.height, fr.width] for fr in frames], np.int64)
        infos = image_infos(frames, None, self.center, self.radius, ssize)
        if cfg.crop_photos:
            full = struct_array(infos, ImageInfo, device)
            self.crops = crop_boxes(self.mesh.points, full, sizes[:, 1], sizes[:, 0], device)
            crop_infos(infos, self.crops)
            self.hmax, self.wmax = int(self.crops[:, 3].max()), int(self.crops[:, 2].max())
        elif self.files:
            self.hmax, self.wmax = int(sizes[:, 0].max()), int(sizes[:, 1].max())
        else:
            self.hmax = max(int(im.shape[0]) for im in images)
            self.wmax = max(int(im.shape[1]) for im in images)
        self.infos_host = infos
        self.infos = struct_array(infos, ImageInfo, device)
        fp16 = cfg.image_precision == "fp16"
        self.img_dtype = wp.vec3h if fp16 else wp.vec3
        pixels = self.hmax * self.wmax
        self.image_bytes = self.n * pixels * 3 * (2 if fp16 else 4)
        per_photo = pixels * (3 * (2 if fp16 else 4) + 4) + 4 * self.shadow_side ** 2
        limit = int(cfg.memory_limit_mb * 2 ** 20)
        requested = cfg.photo_residency
        if requested == "disk" and not self.files:
            raise ConfigError("photo_residency disk needs the photos as files (a capture folder), not arrays",
                              fix="set stream.photo_residency to auto, device or host")
        self.residency, self.residency_reason = choose_residency(requested, device, self.n * per_photo,
                                                                 self.n * per_photo, self.files, limit,
                                                                 windows=cfg.photos_per_window > 0)
        if self.residency == "device":
            self.window = self.n
        elif cfg.photos_per_window > 0:
            self.window = min(self.n, int(cfg.photos_per_window))
        else:
            self.window = window_size(self.n, per_photo, device, limit)
        self.streamed = self.residency != "device"
        self.maps_on_device = self.residency == "disk" and keep_maps_on_device(
            device, self.n * (4 * pixels + 4 * self.shadow_side ** 2), limit)
        """photos streamed from disk with every depth and shadow map kept on the device (else a window's
        maps are recomputed for each pass)"""
        if self.residency == "disk":
            self.residency_reason += ("; depth and shadow maps kept on the device" if self.maps_on_device
                                      else "; depth and shadow maps recomputed per window")
        say("fit", f"photos: {self.residency}, {self.window} per window ({self.residency_reason})")
        if defer_upload and self.residency != "device":
            raise ConfigError(f"a deferred upload needs the photos on the device, not {self.residency}",
                              fix="set stream.photo_residency to device")
        self.loader = PhotoLoader(images, masks, self.crops, sizes, cfg.decode_threads, decoder=cfg.photo_decoder)
        self._open_cache(cfg, fp16)
        self.timings["other"] += time.perf_counter() - t_start
        try:
            if self.residency == "device":
                self._init_device(defer_upload)
            else:
                self._init_windows()
        except BaseException:
            self.loader.close()  # its threads (and a bad photo's pending chunk) end with the set-up
            raise
        if defer_upload:
            return
        if self.residency != "disk":
            self.loader.close()
            self.loader = None  # nothing is read again: drop the caller's photos' references

    def _open_cache(self, cfg: StreamConfig, fp16: bool) -> None:
        """The decoded photos' cache (:class:`~texstream.fit.stream.photo_stream.PhotoCache`): read when one is
        ready for these photos, crops and precision (any residency); started when photos are streamed
        from disk (filled by the first pass). Said, with the reason when none is written."""
        source = self.loader.source
        if cfg.photo_cache == "off" or not self.files or source.cache_dir is None:
            return
        cache = PhotoCache(source, self.crops, self.hmax, self.wmax, np.float16 if fp16 else np.float32,
                           self.loader.has_masks)
        if cache.ready:
            self.loader.cache = cache
            say("fit", f"photos: read from the cache {cache.path} (decoded before)")
        elif self.residency == "device" and cfg.photo_cache == "on":
            self.cache_to_write = cache  # written from the device's photos once they are there (_init_device)
        elif self.residency == "disk":
            why = cache.start_writing()
            if why is None:
                self.loader.cache = cache
                say("fit", f"photos: decoded once into the cache {cache.path} "
                           f"({cache.nbytes / 2 ** 30:.2f} GiB)")
            else:
                say("fit", f"photos: no cache written ({why}); each pass decodes them")

    def _write_cache_from_device(self, masks) -> None:
        """Write :attr:`cache_to_write` from the photos and masks on the device, on a thread of its own (the
        device's photos copied out a chunk at a time on a CUDA stream of its own, while the fit runs on
        the device's); :meth:`wait_for_cache` waits for it."""
        import threading

        cache = self.cache_to_write
        why = cache.start_writing()
        if why is not None:
            say("fit", f"photos: no cache written ({why})")
            return
        pix, dev = self.hmax * self.wmax, self.device
        chunk = max(1, min(self.n, UPLOAD_CHUNK_BYTES // (pix * wp.types.type_size_in_bytes(self.img_dtype))))
        pinned = dev != "cpu"
        buf = wp.empty((chunk, self.hmax, self.wmax), dtype=self.img_dtype, device="cpu", pinned=pinned)
        mbuf = self._masks_buffer(chunk, "cpu", pinned)
        stream = wp.Stream(dev) if pinned else None
        has_masks = self.loader.has_masks

        def write():
            try:
                for b in range(0, self.n, chunk):
                    c = min(chunk, self.n - b)
                    wp.copy(buf, self.images, 0, b * pix, c * pix, stream=stream)
                    if has_masks:
                        wp.copy(mbuf, masks, 0, b * pix, c * pix, stream=stream)
                    if stream is not None:
                        wp.synchronize_stream(stream)
                    images, ms = buf.numpy(), mbuf.numpy() if has_masks else None
                    for j in range(c):
                        cache.store(b + j, images[j], None if ms is None else ms[j])
                cache.finish()
            except Exception:  # noqa: BLE001 - a cache that cannot be written is only a lost speed-up
                cache.abandon()

        self.cache_writer = threading.Thread(target=write, name="texstream-photo-cache")
        self.cache_writer.start()
        say("fit", f"photos: written to the cache {cache.path} in the background "
                   f"({cache.nbytes / 2 ** 30:.2f} GiB)")

    def wait_for_cache(self) -> None:
        """Wait for a cache being written in the background (:meth:`_write_cache_from_device`)."""
        writer = self.cache_writer
        if writer is not None:
            writer.join()
            self.cache_writer = None

    def _finish_cache(self) -> None:
        cache = self.loader.cache if self.loader is not None else None
        if cache is not None and cache.writing and cache.finish():
            say("fit", f"photos: cached in {cache.path}")

    def _sync(self) -> None:
        wp.synchronize_device(self.device)

    def _masks_buffer(self, count: int, device: str, pinned: bool = False):
        """A (count, hmax, wmax) uint8 mask buffer, or a one-element placeholder when no photo has a mask."""
        if not self.loader.has_masks:
            return wp.zeros((1, 1, 1), dtype=wp.uint8, device=device)
        return wp.empty((count, self.hmax, self.wmax), dtype=wp.uint8, device=device, pinned=pinned)

    def _maps(self, first: int, count: int, masks, depth, shadow) -> None:
        """Depth maps (``masks`` applied) and shadow maps of photos first..first+count-1 into ``depth``
        and ``shadow`` (each timed, see ``timings``)."""
        t0 = time.perf_counter()
        self.launch_depth_maps(first, count, masks, depth)
        self._sync()
        t1 = time.perf_counter()
        self.launch_shadow_maps(first, count, shadow)
        self._sync()
        self.timings["depth_maps"] += t1 - t0
        self.timings["shadow_maps"] += time.perf_counter() - t1

    def _photo_chunks(self, count: int, pixels: int):
        """(offset, size) chunks of ``count`` photos of ``pixels`` each, at most :data:`MAX_LAUNCH_THREADS`
        threads a launch (one launch for any ornament-sized set)."""
        step = max(1, MAX_LAUNCH_THREADS // max(pixels, 1))
        return [(j, min(step, count - j)) for j in range(0, count, step)]

    def launch_depth_maps(self, first: int, count: int, masks, depth, use_masks: bool = True,
                          stream: wp.Stream | None = None) -> None:
        """Depth maps of photos first..first+count-1 into ``depth[0:count]`` (``masks`` likewise indexed,
        applied when any photo has a mask and ``use_masks``), on ``stream`` (default: the device's current)."""
        use = int(self.loader.has_masks and use_masks)
        for j, c in self._photo_chunks(count, self.hmax * self.wmax):
            wp.launch(depth_maps_kernel, dim=(c, self.hmax, self.wmax), device=self.device, stream=stream,
                      inputs=[self.mesh.id, self.infos, first + j, masks[j:j + c] if use else masks, use],
                      outputs=[depth[j:j + c]])

    def launch_shadow_maps(self, first: int, count: int, shadow, stream: wp.Stream | None = None) -> None:
        """Shadow maps of photos first..first+count-1 into ``shadow[0:count]``, on ``stream`` (default: the
        device's current)."""
        for j, c in self._photo_chunks(count, self.shadow_side ** 2):
            wp.launch(shadow_maps_kernel, dim=(c, self.shadow_side, self.shadow_side), device=self.device,
                      stream=stream, inputs=[self.mesh.id, self.infos, first + j], outputs=[shadow[j:j + c]])

    def _init_device(self, defer_upload: bool = False) -> None:
        """All photos, depth and shadow maps on the device: photos filled in place on the CPU, or uploaded
        in chunks through pinned buffers, their depth and shadow maps made beside (:func:`upload_photo_sets`).
        ``defer_upload``: the device buffers only, filled later by :func:`upload_photo_sets` with other
        sets' photos (photos split over devices: the host crops all of them once, one pipeline)."""
        n, dev = self.n, self.device
        self.images = wp.empty((n, self.hmax, self.wmax), dtype=self.img_dtype, device=dev)
        self.device_masks = self._masks_buffer(n, dev)
        """the photos' masks on the device while the depth maps are made (then dropped)"""
        self.depth = wp.empty((n, self.hmax, self.wmax), dtype=wp.float32, device=dev)
        self.shadow = wp.empty((n, self.shadow_side, self.shadow_side), dtype=wp.float32, device=dev)
        if defer_upload:
            return
        upload_photo_sets([self])
        if self.cache_to_write is not None:
            self._write_cache_from_device(self.device_masks)
        self.device_masks = None

    def _init_windows(self) -> None:
        """Window-sized device buffers; for "host" residency also every photo and its maps in (pinned)
        host memory, the maps computed a window at a time on the device and copied back."""
        n, dev, w, pix = self.n, self.device, self.window, self.hmax * self.wmax
        pinned = dev != "cpu"
        self.images = wp.empty((w, self.hmax, self.wmax), dtype=self.img_dtype, device=dev)
        self.depth = wp.empty((w, self.hmax, self.wmax), dtype=wp.float32, device=dev)
        self.shadow = wp.empty((w, self.shadow_side, self.shadow_side), dtype=wp.float32, device=dev)
        self.infos_window = wp.zeros(w, dtype=ImageInfo, device=dev)
        self.window_masks = self._masks_buffer(w, dev)
        if self.residency == "disk":
            # two slots the loader fills alternately (one decoding while the other's window is in use);
            # copied to the window's device arrays before each window's passes
            self.slots = WindowSlots(
                [wp.empty((w, self.hmax, self.wmax), dtype=self.img_dtype, device="cpu", pinned=pinned)
                 for _ in range(2)], [self._masks_buffer(w, "cpu", pinned) for _ in range(2)])
            if self.maps_on_device:
                # the depth maps without masks (the masks come with each window's photos, applied by
                # masked_depth_kernel: the same values the masked launch writes)
                self.all_depth = wp.empty((n, self.hmax, self.wmax), dtype=wp.float32, device=dev)
                self.all_shadow = wp.empty((n, self.shadow_side, self.shadow_side), dtype=wp.float32, device=dev)
                t0 = time.perf_counter()
                self.launch_depth_maps(0, n, self.window_masks, self.all_depth, use_masks=False)
                self._sync()
                t1 = time.perf_counter()
                self.launch_shadow_maps(0, n, self.all_shadow)
                self._sync()
                self.timings["depth_maps"] += t1 - t0
                self.timings["shadow_maps"] += time.perf_counter() - t1
            return
        t0 = time.perf_counter()
        self.host_images = wp.empty((n, self.hmax, self.wmax), dtype=self.img_dtype, device="cpu", pinned=pinned)
        self.host_depth = wp.empty((n, self.hmax, self.wmax), dtype=wp.float32, device="cpu", pinned=pinned)
        self.host_shadow = wp.empty((n, self.shadow_side, self.shadow_side), dtype=wp.float32, device="cpu",
                                    pinned=pinned)
        host_masks = self._masks_buffer(w, "cpu", pinned)
        imgs = self.host_images.numpy()
        for b in range(0, n, w):
            c = min(w, n - b)
            t1 = time.perf_counter()
            self.loader.fill(range(b, b + c), imgs[b:b + c], host_masks.numpy() if self.loader.has_masks else None)
            if self.loader.has_masks:
                wp.copy(self.window_masks, host_masks, 0, 0, c * pix)
            self._sync()
            self.timings["upload"] += time.perf_counter() - t1
            self._maps(b, c, self.window_masks, self.depth, self.shadow)
            t2 = time.perf_counter()
            wp.copy(self.host_depth, self.depth, b * pix, 0, c * pix)
            ss = self.shadow_side ** 2
            wp.copy(self.host_shadow, self.shadow, b * ss, 0, c * ss)
            self._sync()
            self.timings["upload"] += time.perf_counter() - t2

    def _init_without_mesh(self, frames, images, masks, config, device) -> None:
        """Photos and masks only (see __init__); never streamed in windows (one view is small)."""
        cfg = config or StreamConfig()
        if isinstance(images, PhotoFiles):
            raise ConfigError("single-view fits take their photos as arrays", fix="load the photos first")
        self.hmax = max(int(im.shape[0]) for im in images)
        self.wmax = max(int(im.shape[1]) for im in images)
        fp16 = cfg.image_precision == "fp16"
        stack = np.zeros((self.n, self.hmax, self.wmax, 3), dtype=np.float16 if fp16 else np.float32)
        depth = np.zeros((self.n, self.hmax, self.wmax), np.float32)
        for k, im in enumerate(images):
            stack[k, :im.shape[0], :im.shape[1]] = im[..., :3]
            mk = masks[k] if masks is not None and masks[k] is not None else np.ones(im.shape[:2], bool)
            depth[k, :im.shape[0], :im.shape[1]] = np.asarray(mk, bool)
        infos = image_infos(frames, None, None, 0.0, 0)
        infos["depth_is_mask"] = 1  # no geometry, no cast shadows: mask them in the photo's mask
        self.mesh = None
        self.files = False
        self.loader = None
        self.window = self.n
        self.streamed = False
        self.residency, self.residency_reason = "device", "single-view photos"
        self.shadow_side = 2
        self.infos_host = infos
        self.infos = struct_array(infos, ImageInfo, device)
        self.img_dtype = wp.vec3h if fp16 else wp.vec3
        self.images = wp.array(stack, dtype=self.img_dtype, device=device)
        self.depth = wp.array(depth, dtype=wp.float32, device=device)
        self.shadow = wp.full((self.n, 2, 2), np.inf, dtype=wp.float32, device=device)
        self.image_bytes = int(stack.nbytes)

    def subset(self, indices, device: str | None = None) -> "PhotoSet":
        """The photos ``indices`` of this set (with their depth and shadow maps, mesh and window size) as a
        PhotoSet of their own, without loading or rendering anything again: e.g. a fit on part of the
        photos judged on the rest (fit/materials.py), or a tile's photos (fit/tiles.py). One copy through
        the host, at set-up (device to device when ``device``, another device, takes every photo).
        ``device``: where the subset lives (default: this set's); another device needs this set's photos
        resident on its device (``residency`` device)."""
        idx = np.asarray(indices, np.int64).reshape(-1)
        if idx.size == 0 or idx.min() < 0 or idx.max() >= self.n:
            raise InputError(f"photo subset {idx.tolist()[:8]} is empty or outside 0..{self.n - 1}",
                             fix="report this with the command that made it")
        dev = self.device if device is None else str(device)
        if dev != self.device and (self.residency != "device" or self.mesh is None):
            raise ConfigError(f"photos held with residency {self.residency} cannot be moved to {dev}",
                              fix="set stream.photo_residency to device to fit on several devices")
        out = PhotoSet.__new__(PhotoSet)
        out.__dict__.update(self.__dict__)
        out.n = int(idx.size)
        out.light_kinds = [self.light_kinds[k] for k in idx]
        out.exposures = [self.exposures[k] for k in idx]
        out.frames = [self.frames[k] for k in idx]
        out.source = None if self.source is None else self.source.subset(idx)
        out.infos_host = self.infos_host[idx]
        out.crops = None if self.crops is None else self.crops[idx]
        out.infos = struct_array(out.infos_host, ImageInfo, dev)
        if dev != self.device:
            out.device = dev
            out.mesh = build_mesh(wp.clone(self.mesh.points, device=dev), wp.clone(self.mesh.indices, device=dev))
            if self.mesh_normals is not None:
                out.mesh_normals = wp.clone(self.mesh_normals, device=dev)
                out.mesh_uvs = wp.clone(self.mesh_uvs, device=dev)
            out.window = out.n
            if np.array_equal(idx, np.arange(self.n)):  # every photo: device to device, no host round trip
                out.images, out.depth, out.shadow = (wp.clone(a, device=dev) for a in (self.images, self.depth,
                                                                                        self.shadow))
                return out
        out.window = min(self.window, out.n)
        if self.residency == "disk":  # the window buffers are shared: the two sets are never streamed at once
            files = self.loader.source.subset(idx)
            out.sizes = self.sizes[idx]
            parent = self.loader
            cache = parent.cache if parent.cached() else None  # a cache still being written serves no subset
            index = None if cache is None else (idx if parent.index is None else parent.index[idx])
            out.loader = PhotoLoader(files, None, out.crops, out.sizes, parent.requested_threads, cache=cache,
                                     index=index, decoder=parent.decoder if parent.processes else "threads")
            out.maps_on_device = False  # the kept maps are the whole set's: a subset's windows make their own
            out.image_bytes = self.image_bytes // self.n * out.n
            return out
        src = (self.host_images, self.host_depth, self.host_shadow) if self.streamed else (self.images, self.depth, self.shadow)
        images, depth, shadow = (np.ascontiguousarray(a.numpy()[idx]) for a in src)
        if out.streamed:  # the window buffers are shared: the two sets are never streamed at once
            pinned = dev != "cpu"
            out.host_images = wp.array(images, dtype=self.images.dtype, device="cpu", pinned=pinned)
            out.host_depth = wp.array(depth, dtype=wp.float32, device="cpu", pinned=pinned)
            out.host_shadow = wp.array(shadow, dtype=wp.float32, device="cpu", pinned=pinned)
        else:
            out.images = wp.array(images, dtype=self.images.dtype, device=dev)
            out.depth = wp.array(depth, dtype=wp.float32, device=dev)
            out.shadow = wp.array(shadow, dtype=wp.float32, device=dev)
        out.image_bytes = int(images.nbytes)
        return out

    def windows(self):
        """Yield (images, depth, shadow, infos, begin, end) device views, uploading windows when streamed
        (and, from disk, decoding the next window on the loader's threads while this one is in use)."""
        if not self.streamed:
            yield self.images, self.depth, self.shadow, self.infos, 0, self.n
            return
        pix = self.hmax * self.wmax
        for b in range(0, self.n, self.window):
            e = min(b + self.window, self.n)
            c = e - b
            if self.residency == "disk":
                images, depth, shadow = self._disk_window(b, c)
            else:
                wp.copy(self.images, self.host_images, 0, b * pix, c * pix)
                wp.copy(self.depth, self.host_depth, 0, b * pix, c * pix)
                ss = self.shadow_side ** 2
                wp.copy(self.shadow, self.host_shadow, 0, b * ss, c * ss)
                images, depth, shadow = self.images, self.depth, self.shadow
            wp.copy(self.infos_window, self.infos, 0, b, c)
            yield images, depth, shadow, self.infos_window, 0, c

    def _submit_window(self, b: int) -> None:
        """Start decoding the window from photo ``b`` into the next slot (once its last upload has left it)."""
        slots = self.slots
        slot = slots.turn % 2
        slots.turn += 1
        if slots.copied[slot] is not None:
            wp.synchronize_event(slots.copied[slot])
        c = min(self.window, self.n - b)
        masks = slots.masks[slot].numpy() if self.loader.has_masks else None
        slots.pending = (self, b, slot, self.loader.submit(range(b, b + c), slots.images[slot].numpy(), masks))

    def _disk_window(self, b: int, c: int):
        """Photos b..b+c-1 decoded (prefetched since the previous window) and uploaded, with their depth
        and shadow maps (recomputed on the device, or the ones kept there, masked by the window's masks);
        starts decoding the next window (cyclically, so a pass's last window prefetches the next pass's
        first). Returns the window's device (images, depth, shadow)."""
        slots = self.slots
        if slots.pending is None or slots.pending[0] is not self or slots.pending[1] != b:
            if slots.pending is not None:
                wait(slots.pending[3])  # a window nobody asked for (a pass cut short, or another set's)
            self._submit_window(b)
        _, _, slot, futures = slots.pending
        wait(futures)
        self._finish_cache()
        self._submit_window(b + self.window if b + self.window < self.n else 0)
        # one copy to the window's device arrays on every device (on the CPU a memcpy, small beside the
        # decoding), so the CPU runs the path CUDA does
        pix = self.hmax * self.wmax
        wp.copy(self.images, slots.images[slot], 0, 0, c * pix)
        if self.loader.has_masks:
            wp.copy(self.window_masks, slots.masks[slot], 0, 0, c * pix)
        if self.device != "cpu":
            slots.copied[slot] = wp.get_stream(self.device).record_event()
        if not self.maps_on_device:
            self.launch_depth_maps(b, c, self.window_masks, self.depth)
            self.launch_shadow_maps(b, c, self.shadow)
            return self.images, self.depth, self.shadow
        shadow = self.all_shadow[b:b + c]
        if not self.loader.has_masks:
            return self.images, self.all_depth[b:b + c], shadow
        wp.launch(masked_depth_kernel, dim=(c, self.hmax, self.wmax), device=self.device,
                  inputs=[self.all_depth, b, self.window_masks], outputs=[self.depth])
        return self.images, self.depth, shadow


def upload_photo_sets(sets: list[PhotoSet], in_place: bool | None = None) -> None:
    """Fill the device photos of ``sets`` (each set up by ``_init_device``; one set, or one per device of a
    photo split) and make their depth and shadow maps (each on its set's device). The maps depend on the
    mesh and the cameras only, so a CUDA set's run on a stream of their own while its photos upload (the
    depth maps unmasked, their masks applied when the masks have arrived: the same values); the CPU's after.

    The photos go in chunks of ~:data:`UPLOAD_CHUNK_BYTES` (:data:`ARRAY_UPLOAD_CHUNK_BYTES` for arrays)
    through :data:`UPLOAD_SLOTS` pinned host buffers shared by all sets: the sets' loaders crop the next
    chunks while the oldest chunk's copy runs to its set's device (:func:`_upload_in_chunks`). The buffers
    hold float32, as the photos come, and half-float photos are converted on the device: a plain host copy
    is ~5x faster than numpy's float16 conversion (both round to nearest even, so the halves are the same).
    The copies and conversions run on a high-priority stream per device, which the device's current stream
    then waits for. ``timings``: ``upload`` until every copy is done; ``depth_maps`` the wait for the maps made
    beside it and the masks' application, or the CPU sets' depth maps; ``shadow_maps`` the CPU sets' shadow
    maps. ``in_place``: CPU sets filled in place, no buffers (default: on the CPU); False runs the pipeline
    there too (tests)."""
    if in_place is None:
        in_place = all(s.device == "cpu" for s in sets)
    t0 = time.perf_counter()
    beside = [s for s in sets if s.device != "cpu"]
    maps_streams = [_maps_beside_the_upload(s) for s in beside]
    if in_place:
        for s in sets:
            s.loader.fill(range(s.n), s.images.numpy(), s.device_masks.numpy() if s.loader.has_masks else None)
    else:
        _upload_in_chunks(sets)
    devices = sorted({s.device for s in sets})
    _synchronize_current_streams(devices)
    t1 = time.perf_counter()
    for s, maps_stream in zip(beside, maps_streams, strict=True):
        wp.synchronize_stream(maps_stream)  # the maps made beside the upload: any wait for them is counted here
        if s.loader.has_masks:
            wp.launch(masked_depth_kernel, dim=(s.n, s.hmax, s.wmax), device=s.device,
                      inputs=[s.depth, 0, s.device_masks], outputs=[s.depth])
    rest = [s for s in sets if s.device == "cpu"]
    for s in rest:
        s.launch_depth_maps(0, s.n, s.device_masks, s.depth)
    for d in devices:
        wp.synchronize_device(d)
    t2 = time.perf_counter()
    for s in rest:
        s.launch_shadow_maps(0, s.n, s.shadow)
    for d in devices:
        wp.synchronize_device(d)
    t3 = time.perf_counter()
    for s in sets:
        s.timings["upload"] += t1 - t0
        s.timings["depth_maps"] += t2 - t1
        s.timings["shadow_maps"] += t3 - t2


def _maps_beside_the_upload(s: PhotoSet) -> wp.Stream:
    """Launch the depth maps (without masks) and shadow maps of CUDA set ``s`` on a new stream of its device,
    after the work queued on its current stream (the mesh, the photos' constants, the buffers), so that they
    run while the host crops the photos (the copies and conversions on a stream of higher priority,
    :func:`_upload_in_chunks`). Returns the stream."""
    maps_stream = wp.Stream(s.device)
    maps_stream.wait_stream(wp.get_stream(s.device))
    # launched on the stream itself, not made the device's current stream: another thread's work on the
    # device meanwhile (the texels' set-up) stays on the current one
    s.launch_depth_maps(0, s.n, s.device_masks, s.depth, use_masks=False, stream=maps_stream)
    s.launch_shadow_maps(0, s.n, s.shadow, stream=maps_stream)
    return maps_stream


def _upload_order(sets: list[PhotoSet], chunks: list[int]) -> list[tuple[int, int, int]]:
    """The pipeline's chunks as (set, first photo, photos): one set after another, each set's in order (sets
    taken at once, alternating, crop with both loaders' threads, which contend for Python's lock: slower on
    a two-GPU host, docs/scale.md)."""
    return [(i, b, min(c, s.n - b)) for i, (s, c) in enumerate(zip(sets, chunks)) for b in range(0, s.n, c)]


def _upload_in_chunks(sets: list[PhotoSet]) -> None:
    """:func:`upload_photo_sets`'s pipeline: the sets' photos in :func:`_upload_order` through
    :data:`UPLOAD_SLOTS` shared host buffers (pinned where a set is on CUDA), the loaders cropping the chunks of
    all buffers but one while the oldest chunk is copied to its set's device."""
    # per set: whether its photos arrive as float32 for half-float storage, and its chunk of photos
    half = [s.img_dtype == wp.vec3h and not s.loader.cached() for s in sets]
    stage_types = {wp.vec3 if h else s.img_dtype for s, h in zip(sets, half)}
    if len(stage_types) > 1:
        raise ValueError("photo sets uploaded together must stage one pixel type")
    stage_dtype = stage_types.pop()
    pixel_bytes = wp.types.type_size_in_bytes(stage_dtype)
    pixels = [s.hmax * s.wmax for s in sets]
    chunks = [max(1, min(s.n, (UPLOAD_CHUNK_BYTES if s.loader.files else ARRAY_UPLOAD_CHUNK_BYTES) // (p * pixel_bytes)))
              for s, p in zip(sets, pixels)]
    size = max(c * p for c, p in zip(chunks, pixels))
    pinned = any(s.device != "cpu" for s in sets)
    order = _upload_order(sets, chunks)
    n_slots = max(2, min(int(UPLOAD_SLOTS), len(order)))
    stage = [wp.empty(size, dtype=stage_dtype, device="cpu", pinned=pinned) for _ in range(n_slots)]
    # mask buffers only where some photo has a mask (a one-element placeholder otherwise, as _masks_buffer)
    mask_size = size if any(s.loader.has_masks for s in sets) else 1
    stage_m = [wp.empty(mask_size, dtype=wp.uint8, device="cpu", pinned=pinned) for _ in range(n_slots)]
    stage_np = [(a.numpy(), m.numpy()) for a, m in zip(stage, stage_m)]
    # per set, where a chunk lands on its device before the conversion to half floats
    landing = [wp.empty((c, s.hmax, s.wmax), dtype=wp.vec3, device=s.device) if h else None
               for s, c, h in zip(sets, chunks, half)]
    copied = [None] * n_slots
    devices = sorted({s.device for s in sets})
    # per CUDA device a high-priority stream for the copies and conversions, after the device's queued work:
    # the maps made beside the upload (default priority) fill the GPU, and each conversion would wait behind
    # them, the host's next crop with it
    streams = {d: wp.Stream(d, priority=-1) for d in devices if d != "cpu"}
    for d, st in streams.items():
        st.wait_stream(wp.get_stream(d))

    def upload(q: int, slot: int, filling: list) -> None:
        i, b, c = order[q]
        s, pix = sets[i], pixels[i]
        st = streams.get(s.device)
        wait(filling)
        if half[i]:
            wp.copy(landing[i], stage[slot], 0, 0, c * pix, stream=st)
            wp.launch(to_half_kernel, dim=(c, s.hmax, s.wmax), device=s.device, stream=st, inputs=[landing[i], b],
                      outputs=[s.images])
        else:
            wp.copy(s.images, stage[slot], b * pix, 0, c * pix, stream=st)
        if s.loader.has_masks:
            wp.copy(s.device_masks, stage_m[slot], b * pix, 0, c * pix, stream=st)
        if st is not None:
            copied[slot] = st.record_event()

    pending, submitted = collections.deque(), []
    try:
        with _short_switch_interval():
            for q, (i, b, c) in enumerate(order):
                s, pix, chunk, slot = sets[i], pixels[i], chunks[i], q % n_slots
                if copied[slot] is not None:
                    wp.synchronize_event(copied[slot])  # this buffer's previous copy has left it
                images = stage_np[slot][0][:chunk * pix].reshape(chunk, s.hmax, s.wmax, -1)
                masks = stage_np[slot][1][:chunk * pix].reshape(chunk, s.hmax, s.wmax) if s.loader.has_masks else None
                # later chunks are cropped while the loaders finish this one: no thread idles at a chunk's end
                filling = s.loader.submit(range(b, b + c), images, masks)
                submitted.extend(filling)
                pending.append((q, slot, filling))
                if len(pending) == n_slots:
                    upload(*pending.popleft())
            while pending:
                upload(*pending.popleft())
    except BaseException:
        # a photo failed: the buffers go with this frame, so no crop may still write them nor copy read them
        concurrent.futures.wait(submitted)
        for d in devices:
            try:
                wp.synchronize_device(d)
            except Exception:  # noqa: BLE001 - the photo's error is the one to report
                pass
        raise
    # the device's later work after the upload's; the pinned buffers are freed on return: every copy reading
    # them done first (freeing pinned memory waits only for the calling thread's current device, not for a
    # copy to another one or on another stream)
    for d, st in streams.items():
        wp.get_stream(d).wait_stream(st)
        wp.synchronize_stream(st)


def _synchronize_current_streams(devices: list[str]) -> None:
    """Wait for the work queued on each CUDA device's current stream (not its other streams: the maps made
    beside the upload)."""
    for d in devices:
        if d != "cpu":
            wp.synchronize_stream(wp.get_stream(d))


_SWITCH_LOCK = threading.Lock()
_switch_state = {"users": 0, "saved": 0.0}


@contextlib.contextmanager
def _short_switch_interval():
    """:data:`UPLOAD_SWITCH_INTERVAL_S` as the interpreter's switch interval while any upload runs (uploads on
    several threads at once share it), the interval before restored when the last one ends."""
    with _SWITCH_LOCK:
        if _switch_state["users"] == 0:
            _switch_state["saved"] = sys.getswitchinterval()
            sys.setswitchinterval(min(_switch_state["saved"], UPLOAD_SWITCH_INTERVAL_S))
        _switch_state["users"] += 1
    try:
        yield
    finally:
        with _SWITCH_LOCK:
            _switch_state["users"] -= 1
            if _switch_state["users"] == 0:
                sys.setswitchinterval(_switch_state["saved"])


def _stream_of(device: str):
    """The device's current stream (None on the CPU, whose copies are synchronous)."""
    return None if device == "cpu" else wp.get_stream(device)


def exposure_mean_square(photos) -> float:
    """The photos' mean squared exposure (1 for none): the view prior's unit (:meth:`StreamProblem.set_view_prior`)."""
    exposures = np.asarray(getattr(photos, "exposures", [1.0]), np.float64)
    return float(np.mean(exposures ** 2)) if exposures.size else 1.0


class StreamProblem:
    """Per-texel objective/gradient/curvature passes over a PhotoSet (buffers allocated once)."""

    def __init__(self, texels: TexelSet, photos: PhotoSet, layout: ModelLayout,
                 config: StreamConfig | None = None, device: str = "cpu"):
        """``photos``: a :class:`PhotoSet`, or photos split over devices
        (:class:`~texstream.fit.multi.photo_split.DevicePhotos`, whose first part is on ``device``): the problem
        then streams its first part itself and the others through ``peers``."""
        self.cfg = cfg = config or StreamConfig()
        self.texels, self.photos, self.layout, self.device = texels, photos, layout, device
        parts = getattr(photos, "parts", None)
        self.own_photos = parts[0] if parts else photos
        """the photos this problem's own launches stream (the first part of split photos)"""
        if self.own_photos.device != device:
            raise ConfigError(f"the problem is on {device} and its photos on {self.own_photos.device}",
                              fix="list the fit's device first in stream.devices")
        kinds = list(getattr(photos, "light_kinds", []))
        unlit = sum(k == "none" for k in kinds)
        if unlit and not layout.is_radiance:
            raise no_light_error(unlit, len(kinds), layout.kind)
        # the light-free passes: 1 the radiance model, 2 the view-dependent one (stream.layout_funcs)
        self.radiance = 2 if layout.view_terms else int(layout.is_radiance)
        self.robust = stream.ROBUST_NONE
        self.robust_scale = 0.0
        self.view_prior = None  # the view terms' ridge prior (set_view_prior): (centre, weights), one row each
        self.material_centre = self.material_weights = None  # the shared materials' prior (set_material_prior)
        if cfg.storage not in PRECISIONS:
            raise ConfigError(f"storage precision {cfg.storage!r} unknown", fix="use fp16, fp32 or fp64")
        self.accumulate = resolve_accumulate(cfg.accumulate, photos.n)
        """the accumulate precision in use ("fp32" or "fp64"; ``cfg.accumulate`` "auto" resolved)"""
        self.scalar, self.vec, self.mat = _vec_types(self.accumulate, layout.n_params)
        self.storage_dtype = PRECISIONS[cfg.storage]
        n = texels.n
        self.n = n
        self.one = self.scalar(1.0)
        self.like = self.vec()
        self.like_m = self.mat()
        dev = device
        self.pos = wp.array(texels.position, dtype=wp.vec3, device=dev)
        self.nrm = wp.array(texels.normal, dtype=wp.vec3, device=dev)
        self.tan = wp.array(texels.tangent, dtype=wp.vec3, device=dev)
        self.bit = wp.array(texels.bitangent, dtype=wp.vec3, device=dev)
        face_nrm = texels.normal if texels.face_normal is None else texels.face_normal
        jac = np.zeros((n, 3, 3), np.float32) if texels.normal_jacobian is None else texels.normal_jacobian
        self.tex = stream.TexelFrames()
        self.tex.pos, self.tex.nrm, self.tex.tan, self.tex.bit = self.pos, self.nrm, self.tan, self.bit
        self.tex.face_nrm = wp.array(np.ascontiguousarray(face_nrm, np.float32), dtype=wp.vec3, device=dev)
        self.tex.dn_dp = wp.array(np.ascontiguousarray(jac, np.float32), dtype=wp.mat33, device=dev)
        self._init_lookup(texels, layout, cfg, dev)
        self._init_taps(self.own_photos, cfg, dev)
        self.neighbors = wp.array(texels.neighbors, dtype=wp.vec4i, device=dev)
        # the other parts of split photos: the same texels over those photos, in this precision
        peer_cfg = dataclasses.replace(cfg, accumulate=self.accumulate)
        self.peers = [StreamProblem(texels, part, layout, peer_cfg, part.device) for part in (parts or [])[1:]]
        """one problem per other part of split photos (photo_split.py): they launch into their own partial
        sums, which this problem adds to its own; empty for a PhotoSet"""
        self._mirrors = {}  # this problem's copies of the first problem's arrays, when it is a peer
        self.set_groups(cfg.groups)
        self.no_diag = wp.zeros((1, 1), dtype=self.vec, device=dev)
        self.all_active = wp.ones(n, dtype=wp.int32, device=dev)
        self.no_direction = wp.zeros((1, 1), dtype=self.storage_dtype, device=dev)
        self.opt = stream.SampleOptions()
        self.opt.cos_light_min = float(cfg.cos_light_min)
        self.opt.cos_view_min = float(cfg.cos_view_min)
        self.opt.depth_tol = float(cfg.depth_tol)
        self.opt.shadow_tol = float(cfg.shadow_tol)
        if cfg.residual_space not in ("radiance", "reflectance"):
            raise ConfigError(f"residual_space {cfg.residual_space!r} unknown", fix="use radiance or reflectance")
        self.opt.reflectance_space = 1 if cfg.residual_space == "reflectance" else 0
        modes = {"bilinear": 0, "point": 1, "filtered": 2}  # stream.SAMPLING_*
        if cfg.photo_sampling not in modes:
            raise ConfigError(f"photo_sampling {cfg.photo_sampling!r} unknown", fix="use filtered, point or bilinear")
        self.opt.sampling = modes[cfg.photo_sampling]
        self.opt.robust_scale = 0.0
        if cfg.cuda_max_registers not in (-1, 0) and not 24 <= cfg.cuda_max_registers <= 255:
            raise ConfigError(f"cuda_max_registers {cfg.cuda_max_registers} invalid",
                              fix="use -1 (automatic), 0 (no cap) or 24 to 255")
        self.max_registers = cfg.cuda_max_registers
        if self.max_registers < 0:
            self.max_registers = 168 if layout.n_params <= 9 else 0
        if cfg.cuda_block_dim < 32 or cfg.cuda_block_dim > 1024 or cfg.cuda_block_dim % 32:
            raise ConfigError(f"cuda_block_dim {cfg.cuda_block_dim} invalid", fix="use a multiple of 32 from 32 to 1024")
        self.block_dim = cfg.cuda_block_dim
        self.passes = 0

    def set_robust_loss(self, kind: str, scale: float = 1.0) -> None:
        """The data term's loss per channel residual r: "none" (r^2 / 2, least squares), "huber" or
        "cauchy" with scale ``scale`` > 0 in residual units (photo values in radiance space), applied
        in the passes as iteratively reweighted least squares (fit/kernels/stream.py
        ``accumulate_kernel``; each loss compiles its own passes). The fit sets it from
        ``FitConfig.robust_loss``; a new problem starts with "none"."""
        if kind not in stream.ROBUST_LOSSES:
            raise ConfigError(f"robust loss {kind!r} unknown", fix=f"use one of {sorted(stream.ROBUST_LOSSES)}")
        code = stream.ROBUST_LOSSES[kind]
        if code != stream.ROBUST_NONE and not (math.isfinite(scale) and scale > 0):
            raise ConfigError(f"robust loss scale {scale} invalid", fix="use a positive scale in residual units")
        self.robust = code
        self.robust_scale = float(scale) if code != stream.ROBUST_NONE else 0.0
        self.opt.robust_scale = self.robust_scale
        for peer in self.peers:
            peer.set_robust_loss(kind, scale)

    def set_view_prior(self, weight: float, mean_sq: float | None = None) -> None:
        """The view-dependent radiance's ridge prior: lam / 2 sum_k a_k^2 per texel over its view-term
        coefficients (fit/models.py), with lam = ``weight`` x the photos' mean squared exposure so that
        ``weight`` counts in samples of the radiance-space residual (a sample's residual scales with its
        exposure; ``mean_sq``: that mean when this problem's photos are part of the fit's, e.g. a tile's).
        Added to every pass's objective, gradient, d^T H d, Jacobi diagonal and J^T J (the centred prior's
        kernels with one row for every texel, centre 0). No-op for other models."""
        if not (math.isfinite(weight) and weight >= 0):
            raise ConfigError(f"view prior {weight} invalid", fix="use a weight >= 0")
        lay = self.layout
        if not lay.view_terms:
            return
        if mean_sq is None:
            mean_sq = exposure_mean_square(self.photos)
        lam = float(weight) * mean_sq
        if lam <= 0:
            self.view_prior = None
            return
        w = np.zeros((1, lay.n_params))
        w[0, lay.view_offset(0):] = lam
        self.view_prior = (self.new_vec(np.zeros((1, lay.n_params))), self.new_vec(w))

    def set_material_prior(self, centre: np.ndarray | None, weights: np.ndarray | None = None) -> None:
        """The shared materials' prior (fit/materials.py): 1/2 sum_k w_ik (p_ik - c_ik)^2 per texel, a
        quadratic pull of each texel's parameters towards a centre of its own (its material's lobe)
        with weights of its own (zero on the columns it leaves free), both (N, n_params), in objective
        units per squared parameter unit. Added to every pass's objective, gradient, d^T H d, Jacobi
        diagonal and J^T J, on the device. ``None`` removes it."""
        if centre is None:
            self.material_centre = self.material_weights = None
            return
        c = np.asarray(centre, np.float64)
        w = np.asarray(weights, np.float64)
        shape = (self.n, self.layout.n_params)
        if c.shape != shape or w.shape != shape:
            raise ConfigError(f"material prior centre {c.shape} and weights {w.shape} must both be {shape}")
        if not (np.isfinite(c).all() and np.isfinite(w).all() and (w >= 0).all()):
            raise ConfigError("material prior has non-finite centres or negative weights",
                              fix="report this with the command that made it")
        self.material_centre = self.new_vec(c)
        self.material_weights = self.new_vec(w)

    def _add_prior(self, params, f, g, act, direction=None, dhd=None, jtj=None, diag=None) -> None:
        want = direction is not None and dhd is not None
        priors = [(self.material_centre, self.material_weights)] if self.material_centre is not None else []
        if self.view_prior is not None:
            priors.append(self.view_prior)
        for centre, weights in priors:
            wp.launch(K.centred_prior_kernel, dim=self.n, device=self.device,
                      inputs=[params, direction if want else self.no_direction, centre, weights, act,
                              self.layout.n_params, int(want), int(diag is not None)],
                      outputs=[f, g, dhd if want else f, diag if diag is not None else g])
            if jtj is not None:
                wp.launch(K.centred_prior_diag_kernel, dim=self.n, device=self.device,
                          inputs=[weights, act, self.layout.n_params], outputs=[jtj])

    def _init_lookup(self, texels: TexelSet, layout: ModelLayout, cfg: StreamConfig, dev: str) -> None:
        """The renderer's texture lookup (``StreamConfig.model_lookup``): texel coordinates and
        their gradients, the atlas's read map and the held parameters (placeholders when off)."""
        if cfg.model_lookup not in ("texel", "bilinear"):
            raise ConfigError(f"model_lookup {cfg.model_lookup!r} unknown", fix="use texel or bilinear")
        self.lookup = cfg.model_lookup == "bilinear"
        tex, n = self.tex, texels.n
        tex.grid_width, tex.grid_height = int(texels.width), int(texels.height)
        tex.n_lobes, tex.anisotropic = int(layout.n_lobes), int(layout.anisotropic)
        if self.lookup and layout.view_terms:
            raise ConfigError("model_lookup bilinear does not blend the view-dependent radiance's view terms",
                              fix="set stream.model_lookup to texel")
        if not self.lookup:
            tex.centre_xy = wp.zeros(1, dtype=wp.vec2, device=dev)
            tex.dx_dp = tex.dy_dp = wp.zeros(1, dtype=wp.vec3, device=dev)
            tex.grid_source = wp.zeros(1, dtype=wp.int32, device=dev)
            tex.lookup_params = wp.zeros((1, layout.n_params), dtype=wp.float32, device=dev)
            return
        if cfg.photo_sampling != "filtered":
            raise ConfigError(f"model_lookup bilinear needs filtered photo sampling, not {cfg.photo_sampling!r}",
                              fix="set photo_sampling to filtered or model_lookup to texel")
        if texels.coordinate_gradients is None or texels.grid_source is None or min(texels.width, texels.height) < 2:
            raise ConfigError("model_lookup bilinear needs an atlas (texel coordinate gradients and padding "
                              "sources; single-view fits have none)", fix="set model_lookup to texel")
        ys, xs = np.divmod(np.asarray(texels.grid_index, np.int64), texels.width)
        tex.centre_xy = wp.array(np.stack([xs, ys], 1).astype(np.float32), dtype=wp.vec2, device=dev)
        grads = np.ascontiguousarray(texels.coordinate_gradients, np.float32)
        tex.dx_dp = wp.array(np.ascontiguousarray(grads[:, 0]), dtype=wp.vec3, device=dev)
        tex.dy_dp = wp.array(np.ascontiguousarray(grads[:, 1]), dtype=wp.vec3, device=dev)
        source = np.asarray(texels.grid_source, np.int64)
        tex.grid_source = wp.array(np.where(source >= 0, source, n).astype(np.int32), dtype=wp.int32, device=dev)
        held = np.tile(layout.defaults().astype(np.float32), (n + 1, 1))  # row n: the defaults
        tex.lookup_params = wp.array(held, dtype=wp.float32, device=dev)

    def _init_taps(self, photos: PhotoSet, cfg: StreamConfig, dev: str) -> None:
        """The filtered taps' geometry (``StreamConfig.tap_geometry``): the mesh they are traced to
        (placeholders for the face plane)."""
        if cfg.tap_geometry not in ("plane", "mesh"):
            raise ConfigError(f"tap_geometry {cfg.tap_geometry!r} unknown", fix="use plane or mesh")
        self.traced = cfg.tap_geometry == "mesh"
        tex = self.tex
        if not self.traced:
            tex.mesh = wp.uint64(0)
            tex.mesh_points = tex.mesh_normals = wp.zeros(1, dtype=wp.vec3, device=dev)
            tex.mesh_indices = wp.zeros(1, dtype=wp.int32, device=dev)
            tex.mesh_uvs = wp.zeros(1, dtype=wp.vec2, device=dev)
            tex.shadow_eps = 0.0
            tex.shadow_rays = 0
            return
        if cfg.photo_sampling != "filtered":
            raise ConfigError(f"tap_geometry mesh needs filtered photo sampling, not {cfg.photo_sampling!r}",
                              fix="set photo_sampling to filtered or tap_geometry to plane")
        if photos.mesh_normals is None or photos.mesh_uvs is None:
            raise ConfigError("tap_geometry mesh needs a mesh with normals and UVs (single-view fits have none)",
                              fix="set tap_geometry to plane")
        tex.mesh = photos.mesh.id
        tex.mesh_points, tex.mesh_indices = photos.mesh.points, photos.mesh.indices
        tex.mesh_normals, tex.mesh_uvs = photos.mesh_normals, photos.mesh_uvs
        tex.shadow_eps = float(photos.shadow_eps)
        tex.shadow_rays = int(cfg.shadow_map_size > 0)

    def refresh_lookup(self, params: wp.array, relaxation: float = 1.0) -> None:
        """Hold the neighbours of the renderer's lookup at ``params`` (N, n_params, storage
        precision) until the next call, or move the held values ``relaxation`` of the way there
        (``FitConfig.lookup_relaxation``); on the device, no host round trip. No-op when off."""
        if self.lookup:
            wp.launch(stream.hold_lookup_params_kernel, dim=(self.n, self.layout.n_params), device=self.device,
                      inputs=[params, float(relaxation)], outputs=[self.tex.lookup_params])
            # a buffer of its own on the peer: the passes' "params" buffer is rewritten every pass
            for peer, mirrored in zip(self.peers, self._to_peers(lookup_params=params)):
                peer.refresh_lookup(mirrored["lookup_params"], relaxation)

    def set_groups(self, groups: int) -> None:
        """Split each pass's photos into ``groups`` groups, one thread per (group, texel); 0 picks
        one group on the CPU and enough for ~262k GPU threads. Reallocates the per-group partials
        (with split photos, ``groups`` per device: the peers' rows follow this problem's own)."""
        n, dev = self.n, self.device
        window = self.own_photos.window
        if groups <= 0:
            groups = 1 if dev == "cpu" else max(1, min(window, math.ceil(262144 / max(n, 1))))
        self.groups = groups
        self.per_group = math.ceil(window / groups)
        self.rows = groups * (1 + len(self.peers))
        """partial-sum rows a pass reduces: this problem's groups, then each peer's"""
        self.pf = wp.zeros((self.rows, n), dtype=self.scalar, device=dev)
        self.pg = wp.zeros((self.rows, n), dtype=self.vec, device=dev)
        self.ph = wp.zeros((self.rows, n), dtype=self.scalar, device=dev)
        self.pst = wp.zeros((self.rows, n), dtype=wp.vec4d, device=dev)
        self.pm = None  # per-group J^T J (LM), allocated on first request
        self.pdiag = None  # per-group Gauss-Newton diagonals, allocated on first request
        for peer in self.peers:
            peer.set_groups(groups)

    def new_storage(self, values: np.ndarray | None = None) -> wp.array:
        """A (N, n_params) parameter array in the storage precision."""
        a = np.zeros((self.n, self.layout.n_params)) if values is None else np.asarray(values)
        return wp.array(np.ascontiguousarray(a), dtype=self.storage_dtype, device=self.device)

    def new_vec(self, values: np.ndarray | None = None) -> wp.array:
        """A (N,) array of n_params-long parameter vectors in the compute precision."""
        if values is None:
            return wp.zeros(self.n, dtype=self.vec, device=self.device)
        return wp.array(np.ascontiguousarray(values, dtype=np.float64), dtype=self.vec, device=self.device)

    def new_scalar(self, fill: float = 0.0) -> wp.array:
        a = wp.zeros(self.n, dtype=self.scalar, device=self.device)
        if fill:
            a.fill_(fill)
        return a

    def evaluate(self, params: wp.array, f: wp.array, g: wp.array, stats: wp.array, *,
                 direction: wp.array | None = None, dhd: wp.array | None = None,
                 active: wp.array | None = None, full_hessian: bool = False,
                 diag: wp.array | None = None) -> None:
        """One streaming pass: f, g (and d^T H d along ``direction`` into ``dhd``) per texel.

        ``params`` and ``direction`` are (N, n_params) arrays; texels whose ``active`` flag is 0
        are skipped (their outputs are zero). ``diag`` (an (N,) parameter-vector array, optional)
        receives the Gauss-Newton diagonal diag(J^T J) of the data term (Jacobi preconditioner).
        """
        lay = self.layout
        # arguments normalised so one pass kind maps to one cached (compiled) kernel
        kernel = stream.accumulate_kernel(lay.n_lobes, int(lay.anisotropic), bool(self.cfg.kahan), diag is not None,
                                          direction is not None, bool(full_hessian and direction is not None),
                                          self.max_registers, self.lookup, self.traced, self.radiance, self.robust)
        if direction is not None and direction.dtype != params.dtype:
            raise ConfigError("direction and parameters must share a dtype")
        h_out = dhd if dhd is not None else self.ph_scratch()

        def launch(pr: StreamProblem, inputs: dict, window) -> None:
            images, depth, shadow, infos, b, e = window
            if diag is not None and pr.pdiag is None:
                pr.pdiag = wp.zeros((pr.rows, pr.n), dtype=pr.vec, device=pr.device)
            dirn = inputs["direction"] if inputs["direction"] is not None else pr.no_direction
            act = inputs["active"] if inputs["active"] is not None else pr.all_active
            wp.launch(kernel, dim=(pr.groups, pr.n), device=pr.device, block_dim=pr.block_dim,
                      inputs=[pr.tex, inputs["params"], dirn, act, images, depth, shadow, infos, b, e,
                              math.ceil((e - b) / pr.groups), pr.opt, pr.like, pr.one],
                      outputs=[pr.pf, pr.pg, pr.ph, pr.pst, pr.pdiag if diag is not None else pr.no_diag])

        partials = ["pf", "pg", "ph", "pst"] + (["pdiag"] if diag is not None else [])
        first = True
        for rows in self._launch_passes(launch, partials, params=params, direction=direction, active=active):
            wp.launch(stream.reduce_partials_kernel, dim=self.n, device=self.device,
                      inputs=[self.pf, self.pg, self.ph, self.pst, rows, 0 if first else 1],
                      outputs=[f, g, h_out, stats])
            if diag is not None:
                wp.launch(stream.reduce_vec_partials_kernel, dim=self.n, device=self.device,
                          inputs=[self.pdiag, rows, 0 if first else 1], outputs=[diag])
            first = False
        act = self.all_active if active is None else active
        self._add_prior(params, f, g, act, direction, dhd, diag=diag)
        self.passes += 1

    def _launch_passes(self, launch, partials: list[str], **inputs):
        """Launch a pass's accumulation over every photo: per window of this problem's photos, yields the
        number of partial-sum rows to reduce after ``launch(problem, inputs, window)`` has filled them.
        With split photos (one window per device): every peer's launch on its device with ``inputs``
        copied there, this problem's own, then the peers' ``partials`` rows copied after its own."""
        if not self.peers:
            for window in self.own_photos.windows():
                launch(self, inputs, window)
                yield self.groups
            return
        for peer, mirrored in zip(self.peers, self._to_peers(**inputs)):
            launch(peer, mirrored, next(iter(peer.own_photos.windows())))
        launch(self, inputs, next(iter(self.own_photos.windows())))
        self._gather_from_peers(partials, self.groups * self.n)
        yield self.rows

    def _same_device(self, peer: "StreamProblem") -> bool:
        """Whether ``peer`` reads this problem's arrays where they are (its device is this one)."""
        return peer.device == self.device

    def _to_peers(self, **arrays) -> list[dict]:
        """Per peer, ``arrays`` (this device's; None passes through) as that peer reads them: the same arrays
        on the same device, else copies on its device. A copy runs on this (the source) device's stream,
        after the work that wrote the array, and this device is synchronised before the peers' launches
        read it (the tiles' halo exchange, fit/tiles.py, orders its copies by host synchronisations too)."""
        out, copied = [], False
        for peer in self.peers:
            if self._same_device(peer):
                out.append(dict(arrays))
                continue
            mirrored = {}
            for name, a in arrays.items():
                if a is not None:
                    buf = peer._mirrors.get(name)
                    if buf is None or buf.shape != a.shape or buf.dtype != a.dtype:
                        buf = peer._mirrors[name] = wp.empty(a.shape, dtype=a.dtype, device=peer.device)
                        wp.synchronize_device(peer.device)  # allocated on the peer's stream: ready for another's
                    wp.copy(buf, a, stream=_stream_of(self.device))
                    copied = True
                    a = buf
                mirrored[name] = a
            out.append(mirrored)
        if copied:
            wp.synchronize_device(self.device)
        return out

    def _from_peer(self, peer: "StreamProblem", pairs, count: int, offset: int) -> None:
        """Copy ``count`` elements of each (peer's array, this problem's array) in ``pairs`` to this one's
        element ``offset``, ahead of this device's launches that read them: from another device on that
        device's stream (after its launches that wrote them), once this device's queued work is done (its
        arrays written), then that device synchronised."""
        if self._same_device(peer):
            for theirs, mine in pairs:
                wp.copy(mine, theirs, offset, 0, count)
            return
        wp.synchronize_device(self.device)
        for theirs, mine in pairs:
            wp.copy(mine, theirs, offset, 0, count, stream=_stream_of(peer.device))
        wp.synchronize_device(peer.device)

    def _gather_from_peers(self, names: list[str], count: int) -> None:
        """Each peer's first ``count`` elements of the partial arrays ``names`` after this problem's own (peer
        k's into rows k x groups on)."""
        for k, peer in enumerate(self.peers, 1):
            self._from_peer(peer, [(getattr(peer, name), getattr(self, name)) for name in names], count, k * count)

    def split_initial_guess(self, kernel, rank: int, low: wp.array, high: wp.array, count: wp.array) -> None:
        """fitter.initial_guess's pass over split photos: each device's 4 smallest samples per channel,
        largest and count, merged on this device (``low``, ``high``, ``count``: the one-pass values)."""
        parts, n = 1 + len(self.peers), self.n
        lists = wp.zeros((parts, n), dtype=wp.mat44, device=self.device)
        highs = wp.zeros((parts, n), dtype=wp.vec3, device=self.device)
        counts = wp.zeros((parts, n), dtype=wp.int32, device=self.device)
        for k, pr in enumerate([self, *self.peers]):
            images, depth, shadow, infos, b, e = next(iter(pr.own_photos.windows()))
            if pr is self:
                out = [low, highs[0], counts[0], lists[0]]
            else:
                out = [wp.zeros(n, dtype=wp.vec3, device=pr.device), wp.zeros(n, dtype=wp.vec3, device=pr.device),
                       wp.zeros(n, dtype=wp.int32, device=pr.device), wp.zeros(n, dtype=wp.mat44, device=pr.device)]
            wp.launch(kernel, dim=n, device=pr.device,
                      inputs=[pr.tex, images, depth, shadow, infos, b, e, pr.opt, rank, 1], outputs=out)
            if pr is not self:
                pr._part_guess = out  # kept until the next call: this device's copies read them after this returns
        for k, peer in enumerate(self.peers, 1):
            _, hi, cnt, sm = peer._part_guess
            self._from_peer(peer, [(sm, lists), (hi, highs), (cnt, counts)], n, k * n)
        wp.launch(stream.merge_smallest_kernel, dim=n, device=self.device,
                  inputs=[lists, highs, counts, parts, rank], outputs=[low, high, count])

    def ph_scratch(self) -> wp.array:
        if not hasattr(self, "_h_scratch"):
            self._h_scratch = self.new_scalar()
        return self._h_scratch

    def evaluate_lm(self, params: wp.array, f: wp.array, g: wp.array, jtj: wp.array, stats: wp.array, *,
                    active: wp.array | None = None) -> None:
        """One streaming pass accumulating f, J^T r and J^T J per texel (Gauss-Newton / LM)."""
        lay = self.layout
        kernel = stream.accumulate_lm_kernel(lay.n_lobes, int(lay.anisotropic), self.max_registers, self.lookup,
                                             self.traced, self.radiance, self.robust)

        def launch(pr: StreamProblem, inputs: dict, window) -> None:
            images, depth, shadow, infos, b, e = window
            if pr.pm is None:
                pr.pm = wp.zeros((pr.rows, pr.n), dtype=pr.mat, device=pr.device)
            act = inputs["active"] if inputs["active"] is not None else pr.all_active
            wp.launch(kernel, dim=(pr.groups, pr.n), device=pr.device, block_dim=pr.block_dim,
                      inputs=[pr.tex, inputs["params"], act, images, depth, shadow, infos, b, e,
                              math.ceil((e - b) / pr.groups), pr.opt, pr.like, pr.like_m, pr.one],
                      outputs=[pr.pf, pr.pg, pr.pm, pr.pst])

        first = True
        for rows in self._launch_passes(launch, ["pf", "pg", "pm", "pst"], params=params, active=active):
            wp.launch(stream.reduce_partials_kernel, dim=self.n, device=self.device,
                      inputs=[self.pf, self.pg, self.pm, self.pst, rows, 0 if first else 1],
                      outputs=[f, g, jtj, stats])
            first = False
        act = self.all_active if active is None else active
        self._add_prior(params, f, g, act, jtj=jtj)
        self.passes += 1
