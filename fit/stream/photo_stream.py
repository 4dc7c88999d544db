"""Getting photos to the passes: per-photo constants in one array, crops to the object, batched
depth and shadow maps, chunked uploads, and photos decoded from disk in windows.

:class:`texstream.fit.stream.problem.PhotoSet` holds the photos where the passes read them; this module
holds what it builds them with, so that its set-up makes no host round trip per photo:

- :func:`texstream.render.camera.image_infos` fills every photo's :class:`~texstream.render.camera.ImageInfo`
  (camera, light, shadow camera, crop) in one numpy structured array, uploaded in one copy;
- :func:`crop_boxes` finds each photo's footprint of the object (the bounding box of the mesh's
  projection, one launch over photos x vertices); a photo is stored cropped to it and its camera
  becomes the crop's (principal point shifted, size the crop's), so the passes, depth maps and
  traced taps need no change and read only pixels a texel can see;
- :class:`PhotoFiles` names the capture's image files and how to decode them (the caller passes
  :mod:`texstream.capture.imageio`'s readers, so this module never imports OpenImageIO);
- :class:`PhotoLoader` fills (photos, mask) slots of a buffer from images in memory or from files,
  on a pool of threads (numpy copies and most of decoding release the GIL), files on machines with many
  cores by worker processes (:mod:`texstream.fit.stream.decode_pool`);
- :func:`choose_residency` picks where the photos live from the memory available.

Imports only numpy, warp and the standard library.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import contextvars
import dataclasses
import os
import queue
import threading
from collections.abc import Callable, Iterator, Sequence

import numpy as np
import warp as wp

from texstream.core.devices import available_memory_bytes
from texstream.core.progress import say
from texstream.fit.stream import decode_pool
from texstream.render.camera import ImageInfo

RESIDENCIES = ("device", "host", "disk")
"""where a PhotoSet keeps its photos: all on the device; all in (pinned) host memory, uploaded a
window per pass; or only a window at a time, decoded from the capture's files each pass"""

CROP_MARGIN_PX = 3
"""pixels kept around the mesh's projected bounding box: a sample's bilinear taps lie within 1 px
of its projection and a filtered tap's ray within 1.5 px (fit/kernels/stream.py ``observe``), so
every pixel a texel can read stays inside the crop; pixels outside it see no surface (depth 0) and
were rejected anyway"""

FILE_DECODE_THREADS = 4
"""default threads decoding photos from files (at most the CPU count): OpenEXR spreads each read over the
cores itself, so more readers only contend for Python's lock; 4 beat 8 on 16-core GPU hosts (docs/scale.md)"""

ARRAY_COPY_THREADS = 4
"""default threads cropping photos given as arrays into the upload buffers (at most the CPU count): beside
the thread issuing the copies, more croppers only contend for Python's lock; 4 beat 8 and 12 on a 32-core
two-GPU host (docs/scale.md)"""

@dataclasses.dataclass
class PhotoFiles:
    """The photos as files, read on demand (``StreamConfig.photo_residency`` "disk").

    Attributes:
        paths: one image file per photo, in the frames' order.
        mask_paths: per photo its mask file or None.
        read_image: (path, rows=None, size=None) -> (H, W, 3) float32 linear image, only rows
            (y0, y1) when given, after checking the header's size against ``size`` (H, W) (e.g.
            ``capture.imageio.read_image``).
        read_mask: (path, (H, W), rows=None) -> (H, W) bool, likewise (e.g. ``capture.imageio.read_mask``).
    """

    paths: Sequence
    mask_paths: Sequence
    read_image: Callable
    read_mask: Callable
    cache_dir: object = None
    """folder for the decoded photos' cache (:class:`PhotoCache`; e.g. ``CAPTURE/.texstream-cache``); None:
    none"""

    def __len__(self) -> int:
        return len(self.paths)

    def subset(self, indices) -> "PhotoFiles":
        """The photos ``indices`` (in that order), same readers and cache folder."""
        return PhotoFiles([self.paths[k] for k in indices], [self.mask_paths[k] for k in indices],
                          self.read_image, self.read_mask, self.cache_dir)


@wp.kernel
def _projected_bounds_kernel(points: wp.array(dtype=wp.vec3), infos: wp.array(dtype=ImageInfo),
                             bounds: wp.array2d(dtype=wp.int32)):
    """Per photo, floor(min) and floor(max) of the mesh vertices' projections (pixel units) into
    bounds[k, 0:4] (x min, y min, x max, y max) and 1 in bounds[k, 4] when a vertex lies at or
    behind the camera plane (its projection bounds nothing). Integer min/max: deterministic."""
    k, v = wp.tid()
    pc = infos[k].rot @ points[v] + infos[k].trans
    if pc[2] <= 1.0e-6 * wp.length(pc):
        wp.atomic_max(bounds, k, 4, 1)
        return
    u = infos[k].fx * pc[0] / pc[2] + infos[k].cx
    w = infos[k].fy * pc[1] / pc[2] + infos[k].cy
    # clamped so a vertex far outside the frame cannot overflow the int conversion
    xi = int(wp.floor(wp.clamp(u, -1.0e6, 1.0e6)))
    yi = int(wp.floor(wp.clamp(w, -1.0e6, 1.0e6)))
    wp.atomic_min(bounds, k, 0, xi)
    wp.atomic_min(bounds, k, 1, yi)
    wp.atomic_max(bounds, k, 2, xi)
    wp.atomic_max(bounds, k, 3, yi)


@wp.kernel
def to_half_kernel(src: wp.array3d(dtype=wp.vec3), first: int, dst: wp.array3d(dtype=wp.vec3h)):
    """dst[first + i] = src[i] in half floats (round to nearest even)."""
    i, y, x = wp.tid()
    dst[first + i, y, x] = wp.vec3h(src[i, y, x])


def crop_boxes(points: wp.array, infos: wp.array, widths: np.ndarray, heights: np.ndarray,
               device: str) -> np.ndarray:
    """(n, 4) int64 (x0, y0, width, height) per photo: the bounding box of the mesh's projection
    grown by :data:`CROP_MARGIN_PX` and clipped to the photo (the whole photo when a vertex lies
    behind the camera; a 1 x 1 box at the origin when the object is out of frame)."""
    n = len(widths)
    init = np.tile(np.array([2 ** 31 - 1, 2 ** 31 - 1, -2 ** 31, -2 ** 31, 0], np.int32), (n, 1))
    bounds = wp.array(init, dtype=wp.int32, device=device)
    wp.launch(_projected_bounds_kernel, dim=(n, points.shape[0]), device=device, inputs=[points, infos, bounds])
    b = bounds.numpy().astype(np.int64)
    w, h = np.asarray(widths, np.int64), np.asarray(heights, np.int64)
    x0 = np.clip(b[:, 0] - CROP_MARGIN_PX, 0, w)
    y0 = np.clip(b[:, 1] - CROP_MARGIN_PX, 0, h)
    x1 = np.clip(b[:, 2] + 1 + CROP_MARGIN_PX, 0, w)
    y1 = np.clip(b[:, 3] + 1 + CROP_MARGIN_PX, 0, h)
    behind = b[:, 4] > 0
    x0[behind], y0[behind], x1[behind], y1[behind] = 0, 0, w[behind], h[behind]
    empty = (x1 <= x0) | (y1 <= y0)
    x0[empty], y0[empty], x1[empty], y1[empty] = 0, 0, 1, 1
    return np.stack([x0, y0, x1 - x0, y1 - y0], axis=1)


CACHE_KEEP = 2
"""photo caches kept per cache folder (the most recently used; a capture fitted with another mesh has other
crops, hence another cache)"""

CACHE_SPARE_BYTES = 1 << 30
"""free disk space a new photo cache leaves on its disk"""


def _alive(pid: int) -> bool:
    """Whether process ``pid`` runs (on this machine)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:
        return True  # it exists, owned by someone else
    return True


class PhotoCache:
    """The photos of a :class:`PhotoFiles` as a window slot holds them (cropped, zero padded to (hmax, wmax),
    in the image precision) and their masks, in one raw file: photos streamed from disk are decoded once, in
    the first pass, and every later pass (and a later fit of the same capture, crops and precision) reads
    them from the file (the page cache when it fits in memory) straight into the slots instead of decoding
    them again. The same bytes as decoding: fits give the same parameters to the bit. Reads and writes are
    positioned (pread / pwrite from the loader's threads), not a memory map, so the page cache does not
    count in the fit's resident memory.

    The file is ``FOLDER/photos-KEY.bin``, KEY a hash of the image and mask paths, sizes and modification
    times, the crops and the precision, so an edited photo or another mesh (other crops) makes another
    cache. It is written to a temporary name and renamed when every photo is in it; at most
    :data:`CACHE_KEEP` caches stay in a folder (the oldest go). Nothing is cached when the folder cannot
    be written or the disk lacks room (the fit decodes as before)."""

    def __init__(self, files: PhotoFiles, crops: np.ndarray | None, hmax: int, wmax: int, dtype,
                 has_masks: bool):
        import hashlib
        import json
        from pathlib import Path

        self.folder = Path(files.cache_dir)
        self.n, self.dtype, self.has_masks = len(files), np.dtype(dtype), bool(has_masks)
        self.slot_shape, self.mask_slot_shape = (hmax, wmax, 3), (hmax, wmax)
        self.photo_bytes = hmax * wmax * 3 * self.dtype.itemsize
        self.mask_bytes = hmax * wmax if self.has_masks else 0
        self.image_bytes = self.n * self.photo_bytes
        self.nbytes = self.image_bytes + self.n * self.mask_bytes

        def stamp(p):
            if p is None:
                return None
            st = os.stat(p)
            return [os.path.abspath(p), st.st_size, st.st_mtime_ns]

        key = json.dumps({"images": [stamp(p) for p in files.paths],
                          "masks": [stamp(p) for p in files.mask_paths],
                          "crops": None if crops is None else np.asarray(crops).tolist(),
                          "shape": [hmax, wmax], "dtype": self.dtype.str,
                          # a reader that resamples (a pyramid level, fit/common/photo_levels.py) names itself
                          "reader": getattr(files.read_image, "cache_key", None)}, sort_keys=True)
        self.path = self.folder / f"photos-{hashlib.sha256(key.encode()).hexdigest()[:20]}.bin"
        self.fd = None
        self.writing = False
        self.ready = self.path.is_file() and self.path.stat().st_size == self.nbytes
        if self.ready:
            try:
                self.fd = os.open(self.path, os.O_RDONLY)
                os.utime(self.path)  # most recently used: kept when another cache is written
            except OSError:
                self.ready = False

    def __del__(self):
        self.close()

    def close(self) -> None:
        if self.fd is not None:
            os.close(self.fd)
            self.fd = None

    def read(self, k: int, img: np.ndarray, msk: np.ndarray | None) -> None:
        """Photo k into its slot ``img`` and mask slot ``msk`` (on the loader's threads)."""
        _read_exactly(self.fd, img, k * self.photo_bytes, self.dtype, self.slot_shape)
        if msk is not None:
            if self.has_masks:
                _read_exactly(self.fd, msk, self.image_bytes + k * self.mask_bytes, np.uint8,
                              self.mask_slot_shape)
            else:
                msk[...] = 1

    def start_writing(self) -> str | None:
        """Open a temporary file for the photos (filled by :meth:`store`). Returns None, or why no cache
        is written."""
        import shutil

        try:
            self.folder.mkdir(parents=True, exist_ok=True)
            for stale in self.folder.glob("photos-*.bin.tmp*"):  # left by a fit that was killed while writing
                pid = stale.name.rsplit(".tmp", 1)[-1]
                if not (pid.isdigit() and _alive(int(pid))):
                    stale.unlink(missing_ok=True)
            if shutil.disk_usage(self.folder).free < self.nbytes + CACHE_SPARE_BYTES:
                return (f"{self.nbytes / 2 ** 30:.2f} GiB would not leave {CACHE_SPARE_BYTES >> 30} GiB free "
                        "there")
            self.tmp = self.path.with_name(f"{self.path.name}.tmp{os.getpid()}")
            self.fd = os.open(self.tmp, os.O_RDWR | os.O_CREAT | os.O_TRUNC, 0o644)
            os.ftruncate(self.fd, self.nbytes)
        except OSError as e:
            self.close()
            return f"{self.folder} cannot be written ({e.strerror or e})"
        self.written = np.zeros(self.n, bool)
        self.writing = True
        return None

    def store(self, k: int, img: np.ndarray, msk: np.ndarray | None) -> None:
        """Photo k as its slot holds it (on the loader's threads: positioned writes of disjoint ranges)."""
        _write_exactly(self.fd, img, k * self.photo_bytes, self.dtype)
        if self.has_masks:
            _write_exactly(self.fd, msk, self.image_bytes + k * self.mask_bytes, np.uint8)
        self.written[k] = True

    def finish(self) -> bool:
        """Once every photo is stored: rename the file into place (older caches beyond :data:`CACHE_KEEP`
        removed) and read from it from now on. Returns whether the cache is ready."""
        if not self.writing or not self.written.all():
            return self.ready
        try:
            os.replace(self.tmp, self.path)  # the descriptor stays open on the renamed file
            self.ready, self.writing = True, False
            caches = sorted(self.folder.glob("photos-*.bin"), key=lambda p: p.stat().st_mtime, reverse=True)
            for old in caches[CACHE_KEEP:]:
                old.unlink(missing_ok=True)
        except OSError:
            self.abandon()
        return self.ready

    def abandon(self) -> None:
        """Stop writing (a fit that ends before a full pass): the temporary file is removed."""
        if self.writing:
            self.writing = False
            self.close()
            try:
                self.tmp.unlink(missing_ok=True)
            except OSError:
                pass


def _read_exactly(fd: int, dst: np.ndarray, offset: int, dtype, shape) -> None:
    """Fill ``dst`` ((shape) of ``dtype``) from the file at ``offset`` (through a temporary when ``dst`` is
    not a contiguous array of that type)."""
    direct = dst.dtype == dtype and dst.flags.c_contiguous and dst.shape == tuple(shape)
    buf = dst if direct else np.empty(shape, dtype)
    view = memoryview(buf.reshape(-1).view(np.uint8))
    done = 0
    while done < view.nbytes:
        got = os.preadv(fd, [view[done:]], offset + done)
        if got <= 0:
            raise OSError(f"photo cache ended early at byte {offset + done}")
        done += got
    if not direct:
        dst[...] = buf


def _write_exactly(fd: int, src: np.ndarray, offset: int, dtype) -> None:
    data = memoryview(np.ascontiguousarray(src, dtype=dtype).reshape(-1).view(np.uint8))
    done = 0
    while done < data.nbytes:
        done += os.pwrite(fd, data[done:], offset + done)


_OPEN_LOADERS: contextvars.ContextVar[list | None] = contextvars.ContextVar("texstream_open_loaders", default=None)


@contextlib.contextmanager
def loaders_closed_after() -> Iterator[None]:
    """Close every :class:`PhotoLoader` made inside the block when it ends, however it ends. A loader
    streaming from disk lives as long as its fit, and its threads would otherwise keep the process alive
    after the stage returns or fails (``texstream``'s exit waits for threads)."""
    token = _OPEN_LOADERS.set([])
    try:
        yield
    finally:
        loaders = _OPEN_LOADERS.get()
        _OPEN_LOADERS.reset(token)
        for loader in loaders:
            loader.close()


class PhotoLoader:
    """Writes photos, cropped and converted to the image precision, into slots of a buffer.

    ``source`` is a list of (H, W, >=3) arrays or :class:`PhotoFiles`; ``masks`` a list of (H, W)
    masks or None entries (ignored for PhotoFiles, which name their own). Slots are zero-padded to
    the buffer's (hmax, wmax); mask slots hold 1 where the photo may be sampled. With a ready
    :class:`PhotoCache` (``cache``, ``index``: photo k is the cache's ``index[k]``) a slot is copied from
    it; with one being written, each decoded slot is also stored in it."""

    def __init__(self, source, masks, crops: np.ndarray | None, sizes: np.ndarray, threads: int = 0,
                 cache: PhotoCache | None = None, index: np.ndarray | None = None, decoder: str = "auto"):
        self.source, self.masks, self.crops, self.sizes = source, masks, crops, np.asarray(sizes)
        self.cache, self.index, self.decoder = cache, index, decoder
        self.files = isinstance(source, PhotoFiles)
        self.has_masks = (any(p is not None for p in source.mask_paths) if self.files
                          else masks is not None and any(m is not None for m in masks))
        default = FILE_DECODE_THREADS if self.files else ARRAY_COPY_THREADS
        self.requested_threads = threads
        self.threads = threads if threads > 0 else min(default, os.cpu_count() or 1)
        # files decoded in worker processes (fit/stream/decode_pool.py): one thread here per worker, each sending a
        # batch and copying its slots from the staging buffer
        self.processes = decode_pool.processes_for(decoder, threads) if self.files else 0
        self.staging: dict = {}
        self.staging_lock = threading.Lock()
        self.free_blocks: queue.SimpleQueue = queue.SimpleQueue()
        for b in range(self.processes):
            self.free_blocks.put(b)
        self.pool = concurrent.futures.ThreadPoolExecutor(max_workers=max(self.threads, self.processes),
                                                          thread_name_prefix="texstream-photo")
        opened = _OPEN_LOADERS.get()
        if opened is not None:
            opened.append(self)

    def close(self) -> None:
        self.pool.shutdown(wait=True, cancel_futures=True)
        self.staging.clear()

    def cached(self) -> bool:
        """Whether slots come from a ready :class:`PhotoCache` (copies, no decoding)."""
        return self.cache is not None and self.cache.ready

    def _fill_one(self, k: int, img: np.ndarray, msk: np.ndarray | None) -> None:
        if self.cached():
            self.cache.read(k if self.index is None else int(self.index[k]), img, msk)
            return
        self._decode_one(k, img, msk)
        if self.cache is not None and self.cache.writing and self.index is None:
            self.cache.store(k, img, msk)

    def _decode_one(self, k: int, img: np.ndarray, msk: np.ndarray | None) -> None:
        crop = None if self.crops is None else self.crops[k]
        if self.files:
            decode_pool.decode_file_into(self.source.read_image, self.source.read_mask, self.source.paths[k],
                                         self.source.mask_paths[k], self.sizes[k], crop, img, msk)
            return
        im, mask = self.source[k], None if self.masks is None else self.masks[k]
        x0, y0, cw, ch = (0, 0, int(im.shape[1]), int(im.shape[0])) if crop is None else (int(v) for v in crop)
        decode_pool.place_photo(im, mask, x0, y0, cw, ch, img, msk)

    def _fill_batch(self, ks: Sequence[int], images: np.ndarray, masks: np.ndarray | None) -> None:
        """Photos ``ks`` (files) decoded by a worker process into a staging block, then copied into their
        slots (and stored in a cache being written); in this thread where the pool has failed."""
        processes = self.processes
        if not processes:
            for j, k in enumerate(ks):
                self._fill_one(k, images[j], None if masks is None else masks[j])
            return
        key = (images.dtype.str, images.shape[1:])
        block = self.free_blocks.get()
        try:
            with self.staging_lock:  # one staging buffer per slot shape, made by the first batch that needs it
                staging = self.staging.get(key)
                if staging is None:
                    staging = self.staging[key] = decode_pool.Staging(processes, decode_pool.BATCH, images.shape[1],
                                                                      images.shape[2], images.dtype)
            jobs = [(str(self.source.paths[k]), None if self.source.mask_paths[k] is None
                     else str(self.source.mask_paths[k]), tuple(int(v) for v in self.sizes[k]),
                     None if self.crops is None else tuple(int(v) for v in self.crops[k])) for k in ks]
            try:
                failure = decode_pool.start(processes).call(
                    decode_pool.decode_batch, staging.task(block), masks is not None, jobs, self.source.read_image,
                    self.source.read_mask)
            except Exception as e:  # noqa: BLE001 - user errors come back as values: this is the pool's failure
                # (a worker killed, readers that cannot be sent) or a reader's bug; threads decode from here on,
                # and raise the photo's own error if it has one
                self._pool_failed(e)
                return self._fill_batch(ks, images, masks)
            staged_images, staged_masks = staging.views(block, len(ks))
            for j, k in enumerate(ks):
                if failure is not None and failure[0] == j:
                    raise decode_pool.user_error(failure)
                images[j] = staged_images[j]
                if masks is not None:
                    masks[j] = staged_masks[j]
                if self.cache is not None and self.cache.writing and self.index is None:
                    self.cache.store(k, images[j], None if masks is None else masks[j])
        finally:
            self.free_blocks.put(block)

    def _pool_failed(self, error: Exception) -> None:
        if self.processes:
            self.processes = 0

            say("fit", f"photo decoding processes failed ({type(error).__name__}: {error}); decoding in threads")

    def submit(self, ks: Sequence[int], images: np.ndarray, masks: np.ndarray | None) -> list:
        """Start filling slot j of ``images`` (and ``masks``) with photo ``ks[j]``; returns the futures."""
        if self.processes and not self.cached():
            b = decode_pool.BATCH
            # in the caller's context, so the pool's failure is said to its log
            return [self.pool.submit(contextvars.copy_context().run, self._fill_batch, [int(k) for k in ks[j:j + b]],
                                     images[j:j + b], None if masks is None else masks[j:j + b])
                    for j in range(0, len(ks), b)]
        return [self.pool.submit(self._fill_one, int(k), images[j], None if masks is None else masks[j])
                for j, k in enumerate(ks)]

    def fill(self, ks: Sequence[int], images: np.ndarray, masks: np.ndarray | None) -> None:
        """:meth:`submit` and wait (errors re-raised here, the first photo's first)."""
        wait(self.submit(ks, images, masks))


@dataclasses.dataclass
class WindowSlots:
    """The two host buffers photos streamed from disk are decoded into, alternately, and what is in
    flight: shared by a PhotoSet and its subsets (never streamed at once, but interleaved), so each
    knows whether the prefetched window is its own.

    Attributes:
        images, masks: per slot a (window, hmax, wmax) Warp array on the CPU (pinned for CUDA).
        turn: windows submitted so far (the next slot is ``turn % 2``).
        pending: (owner PhotoSet, first photo, slot, futures) of the window being decoded, or None.
        copied: per slot the CUDA event of its last upload (None: none, or the CPU).
    """

    images: list
    masks: list
    turn: int = 0
    pending: tuple | None = None
    copied: list = dataclasses.field(default_factory=lambda: [None, None])


def wait(futures: list) -> None:
    """Wait for every future, then raise the first failure in submission order."""
    concurrent.futures.wait(futures)
    for f in futures:
        f.result()


def host_available_bytes() -> int:
    """Memory the OS says a new allocation may take (Linux MemAvailable; else a conservative 4 GiB)."""
    available = available_memory_bytes()
    return 4 << 30 if available is None else available


def device_available_bytes(device: str) -> int:
    """Free memory of a CUDA device, or the host's for the CPU device."""
    if device == "cpu":
        return host_available_bytes()
    return int(wp.get_device(device).free_memory)


MEMORY_FRACTION = 0.5
"""the share of the memory available that the automatic residency lets the photos and their maps
take (the passes' per-texel buffers, the model and other processes need the rest)"""


def choose_residency(requested: str, device: str, device_bytes: int, host_bytes: int, from_files: bool,
                     limit_bytes: int = 0, windows: bool = False) -> tuple[str, str]:
    """(residency, reason): ``requested`` as given, or for "auto" the first of device, host, disk
    whose memory holds the photos and their maps (``device_bytes`` on the device, ``host_bytes`` in
    host memory) within :data:`MEMORY_FRACTION` of what is available and ``limit_bytes`` (0: none).
    ``windows`` (``photos_per_window`` set): never all on the device. Photos already in memory (not
    ``from_files``) are never streamed from disk. On the CPU device, whose memory is the host's, host
    residency is chosen only for windows."""
    if requested != "auto":
        return requested, "requested"
    gib = 1 << 30
    dev_room = device_room(device, limit_bytes)
    host_room = MEMORY_FRACTION * host_available_bytes()
    if limit_bytes > 0:
        host_room = min(host_room, limit_bytes)
    if windows:
        over = "windows requested (photos_per_window)"
    elif device_bytes <= dev_room:
        return "device", f"{device_bytes / gib:.2f} GiB of photos and maps fit {dev_room / gib:.2f} GiB on {device}"
    else:
        over = f"{device_bytes / gib:.2f} GiB of photos and maps exceed {dev_room / gib:.2f} GiB on {device}"
    if (device != "cpu" or windows) and host_bytes <= host_room:
        return "host", f"{over}; held in host memory, uploaded a window at a time"
    if from_files:
        return "disk", (f"{over}, and {host_bytes / gib:.2f} GiB exceed {host_room / gib:.2f} GiB of host memory; "
                        "decoded from the capture's files a window at a time")
    return "host", f"{over}; the photos were given in memory, so they are streamed from there in windows"


def device_room(device: str, limit_bytes: int = 0) -> float:
    """Bytes the photos and their maps may take on ``device``: :data:`MEMORY_FRACTION` of what is
    available, and at most ``limit_bytes`` (0: no limit)."""
    room = MEMORY_FRACTION * device_available_bytes(device)
    return min(room, limit_bytes) if limit_bytes > 0 else room


def window_size(n: int, per_photo_bytes: int, device: str, limit_bytes: int = 0) -> int:
    """Photos per window when streaming: half the room :func:`choose_residency` allows on the device
    (the other half for the next window's buffers and the passes), at least 1."""
    return max(1, min(n, int(device_room(device, limit_bytes) // (2 * max(per_photo_bytes, 1)))))


def keep_maps_on_device(device: str, map_bytes: int, limit_bytes: int = 0) -> bool:
    """Whether photos streamed from disk keep every depth and shadow map on the device (made once at
    set-up) rather than recomputing a window's maps for every pass: on a CUDA device with room for
    them. On the CPU the device's memory is the host memory that streaming from disk saves."""
    return device != "cpu" and map_bytes <= device_room(device, limit_bytes)
