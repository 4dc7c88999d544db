"""Time the glTF core-material fit (fit/models/lafortune/gltf_core.py, the export's per-texel fit) on a model folder,
and, with --before, an earlier version of the module on the same grid, with the largest difference of their maps.

    python benchmarks/gltf_core_speed.py out/demo/model [--device cpu] [--before OLD_gltf_core.py]

(OLD_gltf_core.py: e.g. `git show 8e6e26c:fit/models/lafortune/gltf_core.py > /tmp/old.py`; a version before the
Warp kernel takes no device. The kernel's time is given warm: a first call compiles it, timed apart.)
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
import time

import numpy as np

from texstream.fit.models.lafortune import gltf_core
from texstream.fit.models.registry import load_model_folder


def timed(module, grid, layout, *device) -> tuple[float, object]:
    h, w, _ = grid.shape
    old = (np.full((h, w, 3), 0.1), np.full((h, w, 3), 0.04), np.full((h, w, 1), 0.5))  # only scored beside
    t = time.perf_counter()
    core = module.fit_core_material(grid, layout, module.flash_samples(), None, old, *device)
    return time.perf_counter() - t, core


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("model")
    ap.add_argument("--before", help="an earlier gltf_core.py to time beside")
    ap.add_argument("--device", default="cpu")
    a = ap.parse_args()
    m = load_model_folder(a.model)
    s_first, _ = timed(gltf_core, m.grid[:1, :1], m.layout, a.device)
    s_new, new = timed(gltf_core, m.grid, m.layout, a.device)
    print(f"{m.grid.shape[0] * m.grid.shape[1]} texels on {a.device}: {s_new:.2f} s (first call {s_first:.2f} s)")
    if a.before:
        spec = importlib.util.spec_from_file_location("gltf_core_before", a.before)
        before = importlib.util.module_from_spec(spec)
        sys.modules["gltf_core_before"] = before  # its dataclasses look their module up
        spec.loader.exec_module(before)
        s_old, old = timed(before, m.grid, m.layout)
        diff = max(float(np.abs(getattr(new, f) - getattr(old, f)).max())
                   for f in ("base_color", "metallic", "roughness", "specular_f0"))
        print(f"before: {s_old:.2f} s; largest difference of the maps {diff:.2g}")
