"""What uploading photos given as arrays costs when their own memory is page-locked for the GPU (CUDA host
registration) instead of cropped into pinned buffers on the host; writes JSON.

    python benchmarks/host_register.py --devices cuda:0,cuda:1 --out DIR

Makes ``--photos`` separate (H, W, 3) float32 arrays (as a renderer or a decoder hands them over), then per
variant, fastest of ``--repeats``:

- ``register``: page-lock the arrays' memory (page ranges merged, one ``cuMemHostRegister`` per range) on
  one device, one thread;
- ``dma_rows``: copy each photo's rows ``--rows`` (all columns: contiguous) to the device, asynchronously,
  from the registered memory, then synchronise;
- ``unregister``;
- the same three for each half of the photos on its own device at once (one thread per device; ranges
  split between the halves so that no page is registered twice).

The photos' host work in the pinned-buffer path is the crop, a host copy (benchmarks/photo_split_setup_profile.py);
here the host only locks pages and the copy engines read the photos where they are.
"""

from __future__ import annotations

import argparse
import ctypes
import json
import mmap
import platform
import threading
import time
from pathlib import Path

from gitinfo import commit

PAGE = mmap.PAGESIZE


def page_ranges(arrays) -> list[tuple[int, int]]:
    """Page-aligned [start, end) host ranges covering ``arrays``' memory, overlapping ones merged."""
    spans = sorted((a.ctypes.data // PAGE * PAGE, -(-(a.ctypes.data + a.nbytes) // PAGE) * PAGE) for a in arrays)
    merged: list[list[int]] = []
    for s, e in spans:
        if merged and s <= merged[-1][1]:
            merged[-1][1] = max(merged[-1][1], e)
        else:
            merged.append([s, e])
    return [(s, e) for s, e in merged]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--devices", default="cuda:0,cuda:1")
    ap.add_argument("--photos", type=int, default=1760)
    ap.add_argument("--size", type=int, default=430, help="photo side (pixels)")
    ap.add_argument("--rows", type=int, default=310, help="rows copied per photo (the object's crop)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", required=True)
    a = ap.parse_args()

    import numpy as np
    import warp as wp

    wp.config.quiet = True
    wp.init()
    cuda = ctypes.CDLL("libcuda.so.1")
    cuda.cuMemHostRegister_v2.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_uint]
    cuda.cuMemHostUnregister.argtypes = [ctypes.c_void_p]
    cuda.cuMemcpyHtoDAsync_v2.argtypes = [ctypes.c_uint64, ctypes.c_void_p, ctypes.c_size_t, ctypes.c_void_p]
    devices = [d.strip() for d in a.devices.split(",")]
    photos = []
    for k in range(a.photos):
        im = np.empty((a.size, a.size, 3), np.float32)
        im.fill(k % 7 * 0.1)  # touched: resident pages, as a rendered or decoded photo's
        photos.append(im)
    photos.sort(key=lambda im: im.ctypes.data)
    row_bytes = a.size * 3 * 4
    first_row = (a.size - a.rows) // 2
    landing = {d: wp.empty(a.photos * a.rows * a.size * 3, dtype=float, device=d) for d in devices}

    def check(rc: int, what: str) -> None:
        if rc != 0:
            raise RuntimeError(f"{what}: CUDA driver error {rc}")

    def run_part(device: str, ims: list, ranges: list, barrier: threading.Barrier, out: dict) -> None:
        dev = wp.get_device(device)
        with dev.context_guard:
            t0 = time.perf_counter()
            for s, e in ranges:  # portable: a page of this part's photos may be in another part's range
                check(cuda.cuMemHostRegister_v2(s, e - s, 1), "cuMemHostRegister")
            t1 = time.perf_counter()
            barrier.wait()  # every part's pages locked before any copy reads them
            t2 = time.perf_counter()
            stream = wp.get_stream(device).cuda_stream
            base = landing[device].ptr
            n = a.rows * row_bytes
            for j, im in enumerate(ims):
                check(cuda.cuMemcpyHtoDAsync_v2(base + j * n, im.ctypes.data + first_row * row_bytes, n, stream),
                      "cuMemcpyHtoDAsync")
            wp.synchronize_device(device)
            t3 = time.perf_counter()
            barrier.wait()  # no part's pages unlocked while another part copies from them
            t4 = time.perf_counter()
            for s, _ in ranges:
                check(cuda.cuMemHostUnregister(s), "cuMemHostUnregister")
            t5 = time.perf_counter()
        out.update(register_s=t1 - t0, dma_rows_s=t3 - t2, unregister_s=t5 - t4, ranges=len(ranges),
                   registered_bytes=sum(e - s for s, e in ranges), copied_bytes=len(ims) * n)

    def timed(parts: list[tuple[str, list]]) -> dict:
        # disjoint ranges: the parts' photos are consecutive in memory (sorted by address), so a page shared
        # by two parts' photos is left to the earlier part
        all_ranges, end = [], 0
        for _, ims in parts:
            rs = [(max(s, end), e) for s, e in page_ranges(ims) if e > end]
            all_ranges.append(rs)
            end = max(end, rs[-1][1]) if rs else end
        outs = [dict() for _ in parts]
        barrier = threading.Barrier(len(parts))
        t0 = time.perf_counter()
        threads = [threading.Thread(target=run_part, args=(d, ims, r, barrier, o))
                   for (d, ims), r, o in zip(parts, all_ranges, outs)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        return {"wall_s": time.perf_counter() - t0, "parts": outs}

    results = {}
    half = (a.photos + 1) // 2
    variants = {"one_device": [(devices[0], photos)]}
    if len(devices) > 1:
        variants["halves_on_two_devices"] = [(devices[0], photos[:half]), (devices[1], photos[half:])]
    for name, parts in variants.items():
        runs = [timed(parts) for _ in range(a.repeats)]
        results[name] = min(runs, key=lambda r: r["wall_s"])
        results[name]["all_walls_s"] = [r["wall_s"] for r in runs]
        print(name, json.dumps(results[name]))
    doc = {"command": "python benchmarks/host_register.py " + " ".join(f"--{k} {v}" for k, v in vars(a).items()),
           "commit": commit(), "machine": platform.node(),
           "device_names": {d: wp.get_device(d).name for d in devices},
           "photo_bytes": a.photos * a.size * a.size * 12, "results": results}
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "host_register.json").write_text(json.dumps(doc, indent=2))


if __name__ == "__main__":
    main()
