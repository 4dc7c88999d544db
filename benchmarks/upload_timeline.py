"""Where the photos' upload spends its time (fit/stream/photo_set.py upload_photo_sets, one GPU): the pinned buffers'
allocation, the main thread waiting for each chunk's crops and for each buffer's last copy, and the final
synchronisation, per pipeline shape (buffers, chunk size, crop threads, the interpreter's switch interval).
The full ornament's 1,760 photos of 430x430 (rendered in memory), the fastest of 3 set-ups per shape; writes
JSON and prints a log.

    python benchmarks/upload_timeline.py OUT_DIR [DEVICE]     # on a CUDA machine
"""

from __future__ import annotations

import json
import os
import sys
import time

import warp as wp

import texstream.fit.stream.photo_set as P
from gitinfo import commit
from photo_split_scene import OrnamentAt4x

wp.config.quiet = True
wp.init()
DEVICE = sys.argv[2] if len(sys.argv) > 2 else "cuda:0"
SHAPES = {  # name: (buffers, chunk MiB, crop threads, switch interval s)
    "2 x 16 MiB, 8 threads, 5 ms": (2, 16, 0, 5e-3),
    "2 x 16 MiB, 8 threads, 0.1 ms": (2, 16, 0, 1e-4),
    "2 x 16 MiB, 8 threads, 0.5 ms": (2, 16, 0, 5e-4),
    "4 x 16 MiB, 8 threads, 0.1 ms": (4, 16, 0, 1e-4),
    "2 x 16 MiB, 4 threads, 0.1 ms": (2, 16, 4, 1e-4),
    "3 x 16 MiB, 12 threads, 0.1 ms": (3, 16, 12, 1e-4),
}


class Recorder:
    """Wraps the pipeline's waits and the pinned allocation to time them."""

    def __init__(self):
        self.rows = {"crop_wait_s": 0.0, "buffer_wait_s": 0.0, "pinned_alloc_s": 0.0, "chunks": 0}
        self.real_wait, self.real_event, self.real_empty = P.wait, wp.synchronize_event, wp.empty

    def __enter__(self):
        rows = self.rows

        def wait(futures):
            t = time.perf_counter()
            self.real_wait(futures)
            rows["crop_wait_s"] += time.perf_counter() - t
            rows["chunks"] += 1

        def sync_event(event):
            t = time.perf_counter()
            self.real_event(event)
            rows["buffer_wait_s"] += time.perf_counter() - t

        def empty(*args, **kwargs):
            t = time.perf_counter()
            a = self.real_empty(*args, **kwargs)
            if kwargs.get("pinned"):
                rows["pinned_alloc_s"] += time.perf_counter() - t
            return a

        P.wait, P.wp.synchronize_event, P.wp.empty = wait, sync_event, empty
        return self

    def __exit__(self, *exc):
        P.wait, P.wp.synchronize_event, P.wp.empty = self.real_wait, self.real_event, self.real_empty


scene = OrnamentAt4x(DEVICE)
scene.photoset(DEVICE)  # compiles and loads every kernel
out = {"commit": commit(), "device": wp.get_device(DEVICE).name, "shapes": {}}
for name, (slots, mib, threads, switch) in SHAPES.items():
    P.UPLOAD_SLOTS, P.ARRAY_UPLOAD_CHUNK_BYTES, P.UPLOAD_SWITCH_INTERVAL_S = slots, mib << 20, switch
    best = None
    for _ in range(3):
        wp.synchronize_device(DEVICE)
        with Recorder() as rec:
            t0 = time.perf_counter()
            ps = scene.photoset(DEVICE, decode_threads=threads)
            wp.synchronize_device(DEVICE)
            total = time.perf_counter() - t0
        row = {"photo_set_s": total, **{k: round(v, 4) for k, v in ps.timings.items()}, **rec.rows}
        if best is None or row["upload"] < best["upload"]:
            best = row
        del ps
    out["shapes"][name] = best
    print(f"{name:32s} upload {best['upload']:.3f} s: pinned alloc {best['pinned_alloc_s']:.3f}, waiting for crops "
          f"{best['crop_wait_s']:.3f} ({best['chunks']} chunks), for buffers {best['buffer_wait_s']:.3f}; photo set "
          f"{best['photo_set_s']:.3f} s", flush=True)
os.makedirs(sys.argv[1], exist_ok=True)
with open(os.path.join(sys.argv[1], "upload_timeline.json"), "w") as fh:
    json.dump(out, fh, indent=1)
