"""Say so when a fit will compile its Warp kernels (issue 40: a cold start was 90 s of silence on a fresh GPU).

Warp compiles a module on its first launch and keeps the binary in its kernel cache
(``wp.config.kernel_cache_dir``); later runs load it in milliseconds. Warp has no hook before a compile, so
texstream keeps its own marker beside the cache: one file per (texstream kernel sources, Warp version,
device kind), written after a fit on that device succeeded. The first fit that finds no marker says the
kernels are being built and where they are cached, and builds the default run's modules in parallel
(fit/stages/prewarm.py). The first ``python3 scripts/dev.py demo`` (or any
first fit) warms the cache for the CPU or GPU it ran on.
"""

from __future__ import annotations

import functools
import hashlib
from pathlib import Path

import warp as wp

from texstream.fit.kernels.overloads import declared_precisions

KERNEL_FOLDERS = ("render", "fit", "geometry")
"""the texstream folders whose modules hold Warp kernels (their sources make the marker's key)"""

COLD_SECONDS = {"cpu": "about half a minute on 2 CPU cores", "cuda": "about 10 s on a GPU"}
"""what a cold build of a default fit's kernels takes, as the notice says it (docs/scale.md, issue 40)"""


@functools.cache
def kernel_sources_key() -> str:
    """A hash of the texstream sources that define kernels and of Warp's version: another texstream or Warp
    compiles again."""
    root = Path(__file__).resolve().parents[2]
    h = hashlib.sha256(wp.config.version.encode())
    for folder in KERNEL_FOLDERS:
        for path in sorted((root / folder).rglob("*.py")):
            h.update(path.relative_to(root).as_posix().encode())
            h.update(path.read_bytes())
    return h.hexdigest()[:16]


def _marker(device: str, precision: str = "fp32", group: str | None = "default") -> Path:
    wp.init()  # sets the kernel cache folder
    kind = "cuda" if str(device).startswith("cuda") else "cpu"
    if kind == "cuda":  # binaries are per GPU architecture
        kind += f"-sm{wp.get_device(device).arch}"
    # a process that declared float64 builds modules with those overloads too (fit/kernels/overloads.py): other
    # hashes, another marker, whatever precision this fit uses
    declared = [p for p in declared_precisions() if p != "fp32"] + ([precision] if precision != "fp32" else [])
    suffix = "".join(f"-{p}" for p in dict.fromkeys(declared))
    # one marker per group of models built ahead together (fit/stages/prewarm.py KERNEL_GROUPS)
    suffix += "" if group == "default" else f"-{group or 'other'}"
    return Path(wp.config.kernel_cache_dir or "") / f"texstream-{kernel_sources_key()}-{kind}{suffix}.warm"


_ANNOUNCED: set = set()


def kernels_cold(device: str, precision: str = "fp32", group: str | None = "default") -> bool:
    """Whether this texstream's kernels of compute ``precision`` for the models of ``group`` were never built on
    ``device``'s kind in Warp's cache: true at most once per process, device, precision and group (the first fit
    there says so and builds them, fit/stages/prewarm.py)."""
    if (device, precision, group) in _ANNOUNCED:
        return False
    _ANNOUNCED.add((device, precision, group))
    try:
        return not _marker(device, precision, group).exists()
    except OSError:
        return False


def kernel_build_line(device: str, how: str = "") -> str:
    """The notice of a cold build on ``device``; ``how`` says how it is built."""
    kind = "cuda" if str(device).startswith("cuda") else "cpu"
    return (f"first fit of this texstream on {device}: compiling its Warp kernels ({COLD_SECONDS[kind]}"
            + (f"; {how}" if how else "") + f"); they are kept in {wp.config.kernel_cache_dir} and later runs "
            "start at once")


def mark_kernels_built(device: str, precision: str = "fp32", group: str | None = "default") -> None:
    """Record that a fit on ``device`` of compute ``precision`` succeeded, so its kernels are in the cache (best
    effort: a cache folder that cannot be written only means the notice shows again)."""
    try:
        marker = _marker(device, precision, group)
        marker.parent.mkdir(parents=True, exist_ok=True)
        marker.touch()
    except OSError:
        pass
