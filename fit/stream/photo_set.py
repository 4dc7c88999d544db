"""The photos of a streaming fit where its passes read them (:class:`PhotoSet`), and their upload.

Photos live on the device, in (pinned) host memory uploaded a window per pass, or on disk decoded a
window per pass; their depth and shadow maps beside them. :func:`upload_photo_sets` fills the device
photos of one set or of one set per device (the photo split) through one pipeline of pinned buffers.
Imports only numpy and warp (plus numpy-only spine modules).
"""

from __future__ import annotations

import collections
import concurrent.futures
import contextlib
import sys
import threading
import time

import numpy as np
import warp as wp

from texstream.core.errors import ConfigError, InputError
from texstream.core.progress import say

from texstream.render.shading import SHADOW_EPS_REL
from texstream.render.visibility import depth_maps_kernel, masked_depth_kernel, shadow_maps_kernel
from texstream.fit.stream.config import StreamConfig
from texstream.fit.stream.photo_stream import (PhotoCache, PhotoFiles, PhotoLoader, WindowSlots, choose_residency,
                                               crop_boxes, keep_maps_on_device, to_half_kernel, wait, window_size)
from texstream.render.camera import ImageInfo, PhotoFrame, crop_infos, image_infos, struct_array

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


def gather_rows(src: wp.array, rows: np.ndarray) -> wp.array:
    """Rows ``rows`` of a contiguous (n, ...) array, in that order, as a new array on its device: one copy per run
    of consecutive rows, on the device (a subset of the photos for a validation split: no trip through the
    host, which for the full ornament's 1,540 photos and their maps, 4 GiB each way, took 5.1 s of the
    materials choice's 18 s on an H200)."""
    per = int(np.prod(src.shape[1:], dtype=np.int64))
    out = wp.empty((len(rows), *src.shape[1:]), dtype=src.dtype, device=src.device)
    cuts = [0, *(np.flatnonzero(np.diff(rows) != 1) + 1).tolist(), len(rows)]
    for a, b in zip(cuts[:-1], cuts[1:]):
        wp.copy(out, src, a * per, int(rows[a]) * per, (b - a) * per)
    return out


class PhotoSet:
    """Photos, depth maps and shadow maps where the passes read them: on the device, in (pinned)
    host memory uploaded a window per pass, or decoded from the capture's files a window per pass
    (``residency``; ``StreamConfig.photo_residency``). Set-up makes no host round trip per photo:
    per-photo constants in one array, photos uploaded in chunks through pinned buffers, depth and
    shadow maps in one launch over photos x pixels (fit/stream/photo_stream.py)."""

    def __init__(self, frames: list[PhotoFrame], images, mesh_points: np.ndarray | None,
                 mesh_faces: np.ndarray | None, masks: list[np.ndarray | None] | None = None,
                 config: StreamConfig | None = None, device: str = "cpu", mesh_normals: np.ndarray | None = None,
                 mesh_uvs: np.ndarray | None = None, defer_upload: bool = False):
        """``images``: a list of (H, W, >=3) linear arrays, or a :class:`~texstream.fit.stream.photo_stream.PhotoFiles`
        to read them from (masks then come from its mask paths). ``mesh_points=None`` (no geometry:
        single-view fits, fit/common/single_view.py) builds no depth or shadow maps: each photo's depth
        map holds its mask (1 = sample, 0 = masked) and ``ImageInfo.depth_is_mask`` tells the kernels
        to test only that. Per-vertex ``mesh_normals`` and ``mesh_uvs`` serve traced taps
        (``StreamConfig.tap_geometry``).

        ``timings`` records the set-up's phases in seconds (upload, depth_maps, shadow_maps, other;
        each phase ends with a device synchronisation so the figures are its own).

        ``defer_upload`` (photos resident on the device): the device buffers only, with the loader kept
        open; :func:`upload_photo_sets` fills them together with other devices' sets (the photo split)."""
        self.mesh_normals = self.mesh_uvs = None
        self.frames = list(frames)
        """the photos' :class:`PhotoFrame`s (a tile's actor builds its own set from them, fit/multi/tiles_ray.py)"""
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
        """the mesh as given (another process builds the same set from them, fit/multi/tiles_ray.py)"""
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
        photos judged on the rest (fit/models/materials.py), or a tile's photos (fit/multi/tiles.py). Photos held on
        the device are copied there (:func:`gather_rows`); photos held on the host, one copy there.
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
        if not self.streamed:  # photos on the device: copied there, run by run, the same bytes as through the host
            out.images, out.depth, out.shadow = (gather_rows(a, idx) if dev == self.device else
                                                 wp.clone(gather_rows(a, idx), device=dev)
                                                 for a in (self.images, self.depth, self.shadow))
            out.image_bytes = self.image_bytes // self.n * out.n
            return out
        src = (self.host_images, self.host_depth, self.host_shadow)
        images, depth, shadow = (np.ascontiguousarray(a.numpy()[idx]) for a in src)
        # the window buffers are shared: the two sets are never streamed at once
        pinned = dev != "cpu"
        out.host_images = wp.array(images, dtype=self.images.dtype, device="cpu", pinned=pinned)
        out.host_depth = wp.array(depth, dtype=wp.float32, device="cpu", pinned=pinned)
        out.host_shadow = wp.array(shadow, dtype=wp.float32, device="cpu", pinned=pinned)
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
