"""A 300 MiB copy from cuda:1 to cuda:0 with and without peer access (what fit/photo_split.py switches on for the
partial sums it copies each pass); prints the mean time and rate of 10 copies after 2 untimed ones.

    python benchmarks/peer_copy.py     # on a machine with two CUDA GPUs
"""

import time

import warp as wp

wp.init()
print("peer", wp.is_peer_access_supported("cuda:0", "cuda:1"), "mempool",
      wp.is_mempool_access_supported("cuda:0", "cuda:1"))
for enable in (False, True):
    if enable:
        from texstream.fit.multi.photo_split import enable_peer_copies

        enable_peer_copies(["cuda:0", "cuda:1"])
    a = wp.zeros(300 * 2**20 // 4, dtype=float, device="cuda:1")
    b = wp.zeros(a.shape[0], dtype=float, device="cuda:0")
    for _ in range(2):
        wp.copy(b, a)
    wp.synchronize_device("cuda:0")
    wp.synchronize_device("cuda:1")
    t = time.perf_counter()
    for _ in range(10):
        wp.copy(b, a)
    wp.synchronize_device("cuda:0")
    dt = (time.perf_counter() - t) / 10
    print("enabled", enable, "300 MiB copy cuda:1 -> cuda:0 %.2f ms, %.0f GB/s" % (dt * 1e3, 300 * 2**20 / dt / 1e9))
