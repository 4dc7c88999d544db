"""Warp kernels on every CPU core (the photometric refinement's launches, dense stereo's photos): Warp runs a CPU
kernel on the thread that launches it, one core, and its launches release the GIL (a ctypes call of the
kernel's compiled entry point), so work split into parts that write disjoint arrays, one launching thread each,
keeps the cores busy and gives one thread's result to the bit. (fit/multi/cpu_threads.py, a layer above, does
the same for the fit, with these cores.) The standard library and texstream.core only."""

from __future__ import annotations

import concurrent.futures
import os

from texstream.core.devices import available_memory_bytes

MAX_AUTO_THREADS = 8
"""the most threads ``threads`` 0 picks (measured on 2 cores only)"""


def usable_cpus() -> int:
    """The CPU cores this process may run on (its affinity mask where the OS has one)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # macOS and Windows have no affinity call
        return os.cpu_count() or 1


def threads_for(asked: int, device: str) -> int:
    """The threads a stage's launches split over: ``asked``, or (0) the usable cores (at most
    :data:`MAX_AUTO_THREADS`); 1 off the CPU (one launch fills a GPU)."""
    if not str(device).startswith("cpu"):
        return 1
    return asked if asked > 0 else max(1, min(usable_cpus(), MAX_AUTO_THREADS))


def threads_within_memory(threads: int, bytes_per_thread: int, fraction: float = 0.5) -> int:
    """``threads`` or fewer, so that their scratch of ``bytes_per_thread`` each stays within ``fraction`` of the memory
    the OS says is available (Linux MemAvailable; elsewhere no cap): dense stereo's sweep of a 3072x2048 photo at
    level 0 holds about 1 GB. At least one."""
    available = available_memory_bytes()
    if available is None:
        return threads
    return max(1, min(threads, int(fraction * available) // max(int(bytes_per_thread), 1)))


def in_order(work, items: list, threads: int):
    """(item, ``work(item)``) in the items' order, the work done on ``threads`` threads at once (in the caller's
    thread with one); the work not started yet is cancelled when the caller stops early."""
    if threads <= 1 or len(items) < 2:
        for item in items:
            yield item, work(item)
        return
    with concurrent.futures.ThreadPoolExecutor(min(threads, len(items)), thread_name_prefix="texstream") as pool:
        futures = [pool.submit(work, item) for item in items]
        try:
            for item, done in zip(items, futures):
                yield item, done.result()
        finally:
            for done in futures:
                done.cancel()
