"""Environment light files, read and written in render/sh.py's convention.

Two formats, told by the extension: a latitude-longitude environment map (``.exr`` / ``.hdr``: linear
radiance, row 0 the zenith +z, projected on the 9 SH functions by ``sh.project_latlong``), or JSON
``{"sh": [[r, g, b] x 9]}`` (the coefficients themselves, as a model folder's light.json holds them). Every
problem is one InputError naming the file and the fix. OpenImageIO loads inside capture.imageio's functions.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from texstream.capture.imageio import read_image
from texstream.core.errors import InputError
from texstream.core.outputs import read_json, write_json_atomic
from texstream.render import sh

MAP_EXTENSIONS = (".exr", ".hdr")
FIX = "give a linear latitude-longitude map (.exr / .hdr, row 0 the zenith +z: render/sh.py) or a JSON file " \
      "{\"sh\": [[r, g, b] x 9]}"


def read_light(path) -> np.ndarray:
    """(9, 3) float64 SH light of an environment file."""
    p = Path(path)
    if not p.is_file():
        raise InputError("environment light file not found", p, FIX)
    ext = p.suffix.lower()
    if ext == ".json":
        data = read_json(p, what="environment light")
        coeffs = data.get("sh") if isinstance(data, dict) else None
        try:
            light = np.asarray(coeffs, dtype=np.float64)
        except (TypeError, ValueError):
            light = np.zeros(0)
        if light.shape != (sh.SH_COUNT, 3) or not np.all(np.isfinite(light)):
            raise InputError(f"environment light JSON needs \"sh\": 9 rows of 3 finite numbers (got shape "
                             f"{light.shape if coeffs is not None else 'none'})", p, FIX)
        return light
    if ext not in MAP_EXTENSIONS:
        raise InputError(f"environment light file has an unknown extension {ext or '(none)'!r}", p, FIX)
    env = read_image(p, channels=3)  # an unreadable file: read_image's InputError names it
    h, w = env.shape[:2]
    if h < 2 or w != 2 * h:
        raise InputError(f"environment map is {w}x{h} pixels, a latitude-longitude map is twice as wide as high",
                         p, FIX)
    if not np.all(np.isfinite(env)) or env.min() < 0:
        raise InputError("environment map has negative or non-finite radiance", p, FIX)
    return sh.project_latlong(env)


def light_json(light: np.ndarray) -> dict:
    """The JSON form of an SH light (what :func:`read_light` reads back)."""
    return {"sh": [[float(v) for v in row] for row in np.asarray(light, np.float64)],
            "convention": "render/sh.py: order-2 real SH, (l, m) = (0,0), (1,-1), (1,0), (1,1), (2,-2), (2,-1), "
                          "(2,0), (2,1), (2,2); rows per coefficient, columns r, g, b; world +z up"}


def write_light_json(path, light: np.ndarray) -> None:
    write_json_atomic(Path(path), light_json(light))
