"""How fast the fit's loader decodes a capture's photos, by decode threads and OpenEXR's own threads (JSON).

    python benchmarks/decode_threads.py --capture CAPTURE --out DIR [--threads 1,8,16] [--exr-threads -1,0,1] [--raw]
        [--processes 8,16 [--reader-threads 1,0]]

Decodes every photo of CAPTURE (with its mask) into a slot buffer the way the fit's set-up does
(``fit/photo_stream.py`` ``PhotoLoader``: cropped to the object's footprint, only the crop's rows read), in
chunks of 64 photos, for each number of decode threads and each OpenImageIO ``exr_threads`` setting
(OpenEXR's thread pool: -1 leaves OpenImageIO's default, 0 turns it off, N sizes it), and once with
whole photos read and cropped afterwards (``--whole``). Reports milliseconds per photo of wall time and
the throughput in decoded megabytes per second. The crops are computed on ``--device`` (cpu or cuda:N).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

from gitinfo import commit


def decode_with_loader(files, crops, sizes, images, masks, threads: int, decoder: str, reader_threads: int,
                       pipelined: bool, decoded_mb: float) -> dict:
    """Wall time of the fit's loader (``PhotoLoader``, ``decoder`` threads or processes) filling every photo in
    chunks of ``images``' length; ``pipelined``: the next chunk submitted before the current one is waited for
    (as the set-up's upload does). A pool of processes is started first, its start timed apart."""
    import time

    from texstream.fit.stream import decode_pool
    from texstream.fit.stream.photo_stream import PhotoLoader, wait

    t0 = time.perf_counter()
    if decoder == "processes":
        pool = decode_pool.start(threads, reader_threads)
        for w in pool.workers:  # every worker up, its readers imported
            w.call(os.getpid, ())
    t1 = time.perf_counter()
    loader = PhotoLoader(files, None, crops, sizes, threads, decoder=decoder)
    n, chunk = len(files.paths), len(images) // 2
    pending = None
    for turn, b in enumerate(range(0, n, chunk)):
        c, half = min(chunk, n - b), (turn % 2) * chunk
        futures = loader.submit(range(b, b + c), images[half:half + c],
                                masks[half:half + c] if loader.has_masks else None)
        if not pipelined:
            wait(futures)
        elif pending is not None:
            wait(pending)
        pending = futures
    wait(pending or [])
    wall = time.perf_counter() - t1
    loader.close()
    return {"decoder": decoder, "threads_or_processes": threads, "reader_threads": reader_threads,
            "pipelined": pipelined, "photos": n, "pool_start_s": t1 - t0, "wall_s": wall,
            "ms_per_photo": 1000 * wall / n, "decoded_mb_per_s": decoded_mb / wall}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--capture", required=True)
    ap.add_argument("--out", required=True)
    ap.add_argument("--threads", default="1,8,16")
    ap.add_argument("--exr-threads", default="-1,0", help="OpenImageIO exr_threads values (-1: leave the default)")
    ap.add_argument("--whole", action="store_true", help="also read whole photos (no row crop)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--limit", type=int, default=0, help="first N photos only (0: all)")
    ap.add_argument("--raw", action="store_true", help="also time OpenImageIO's reads alone (the crop's rows of each "
                                                      "photo, no mask, no conversion or checks) on the same threads")
    ap.add_argument("--processes", default="", help="also decode with the loader's worker processes "
                                                    "(fit/decode_pool.py), pools of these sizes, e.g. 8,16, against "
                                                    "4 threads; chunks waited for and pipelined")
    ap.add_argument("--reader-threads", default="1,0", help="with --processes: each worker's reader threads "
                                                           "(decode_pool.READER_THREADS; 0: the reader's default)")
    a = ap.parse_args()

    import numpy as np
    import OpenImageIO as oiio
    import warp as wp

    wp.config.quiet = True
    wp.init()
    from texstream.capture.capture_json import read_capture
    from texstream.fit.stream.photo_stream import PhotoLoader, crop_boxes
    from texstream.render.camera import ImageInfo, PhotoFrame, image_infos, struct_array
    from texstream.fit.stages.stage import load_geometry, photo_files

    cap = Path(a.capture)
    capture = read_capture(cap)
    frames = capture.frames[:a.limit] if a.limit else capture.frames
    mesh, _ = load_geometry(cap / "ground_truth", 64, "cpu")
    pf = [PhotoFrame.from_capture_frame(f) for f in frames]
    lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
    infos = image_infos(pf, None, 0.5 * (lo + hi), 0.5 * float(np.linalg.norm(hi - lo)), 0)
    sizes = np.array([[f.height, f.width] for f in pf], np.int64)
    points = wp.array(np.asarray(mesh.vertices, np.float32), dtype=wp.vec3, device=a.device)
    crops = crop_boxes(points, struct_array(infos, ImageInfo, a.device), sizes[:, 1], sizes[:, 0], a.device)
    files = photo_files(capture, frames)
    n = len(frames)
    hmax, wmax = int(crops[:, 3].max()), int(crops[:, 2].max())
    chunk = 64
    images = np.empty((chunk, hmax, wmax, 3), np.float32)
    masks = np.empty((chunk, hmax, wmax), np.uint8)
    decoded_mb = float((crops[:, 2] * crops[:, 3]).sum()) * 12 / 1e6
    rows = []
    for exr_threads in [int(x) for x in a.exr_threads.split(",")]:
        if exr_threads >= 0:
            oiio.attribute("exr_threads", exr_threads)
        for threads in [int(x) for x in a.threads.split(",")]:
            for whole in ([False, True] if a.whole else [False]):
                loader = PhotoLoader(files, None, None if whole else crops, sizes, threads)
                if whole:  # the whole photo decoded, the crop cut afterwards (what the set-up did before)
                    loader.crops = None
                    buf_i = np.empty((chunk, int(sizes[:, 0].max()), int(sizes[:, 1].max()), 3), np.float32)
                    buf_m = np.empty(buf_i.shape[:3], np.uint8)
                else:
                    buf_i, buf_m = images, masks
                t0 = time.perf_counter()
                for b in range(0, n, chunk):
                    c = min(chunk, n - b)
                    loader.fill(range(b, b + c), buf_i[:c], buf_m[:c] if loader.has_masks else None)
                wall = time.perf_counter() - t0
                loader.close()
                row = {"exr_threads": exr_threads, "threads": threads, "whole": whole, "photos": n, "wall_s": wall,
                       "ms_per_photo": 1000 * wall / n, "decoded_mb_per_s": decoded_mb / wall}
                rows.append(row)
                print(json.dumps(row), flush=True)
    if a.raw:  # the reads alone: does the loader's own work (masks, checks, copies) or the decoding bound it?
        import concurrent.futures

        from texstream.capture.imageio import _read_raw

        def read(k):
            y0, ch = int(crops[k, 1]), int(crops[k, 3])
            return _read_raw(files.paths[k], (y0, y0 + ch))[0].shape

        for threads in [int(x) for x in a.threads.split(",")]:
            with concurrent.futures.ThreadPoolExecutor(threads) as pool:
                t0 = time.perf_counter()
                list(pool.map(read, range(n)))
                wall = time.perf_counter() - t0
            row = {"raw_reads": True, "threads": threads, "photos": n, "wall_s": wall, "ms_per_photo": 1000 * wall / n,
                   "decoded_mb_per_s": decoded_mb / wall}
            rows.append(row)
            print(json.dumps(row), flush=True)
    if a.processes:  # the fit's loader with threads against worker processes, chunks waited for or pipelined
        two = np.empty((2 * chunk, hmax, wmax, 3), np.float32), np.empty((2 * chunk, hmax, wmax), np.uint8)
        configs = [("threads", t, -1) for t in (4,)] + [
            ("processes", p, r) for p in (int(x) for x in a.processes.split(",") if x.strip())
            for r in (int(x) for x in a.reader_threads.split(","))]
        for decoder, count, reader_threads in configs:
            for pipelined in (False, True):
                row = decode_with_loader(files, crops, sizes, *two, count, decoder, reader_threads, pipelined,
                                         decoded_mb)
                rows.append(row)
                print(json.dumps(row), flush=True)
        from texstream.fit.stream import decode_pool

        decode_pool.shutdown()
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "decode_threads.json").write_text(json.dumps(
        {"command": "python benchmarks/decode_threads.py " + " ".join(f"--{k.replace('_', '-')} {v}" for k, v in
                                                                       vars(a).items()),
         "commit": commit(), "machine": platform.node(), "cpus": os.cpu_count(), "capture": str(cap),
         "stored_photo_size": [hmax, wmax], "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
