"""Summation study (issue 20 part 2; seed ch. 6): error of streamed per-texel sums against exact sums.

    .venv/bin/python benchmarks/summation.py --out benchmarks/results/summation_cpu

For 10^3..10^7 terms (3 colour channels per photo, so 333..3.3M photos of one texel) and the chapter-6 sign
mixes (fit/kernels/summation.py: all-positive error sums, mixed-sign gradient sums), each row is summed as
the fit's passes sum it (a thread adds photo after photo in registers): naive float32, Kahan float32 (the
passes' ``kahan_add``), float64, and a pairwise float32 tree for comparison. Exact: ``math.fsum`` of the
float32 terms (the correctly rounded float64 of the exact sum; its own error, 1.1e-16 relative, is far
below every float32 error measured). Errors: |sum - exact| / |exact| (the relative error) and
|sum - exact| / sum |term| (normalised by the terms' magnitude: for mixed signs the relative error is
unbounded as the sum cancels). Writes summation.json and summation.png.
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np

SIZES = (1_000, 3_000, 6_000, 10_000, 30_000, 100_000, 300_000, 1_000_000, 3_000_000, 10_000_000)
METHODS = ("fp32", "fp32_kahan", "fp64", "pairwise")


def measure(sizes, trials: int, device: str) -> list[dict]:
    from texstream.fit.kernels.summation import ERROR_SUMS, GRADIENT_SUMS, streamed_sums, study_terms

    rows = []
    for kind in ERROR_SUMS + GRADIENT_SUMS:
        for k, n in enumerate(sizes):
            terms = study_terms(kind, trials, n, seed=1000 * k + 7)
            exact = np.array([math.fsum(t.astype(np.float64).tolist()) for t in terms])
            magnitude = np.abs(terms.astype(np.float64)).sum(axis=1)
            row = {"kind": kind, "terms": n, "photos": n // 3, "trials": trials}
            for m in METHODS:
                t0 = time.perf_counter()
                s = streamed_sums(terms, m, device)
                row[f"{m}_seconds"] = time.perf_counter() - t0
                err = np.abs(s - exact)
                row[f"{m}_rel"] = float(np.max(err / np.abs(exact)))
                row[f"{m}_norm"] = float(np.max(err / magnitude))
            rows.append(row)
            print(kind, n, {m: f"{row[m + '_rel']:.2e}" for m in METHODS}, flush=True)
    return rows


def safe_photo_count(rows: list[dict], method: str, tolerance: float) -> int:
    """The largest photo count up to which every error sum with ``method`` stayed within ``tolerance``
    relative (at that size and every smaller one)."""
    from texstream.fit.kernels.summation import ERROR_SUMS

    sizes = sorted({r["terms"] for r in rows})
    safe = 0
    for n in sizes:
        worst = max(r[f"{method}_rel"] for r in rows if r["terms"] == n and r["kind"] in ERROR_SUMS)
        if worst > tolerance:
            break
        safe = n // 3
    return safe


def plot(rows: list[dict], path: Path, threshold_photos: int) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from texstream.fit.kernels.summation import ERROR_SUMS, GRADIENT_SUMS

    fig, axes = plt.subplots(1, 2, figsize=(12, 4.6), sharex=True)
    colours = {"fp32": "C3", "fp32_kahan": "C0", "fp64": "C2", "pairwise": "C1"}
    styles = ["-", "--", ":"]
    for ax, kinds, metric, title in ((axes[0], ERROR_SUMS, "rel", "error sums (all positive): |s - S| / S"),
                                     (axes[1], GRADIENT_SUMS, "norm", "gradient sums (mixed sign): |s - S| / sum |x|")):
        for ls, kind in zip(styles, kinds):
            sel = [r for r in rows if r["kind"] == kind]
            x = [r["photos"] for r in sel]
            for m in METHODS:
                y = [max(r[f"{m}_{metric}"], 1e-17) for r in sel]
                ax.loglog(x, y, ls, color=colours[m], label=f"{m}, {kind}")
        ax.axhline(1e-5, color="k", lw=0.8)
        ax.axvline(threshold_photos, color="grey", lw=0.8, ls="-.")
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("photos per texel (3 terms each)")
        ax.grid(True, which="major", alpha=0.3)
        ax.legend(fontsize=6, ncol=2)
    axes[0].set_ylabel("worst error over trials")
    fig.suptitle(f"streamed sums against exact (0 drawn at 1e-17); 1e-5 line; fp32 safe up to {threshold_photos} photos", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/summation_cpu"))
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--trials", type=int, default=4, help="independent rows per size and sign mix")
    ap.add_argument("--max-terms", type=int, default=SIZES[-1])
    a = ap.parse_args()
    import warp as wp

    wp.config.quiet = True
    from texstream.core.outputs import write_atomic_with, write_json_atomic
    from texstream.fit.stream.config import FP32_SAFE_PHOTOS, FP32_SAFE_TOLERANCE

    sizes = [n for n in SIZES if n <= a.max_terms]
    rows = measure(sizes, a.trials, a.device)
    derived = safe_photo_count(rows, "fp32", FP32_SAFE_TOLERANCE)
    result = {"device": a.device, "trials": a.trials, "sizes": sizes, "rows": rows,
              "fp32_safe_tolerance": FP32_SAFE_TOLERANCE, "fp32_safe_photos_measured": derived,
              "fp32_safe_photos_used": FP32_SAFE_PHOTOS,
              "worst_rel_at_largest": {m: max(r[f"{m}_rel"] for r in rows if r["terms"] == sizes[-1]
                                              and r["kind"].startswith("error")) for m in METHODS}}
    write_json_atomic(a.out / "summation.json", result, indent=1)
    png = a.out / "summation.png"
    tmp = a.out / ".summation.tmp.png"
    plot(rows, tmp, FP32_SAFE_PHOTOS)
    write_atomic_with(png, lambda fh: fh.write(tmp.read_bytes()))
    tmp.unlink()
    print(f"fp32 naive within {FP32_SAFE_TOLERANCE:g} up to {derived} photos (used: {FP32_SAFE_PHOTOS}); "
          f"wrote {a.out}")


if __name__ == "__main__":
    main()
