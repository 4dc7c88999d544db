"""How fast the host can move photos into pinned buffers, by method and thread count: the bound on the photos'
upload (fit/stream/photo_set.py upload_photo_sets). Photos as the renderer gives them (one float32 (H, W, 3) array and
one bool mask per photo), cropped to a fixed box:

- ``crop``: the upload's own crop (decode_pool.place_photo: the box's pixels, zero padding, the mask);
- ``rows``: the box's rows only, whole width (one contiguous block of the photo; the columns would be cut on the
  device), and their mask rows;
- ``memcpy``: one contiguous block of the same size split between the threads (the memory's own rate).

Each into one pinned buffer holding every photo (``full``) and into two 16 MiB pinned slots reused in turn
(``ring``, as the upload pipeline does). Also the pinned host-to-device copy rate per GPU and with every GPU at
once, and (``--pageable-threads``) each photo's rows copied straight from its own pageable memory to a device
buffer (the driver stages them), by thread count, to each GPU alone and to every GPU at once (the photos split
between them): whether the host's part of the upload divides between GPUs. Writes JSON and prints a log.

    python benchmarks/host_copy_rates.py --out DIR [--photos 1760 --size 430 --box 350x312] [--devices cuda:0,cuda:1]
        [--pageable-threads 1,2,4,8]
"""

from __future__ import annotations

import argparse
import concurrent.futures
import json
import os
import platform
import subprocess
import time

import numpy as np
import warp as wp

from texstream.fit.stream.decode_pool import place_photo


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--photos", type=int, default=1760)
    ap.add_argument("--size", type=int, default=430)
    ap.add_argument("--box", default="350x312", help="crop rows x columns")
    ap.add_argument("--threads", default="1,4,8,16,24")
    ap.add_argument("--devices", default="")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--pageable-threads", default="", help="thread counts for the pageable copies (none: skipped)")
    a = ap.parse_args()
    wp.config.quiet = True
    wp.init()
    pinned = wp.is_cuda_available()  # pinned memory needs CUDA; elsewhere the same buffers, pageable
    os.makedirs(a.out, exist_ok=True)
    n, s = a.photos, a.size
    ch, cw = (int(v) for v in a.box.split("x"))
    y0, x0 = (s - ch) // 2, (s - cw) // 2
    rng = np.random.default_rng(0)
    photos = [np.full((s, s, 3), rng.random(), np.float32) for _ in range(n)]
    masks = [np.ones((s, s), bool) for _ in range(n)]
    thread_counts = [int(t) for t in a.threads.split(",")]
    slot_bytes = 16 << 20
    crop_px, rows_px = ch * cw, ch * s
    result = {"command": "python benchmarks/host_copy_rates.py " + " ".join(
        f"--{k} {v}" for k, v in vars(a).items() if k != "out") + " --out DIR",
              "machine": platform.node(), "cpus": os.cpu_count(), "photos": n, "size": s, "box": [ch, cw],
              "rates_gb_s": {}}
    try:
        result["cpu"] = subprocess.run(["lscpu"], capture_output=True, text=True).stdout.splitlines()[:20]
    except OSError:
        pass

    def buffers(kind: str, px: int):
        """(image slots (k, px*3) float32, mask slots (k, px) uint8) per buffer, and photos per buffer."""
        per = n if kind == "full" else max(1, slot_bytes // (px * 12))
        count = 1 if kind == "full" else 2
        bufs = [(wp.empty(per * px * 3, dtype=wp.float32, device="cpu", pinned=pinned),
                 wp.empty(per * px, dtype=wp.uint8, device="cpu", pinned=pinned)) for _ in range(count)]
        return [(b.numpy().reshape(per, px * 3), m.numpy().reshape(per, px)) for b, m in bufs], per, bufs

    def crop_one(k, img, msk):
        place_photo(photos[k], masks[k], x0, y0, cw, ch, img.reshape(ch, cw, 3), msk.reshape(ch, cw))

    def rows_one(k, img, msk):
        np.copyto(img.reshape(ch, s, 3), photos[k][y0:y0 + ch])
        np.copyto(msk.reshape(ch, s), masks[k][y0:y0 + ch].view(np.uint8))

    for method, px, fn in (("crop", crop_px, crop_one), ("rows", rows_px, rows_one)):
        for kind in ("full", "ring"):
            views, per, keep = buffers(kind, px)
            for t in thread_counts:
                pool = concurrent.futures.ThreadPoolExecutor(t)
                best = None
                for _ in range(a.repeats):
                    t0 = time.perf_counter()
                    futures = []
                    for k in range(n):
                        img, msk = views[(k // per) % len(views)]
                        futures.append(pool.submit(fn, k, img[k % per], msk[k % per]))
                        if kind == "ring" and k % per == per - 1:
                            concurrent.futures.wait(futures)  # the slot is reused next round: its crops done
                            futures = []
                    concurrent.futures.wait(futures)
                    dt = time.perf_counter() - t0
                    best = dt if best is None else min(best, dt)
                pool.shutdown()
                gb = n * px * 13 / 1e9
                result["rates_gb_s"][f"{method}_{kind}_t{t}"] = {"s": best, "gb_written": gb, "gb_s": gb / best}
                print(f"{method:6s} {kind:4s} threads {t:2d}: {best:.3f} s, {gb / best:5.1f} GB/s written", flush=True)
            del views, keep
    # the memory's own rate: one contiguous block of the cropped photos' size, split between the threads
    total = n * crop_px * 3
    src = np.ones(total, np.float32)
    dst_buf = wp.empty(total, dtype=wp.float32, device="cpu", pinned=pinned)
    dst = dst_buf.numpy()
    dst[:] = 0
    for t in thread_counts:
        parts = np.array_split(np.arange(total), t)
        bounds = [(int(p[0]), int(p[-1]) + 1) for p in parts]
        pool = concurrent.futures.ThreadPoolExecutor(t)
        best = None
        for _ in range(a.repeats):
            t0 = time.perf_counter()
            list(pool.map(lambda be: np.copyto(dst[be[0]:be[1]], src[be[0]:be[1]]), bounds))
            dt = time.perf_counter() - t0
            best = dt if best is None else min(best, dt)
        pool.shutdown()
        result["rates_gb_s"][f"memcpy_t{t}"] = {"s": best, "gb_written": total * 4 / 1e9, "gb_s": total * 4 / 1e9 / best}
        print(f"memcpy      threads {t:2d}: {best:.3f} s, {total * 4 / 1e9 / best:5.1f} GB/s", flush=True)
    devices = [d for d in a.devices.split(",") if d]
    if devices:
        chunk = 64 << 20 >> 2
        dev_dst = {d: wp.empty(chunk, dtype=wp.float32, device=d) for d in devices}
        for group in [[d] for d in devices] + ([devices] if len(devices) > 1 else []):
            for d in group:
                wp.synchronize_device(d)
            t0 = time.perf_counter()
            reps = 40
            for r in range(reps):
                for d in group:
                    wp.copy(dev_dst[d], dst_buf, 0, (r * chunk) % (total - chunk), chunk)
            for d in group:
                wp.synchronize_device(d)
            dt = time.perf_counter() - t0
            gb = reps * len(group) * chunk * 4 / 1e9
            result["rates_gb_s"]["h2d_" + "+".join(group)] = {"s": dt, "gb": gb, "gb_s": gb / dt}
            print(f"host to {'+'.join(group)}: {gb / dt:5.1f} GB/s", flush=True)
        pageable_rates(a, result, photos, masks, y0, ch, devices)
    with open(os.path.join(a.out, "host_copy_rates.json"), "w") as fh:
        json.dump(result, fh, indent=1)


def pageable_rates(a, result: dict, photos: list, masks: list, y0: int, ch: int, devices: list[str]) -> None:
    """Each photo's rows ``y0:y0+ch`` (one contiguous block of its own pageable memory) and its mask rows copied
    straight to a device buffer, ``t`` threads per device each with its own stream, to each device alone and
    to every device at once (photo k to device k % devices): GB/s of photo bytes, all copies finished."""
    n, s = len(photos), photos[0].shape[1]
    row_floats = ch * s * 3
    for t in [int(v) for v in a.pageable_threads.split(",") if v]:
        for group in [[d] for d in devices] + ([devices] if len(devices) > 1 else []):
            landing = {(d, j): (wp.empty(row_floats, dtype=wp.float32, device=d),
                                wp.empty(ch * s, dtype=wp.uint8, device=d)) for d in group for j in range(t)}
            streams = {(d, j): wp.Stream(d) if d != "cpu" else None for d in group for j in range(t)}

            def worker(d_j):
                d, j = d_j
                img, msk = landing[d_j]
                stream = streams[d_j]
                for k in range(group.index(d) + j * len(group), n, len(group) * t):
                    rows = photos[k][y0:y0 + ch].reshape(-1)
                    wp.copy(img, wp.array(ptr=rows.ctypes.data, shape=(rows.size,), dtype=wp.float32, device="cpu"),
                            stream=stream)
                    mrows = masks[k][y0:y0 + ch].reshape(-1)
                    wp.copy(msk, wp.array(ptr=mrows.ctypes.data, shape=(mrows.size,), dtype=wp.uint8, device="cpu"),
                            stream=stream)
                if stream is not None:
                    wp.synchronize_stream(stream)

            pool = concurrent.futures.ThreadPoolExecutor(t * len(group))
            best = None
            for _ in range(a.repeats):
                for d in group:
                    wp.synchronize_device(d)
                t0 = time.perf_counter()
                list(pool.map(worker, list(landing)))
                dt = time.perf_counter() - t0
                best = dt if best is None else min(best, dt)
            pool.shutdown()
            gb = n * ch * s * 13 / 1e9
            key = f"pageable_rows_{'+'.join(group)}_t{t}"
            result["rates_gb_s"][key] = {"s": best, "gb": gb, "gb_s": gb / best}
            print(f"pageable rows to {'+'.join(group)}, {t} threads each: {best:.3f} s, {gb / best:5.1f} GB/s", flush=True)


if __name__ == "__main__":
    main()
