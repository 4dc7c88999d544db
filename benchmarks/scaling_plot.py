"""Plots and a table of the scaling study (benchmarks/setup_time.py runs from disk; writes PNG and Markdown).

    python benchmarks/scaling_plot.py benchmarks/results/scaling_h100

Reads the folder's ``disk_device_N.json`` (every photo decoded once into device memory), ``disk_stream_N.json`` /
``disk_stream_N_recompute.json`` (streamed from disk through the photo cache under a memory cap) and
``size_220photos_S.json`` (220 photos of S x S pixels, cropped to the object), and writes ``scaling.png`` (time
to a converged model and per-pass time against the photo count; peak host and device memory against the
photo count; set-up and device memory against the image size) and ``scaling.md`` (the same figures as a table).
"""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path


def runs(folder: Path, pattern: str) -> list[tuple[int, dict]]:
    out = []
    for p in folder.glob("*.json"):
        m = re.fullmatch(pattern, p.stem)
        if m:
            run = next(iter(json.loads(p.read_text())["runs"].values()))
            out.append((int(m.group(1)), run))
    return sorted(out, key=lambda r: r[0])


def converged(r: dict) -> float:
    """Seconds from reading the folder to a converged model: the set-up and the fit to within 0.1 dB of its best,
    and for streamed photos also the first passes (the warm-up fit: the initial guess and one iteration, which
    decode every photo into the cache)."""
    return r["converged_model_s"] + (0.0 if r["residency"] == "device" else r["warmup_fit_s"])


def main() -> None:
    folder = Path(sys.argv[1] if len(sys.argv) > 1 else "benchmarks/results/scaling_h100")
    device = runs(folder, r"disk_device_(\d+)")
    stream = [r for r in runs(folder, r"disk_stream_(\d+)(?:_recompute)?") if not r[1].get("residency_reason", "")
              .endswith("kept on the device")]
    sizes = runs(folder, r"size_220photos_(\d+)")
    rows = ["| photos from disk | photos | stored crop | set-up (s) | first passes, decoding (s) | later pass (ms) | "
            "converged model (s) | peak host RSS (MiB) | device peak (MiB) |",
            "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for name, rs in (("all on the device", device), ("streamed from the photo cache, maps per window", stream),
                     ("220 photos, all on the device", sizes)):
        for key, r in rs:
            first = "" if r["residency"] == "device" else f"{r['warmup_fit_s']:.2f}"
            rows.append(f"| {name} | {r['photos']} | {r['stored_photo_size'][1]}x{r['stored_photo_size'][0]} | "
                        f"{r['setup_s']:.2f} | {first} | {r['pass_ms']:.1f} | {converged(r):.2f} | "
                        f"{r['peak_rss_mib']:.0f} | {r.get('device_peak_mib') or 0:.0f} |")
    (folder / "scaling.md").write_text("\n".join(rows) + "\n")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 3, figsize=(15, 4))
    n = [k for k, _ in device]
    ax[0].loglog(n, [converged(r) for _, r in device], "o-", label="converged model, all on the device (s)")
    ax[0].loglog([k for k, _ in stream], [converged(r) for _, r in stream], "d-",
                 label="converged model, streamed (s)")
    ax[0].loglog([k for k, _ in stream], [r["pass_ms"] / 1000 for _, r in stream], "s-",
                 label="one pass streamed from the photo cache (s)")
    ax[0].loglog(n, [r["pass_ms"] / 1000 for _, r in device], "^-", label="one pass, all on the device (s)")
    ax[0].set_xlabel("photos (430x430, float EXR)")
    ax[0].legend(fontsize=8)
    ax[1].semilogx(n, [r["peak_rss_mib"] for _, r in device], "o-", label="host, all on the device")
    ax[1].semilogx(n, [r.get("device_peak_mib") or 0 for _, r in device], "o--", label="device, all on the device")
    ax[1].semilogx([k for k, _ in stream], [r["peak_rss_mib"] for _, r in stream], "s-", label="host, streamed")
    ax[1].semilogx([k for k, _ in stream], [r.get("device_peak_mib") or 0 for _, r in stream], "s--",
                   label="device, streamed")
    ax[1].set_xlabel("photos")
    ax[1].set_ylabel("peak memory (MiB)")
    ax[1].legend(fontsize=8)
    s = [k for k, _ in sizes]
    ax[2].loglog(s, [r["setup_s"] for _, r in sizes], "o-", label="set-up from disk (s)")
    ax[2].loglog(s, [(r.get("device_peak_mib") or 0) / 1024 for _, r in sizes], "s-", label="device peak (GiB)")
    ax[2].set_xlabel("image side (220 photos)")
    ax[2].legend(fontsize=8)
    fig.suptitle("full ornament (95,136 texels), LM, photos from a capture folder on disk; " + folder.name)
    fig.tight_layout()
    fig.savefig(folder / "scaling.png", dpi=100)
    print((folder / "scaling.md").read_text())


if __name__ == "__main__":
    main()
