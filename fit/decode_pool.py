"""Photo files decoded in worker processes, so that decoding shares no lock with the fit.

Decoding an image file in threads of the fitting process leaves part of each read holding Python's
lock (opening the file, the reader binding's bookkeeping, the checks and crops in numpy), so on a machine
with many cores the threads queue for it. Here a pool of processes decodes: each worker reads a batch of
photos (the crop's rows only), crops and converts them exactly as the threads would and writes them into a
block of a shared staging buffer (an anonymous memory file the parent maps too); the parent's thread that
sent the batch copies the block into its destination. The values are the same bytes as decoding in threads.

The pool is shared by the process and started once: ``texstream fit`` and ``texstream run`` start it in the
background before their imports (:func:`start_in_background`), so the workers are up, their readers
imported, by the time the photos are read. Its processes come from a fork server (a fresh interpreter
that has imported numpy and the readers), never from a fork of the fitting process, whose threads may
hold locks. Where processes are not available, or the pool fails, the loader decodes in threads.

The automatic choice uses processes only under those commands: like any process pool that is not forked,
the workers import the main script of the program that started them, so a fit called from a script
without a ``if __name__ == "__main__"`` guard would run again in each of them. From Python, processes are
used when asked for (``StreamConfig.photo_decoder = "processes"``).

Imports only numpy and the standard library; the workers import the readers they are given.
"""

from __future__ import annotations

import concurrent.futures
import itertools
import mmap
import os
import sys
import tempfile
import threading
import weakref

import numpy as np

MIN_CPUS = 8
"""the automatic choice decodes in processes on machines with at least this many CPUs: with fewer, the
threads of one process keep the cores busy (the reads themselves release Python's lock) and a pool's
start would cost more than the lock does"""

MAX_PROCESSES = 16
"""most workers the automatic choice starts (one per CPU up to this): 16 processes decoded the full
ornament's 1,760 float EXRs in 1.3-1.6 s on a 16-core GPU host (docs/scale.md)"""

READER_THREADS = 1
"""threads each worker's reader (OpenImageIO, OpenEXR) decodes one file with: the pool's parallelism is
over photos (0: the reader's default, a thread per CPU in each worker)"""

BATCH = 4
"""photos per task sent to a worker: few enough that a window's batches spread over the workers, enough
that the per-task cost (a message each way) stays small against decoding"""

DECODERS = ("auto", "threads", "processes")

_lock = threading.Lock()
_pool: concurrent.futures.ProcessPoolExecutor | None = None
_pool_size: tuple = (0, 0)
_tokens = itertools.count(1)
_command_processes = 0  # the automatic choice's workers, set by start_in_background (the texstream command)


def default_processes() -> int:
    """Workers of the automatic choice under the ``texstream`` command: one per CPU up to
    :data:`MAX_PROCESSES` with at least :data:`MIN_CPUS` CPUs, else none (threads decode)."""
    cpus = os.cpu_count() or 1
    return min(MAX_PROCESSES, cpus) if cpus >= MIN_CPUS else 0


def processes_for(decoder: str, count: int = 0) -> int:
    """Workers for ``StreamConfig.photo_decoder`` ("auto", "threads" or "processes") and
    ``decode_threads`` ``count`` (0: the default), or 0 for threads: "auto" is processes only under a
    command that called :func:`start_in_background`; 0 too where the platform has no fork server."""
    if decoder == "threads" or not available():
        return 0
    if decoder == "processes":
        return count if count > 0 else max(2, min(MAX_PROCESSES, os.cpu_count() or 1))
    return (count if count > 0 else _command_processes) if _command_processes else 0


def available() -> bool:
    """Whether worker processes can be started here (a fork server: Linux and macOS)."""
    import multiprocessing

    return "forkserver" in multiprocessing.get_all_start_methods()


def _start(processes: int, reader_threads: int = -1) -> concurrent.futures.ProcessPoolExecutor:
    global _pool, _pool_size
    import multiprocessing

    key = (processes, READER_THREADS if reader_threads < 0 else reader_threads)
    with _lock:
        if _pool is not None and _pool_size == key:
            return _pool
        if _pool is not None:
            _pool.shutdown(wait=False, cancel_futures=True)
        ctx = multiprocessing.get_context("forkserver")
        # imported once in the fork server, so each worker starts with them
        ctx.set_forkserver_preload([__name__, "numpy", "OpenImageIO", "texstream.capture.imageio"])
        _pool = concurrent.futures.ProcessPoolExecutor(processes, mp_context=ctx, initializer=_worker_init,
                                                       initargs=(key[1],))
        _pool_size = key
        pool = _pool
    for _ in range(processes):  # one task per worker: the pool starts them all now
        pool.submit(_ready)
    return pool


def start(processes: int, reader_threads: int = -1) -> concurrent.futures.ProcessPoolExecutor:
    """The shared pool of ``processes`` workers whose readers use ``reader_threads`` (-1:
    :data:`READER_THREADS`), started (or restarted so) if need be. Starting blocks the caller until the
    fork server has imported its modules."""
    return _start(processes, reader_threads)


def start_in_background() -> None:
    """Make the automatic choice processes (:func:`default_processes`), and start their pool in a thread,
    returning at once (nothing where the automatic choice is threads)."""
    global _command_processes
    n = default_processes() if available() else 0
    _command_processes = n
    if n:
        threading.Thread(target=_start, args=(n,), name="texstream-decode-pool", daemon=True).start()


def shutdown() -> None:
    """Stop the shared pool's workers (the command's end; idle workers exit at once)."""
    global _pool, _pool_size, _command_processes
    with _lock:
        pool, _pool, _pool_size, _command_processes = _pool, None, (0, 0), 0
    if pool is not None:
        pool.shutdown(wait=True, cancel_futures=True)


def _ready() -> int:
    return os.getpid()


def _worker_init(reader_threads: int) -> None:
    """The worker's reader threads (:data:`READER_THREADS`; 0 leaves the reader's default)."""
    if reader_threads <= 0:
        return
    try:
        import OpenImageIO as oiio

        oiio.attribute("threads", reader_threads)
        oiio.attribute("exr_threads", reader_threads)
    except ImportError:
        pass


class Staging:
    """A buffer of ``blocks`` x ``per_block`` photo slots ((hmax, wmax, 3) of ``dtype``) and their masks
    ((hmax, wmax) uint8) in an anonymous memory file the workers map by its /proc path (a temporary file,
    removed when the staging is, where there is no memfd)."""

    def __init__(self, blocks: int, per_block: int, hmax: int, wmax: int, dtype):
        self.dtype = np.dtype(dtype)
        self.slot_shape, self.per_block = (hmax, wmax, 3), per_block
        self.image_bytes = hmax * wmax * 3 * self.dtype.itemsize
        self.mask_bytes = hmax * wmax
        self.block_bytes = per_block * (self.image_bytes + self.mask_bytes)
        self.nbytes = blocks * self.block_bytes
        if hasattr(os, "memfd_create") and sys.platform.startswith("linux"):
            fd = os.memfd_create("texstream-decode")
            self.path, temp = f"/proc/{os.getpid()}/fd/{fd}", None
        else:
            fd, temp = tempfile.mkstemp(prefix="texstream-decode-")
            self.path = temp
        os.ftruncate(fd, self.nbytes)
        self.map = mmap.mmap(fd, self.nbytes)
        self.token = next(_tokens)
        weakref.finalize(self, _release, fd, temp)

    def views(self, block: int, count: int) -> tuple[np.ndarray, np.ndarray]:
        """(images (count, hmax, wmax, 3), masks (count, hmax, wmax)) of ``block``."""
        return block_views(self.map, block * self.block_bytes, count, self.slot_shape, self.dtype,
                           self.per_block)

    def task(self, block: int) -> tuple:
        """What a worker needs to find ``block``."""
        return (self.path, self.token, self.nbytes, block * self.block_bytes, self.slot_shape, self.dtype.str,
                self.per_block)


def _release(fd: int, temp: str | None) -> None:
    os.close(fd)
    if temp is not None:
        try:
            os.unlink(temp)
        except OSError:
            pass


def block_views(buffer, offset: int, count: int, slot_shape, dtype, per_block: int):
    """Images and masks of a block starting at byte ``offset`` of ``buffer`` (see :class:`Staging`)."""
    hmax, wmax, _ = slot_shape
    image_bytes = hmax * wmax * 3 * np.dtype(dtype).itemsize
    images = np.frombuffer(buffer, dtype, count * hmax * wmax * 3, offset).reshape(count, *slot_shape)
    masks = np.frombuffer(buffer, np.uint8, count * hmax * wmax, offset + per_block * image_bytes)
    return images, masks.reshape(count, hmax, wmax)


def place_photo(im: np.ndarray, mask, x0: int, y0: int, cw: int, ch: int, img: np.ndarray, msk) -> None:
    """Write the (ch, cw) crop at (x0, y0) of ``im`` (and of ``mask``, None: all valid) into the slot
    ``img`` (and ``msk``, None: not kept), zero padding the rest."""
    img[:ch, :cw] = im[y0:y0 + ch, x0:x0 + cw, :3]
    img[ch:] = 0
    img[:ch, cw:] = 0
    if msk is not None:
        msk[...] = 0
        msk[:ch, :cw] = 1 if mask is None else np.asarray(mask[y0:y0 + ch, x0:x0 + cw], bool)


def decode_file_into(read_image, read_mask, path, mask_path, size, crop, img: np.ndarray, msk) -> None:
    """Decode photo ``path`` (and its mask) of (H, W) ``size`` into a slot: only the rows of ``crop``
    (x0, y0, width, height; None: the whole photo), then :func:`place_photo`."""
    h, w = (int(v) for v in size)
    if crop is not None:
        x0, y0, cw, ch = (int(v) for v in crop)
        rows = (y0, y0 + ch)
        im = read_image(path, rows=rows, size=(h, w))
        mask = None if mask_path is None else read_mask(mask_path, (h, w), rows=rows)
        place_photo(im, mask, x0, 0, cw, ch, img, msk)
        return
    im = read_image(path, rows=None, size=(h, w))
    mask = None if mask_path is None else read_mask(mask_path, (h, w), rows=None)
    place_photo(im, mask, 0, 0, int(im.shape[1]), int(im.shape[0]), img, msk)


_mapped: dict = {}


def decode_batch(staging: tuple, with_masks: bool, jobs: list, read_image, read_mask):
    """(In a worker.) Decode ``jobs`` ((path, mask path or None, (H, W), crop or None) each) into the
    slots of a staging block (:meth:`Staging.task`). Returns None, or (j, error class name, message,
    path, fix) of the first photo that failed with a user error; the batch's later photos are left."""
    from texstream.core.errors import TexstreamError

    path, token, nbytes, offset, slot_shape, dtype, per_block = staging
    buf = _mapped.get(token)
    if buf is None:
        _mapped.clear()  # one staging at a time is in use; an older one is not written again
        fd = os.open(path, os.O_RDWR)
        try:
            buf = _mapped[token] = mmap.mmap(fd, nbytes)
        finally:
            os.close(fd)
    images, masks = block_views(buf, offset, len(jobs), slot_shape, np.dtype(dtype), per_block)
    for j, (p, mp, size, crop) in enumerate(jobs):
        try:
            decode_file_into(read_image, read_mask, p, mp, size, crop, images[j], masks[j] if with_masks else None)
        except TexstreamError as e:
            return j, type(e).__name__, e.message, e.path, e.fix
    return None


def user_error(failure: tuple) -> Exception:
    """The :class:`~texstream.core.errors.TexstreamError` a worker reported (:func:`decode_batch`)."""
    from texstream.core import errors

    _, name, message, path, fix = failure
    cls = getattr(errors, name, errors.InputError)
    return cls(message, path, fix)
