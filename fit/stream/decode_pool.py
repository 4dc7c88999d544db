"""Photo files decoded in worker processes, so that decoding shares no lock with the fit.

Decoding an image file in threads of the fitting process leaves part of each read holding Python's
lock (opening the file, the reader binding's bookkeeping, the checks and crops in numpy), so on a machine
with many cores the threads queue for it. Here a pool of processes decodes: each worker reads a batch of
photos (the crop's rows only), crops and converts them exactly as the threads would and writes them into a
block of a shared staging buffer (an anonymous memory file the parent maps too); the parent's thread that
sent the batch copies the block into its destination. The values are the same bytes as decoding in threads.

The pool is shared by the process and started once: ``texstream fit`` and ``texstream run`` start it in the
background before their imports (:func:`start_in_background`), so the workers are up, their readers
imported, by the time the photos are read. Each worker is a fresh interpreter (``python -c``, the parent's
``sys.path``) talking to the parent over two pipes: never a fork of the fitting process, whose threads may
hold locks, and never an import of the program's main script (which ``multiprocessing``'s spawn and fork
server do). Where the pool fails (a worker killed, readers that cannot be sent), the loader decodes in
threads.

The automatic choice uses processes only under those commands, where the workers' start (about 0.5 s for 16,
their imports) is hidden behind the command's own; from Python, processes are used when asked for
(``StreamConfig.photo_decoder = "processes"``).

Imports numpy, the standard library, ``texstream.core.errors`` and ``texstream.capture.imageio`` (the
readers' module, so a worker has it before its first task); the workers import the readers they are given.
"""

from __future__ import annotations

import itertools
import mmap
import os
import sys
import tempfile
import threading
import weakref

import numpy as np

from texstream.capture import imageio  # noqa: F401 - the readers' module (see above)
from texstream.core import errors
from texstream.core.errors import TexstreamError

MIN_CPUS = 16
"""the automatic choice decodes in processes on machines with at least this many CPUs: on a 16-core GPU host 8
workers did no better than 4 threads (2.2 s for 1,760 float EXRs), 16 took half the time (docs/scale.md)"""

MAX_PROCESSES = 16
"""most workers the automatic choice starts (one per CPU up to this): 16 decoded the full ornament's 1,760 float
EXRs in 1.13 s on a 16-core GPU host, against 2.2 s for 4 threads (docs/scale.md)"""

READER_THREADS = 1
"""threads each worker's reader (OpenImageIO, OpenEXR) decodes one file with: the pool's parallelism is
over photos (0: the reader's default, a thread per CPU in each worker)"""

BATCH = 4
"""photos per task sent to a worker: few enough that a window's batches spread over the workers, enough
that the per-task cost (a message each way) stays small against decoding"""

_lock = threading.Lock()
_pool: "WorkerPool | None" = None
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
    command that called :func:`start_in_background`."""
    if decoder == "threads":
        return 0
    if decoder == "processes":
        return count if count > 0 else max(2, min(MAX_PROCESSES, os.cpu_count() or 1))
    return (count if count > 0 else _command_processes) if _command_processes else 0


class WorkerFailed(RuntimeError):
    """A worker died or its task could not be sent or answered: the pool is no longer used."""


class Worker:
    """One decoding process: a fresh interpreter running :func:`serve` on two pipes."""

    def __init__(self, reader_threads: int):
        import json
        import subprocess

        from_parent, to_worker = os.pipe()
        from_worker, to_parent = os.pipe()
        code = (f"import sys; sys.path[:] = {json.dumps(sys.path)}; "
                f"from texstream.fit.stream.decode_pool import serve; serve({from_parent}, {to_parent}, {reader_threads})")
        # one thread of BLAS and OpenMP per worker: numpy's import would otherwise start a pool of CPU-count
        # threads in each worker, which slows every process on the machine while they start
        env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1")
        try:
            self.proc = subprocess.Popen([sys.executable, "-c", code], pass_fds=(from_parent, to_parent),
                                         stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                         stderr=subprocess.DEVNULL, env=env)
        finally:
            os.close(from_parent)
            os.close(to_parent)
        from multiprocessing.connection import Connection

        self.send, self.recv = Connection(to_worker, readable=False), Connection(from_worker, writable=False)

    def call(self, fn, args: tuple):
        """``fn(*args)`` in the worker: its value, or its exception raised here."""
        try:
            self.send.send((fn, args))
            ok, value = self.recv.recv()
        except (EOFError, OSError, TypeError, AttributeError, ValueError) as e:  # died, or unpicklable
            raise WorkerFailed(f"{type(e).__name__}: {e}") from e
        if not ok:
            raise value
        return value

    def close(self) -> None:
        """Close the pipes: the worker exits when it reaches the end of its input."""
        for conn in (self.send, self.recv):
            conn.close()


class WorkerPool:
    """``processes`` :class:`Worker` s, lent one at a time to the calling thread (the loader runs one thread
    per worker, so none waits for another's)."""

    def __init__(self, processes: int, reader_threads: int):
        import queue

        self.key = (processes, reader_threads)
        self.broken = False
        self.workers = [Worker(reader_threads) for _ in range(processes)]
        self.idle: queue.SimpleQueue = queue.SimpleQueue()
        for w in self.workers:
            self.idle.put(w)

    def call(self, fn, *args):
        """``fn(*args)`` on an idle worker (waiting for one). :class:`WorkerFailed` if it died, and for every
        call after that: a failed worker's pipes may hold half a message, so the pool is given up."""
        worker = self.idle.get()
        if worker is None:  # the pool broke while this thread waited
            self.idle.put(None)
            raise WorkerFailed("an earlier worker failed")
        try:
            value = worker.call(fn, args)
        except WorkerFailed:
            self.broken = True
            worker.close()
            worker.proc.kill()
            self.idle.put(None)  # wakes the threads waiting for a worker
            raise
        except BaseException:
            self.idle.put(worker)
            raise
        self.idle.put(worker)
        return value

    def shutdown(self, wait: bool = True) -> None:
        """Close every worker's pipes; with ``wait``, reap them (they exit together, a worker busy with a
        batch after it)."""
        for w in self.workers:
            w.close()
        if wait:
            for w in self.workers:
                w.proc.wait()


def start(processes: int, reader_threads: int = -1) -> WorkerPool:
    """The shared pool of ``processes`` workers whose readers use ``reader_threads`` (-1:
    :data:`READER_THREADS`), started (or restarted so) if need be; its workers import their modules in the
    background."""
    global _pool
    key = (processes, READER_THREADS if reader_threads < 0 else reader_threads)
    with _lock:
        if _pool is not None and _pool.key == key and not _pool.broken:
            return _pool
        old, _pool = _pool, WorkerPool(*key)
        pool = _pool
    if old is not None:
        old.shutdown(wait=False)
    return pool


def start_in_background() -> None:
    """Make the automatic choice processes (:func:`default_processes`), and start their pool in a thread,
    returning at once (nothing where the automatic choice is threads)."""
    global _command_processes
    n = default_processes()
    _command_processes = n
    if n:
        threading.Thread(target=start, args=(n,), name="texstream-decode-pool", daemon=True).start()


def shutdown(wait: bool = True) -> None:
    """Stop the shared pool's workers; ``wait``: until they have exited (a command about to end need not:
    they exit at the end of their input)."""
    global _pool, _command_processes
    with _lock:
        pool, _pool, _command_processes = _pool, None, 0
    if pool is not None:
        pool.shutdown(wait)


def serve(from_parent: int, to_parent: int, reader_threads: int) -> None:
    """(A worker's main.) Answer (fn, args) messages with (True, value) or (False, exception) until the
    parent closes the pipe."""
    from multiprocessing.connection import Connection

    try:
        import OpenImageIO as oiio

        if reader_threads > 0:
            oiio.attribute("threads", reader_threads)
            oiio.attribute("exr_threads", reader_threads)
    except ImportError:
        pass

    inbox, outbox = Connection(from_parent, writable=False), Connection(to_parent, readable=False)
    while True:
        try:
            fn, args = inbox.recv()
        except (EOFError, OSError):
            return
        try:
            reply = (True, fn(*args))
        except Exception as e:  # noqa: BLE001 - sent back and raised in the parent
            reply = (False, e)
        try:
            outbox.send(reply)
        except Exception:  # noqa: BLE001 - an exception that cannot be pickled
            outbox.send((False, RuntimeError(f"{type(reply[1]).__name__}: {reply[1]}")))


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
    _, name, message, path, fix = failure
    cls = getattr(errors, name, errors.InputError)
    return cls(message, path, fix)
