"""Parameter maps as float EXR files: how a synthetic set's ground truth (``ground_truth/``) and a fitted
model folder store a texture's per-texel parameters, and how they are read back."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from texstream.capture.imageio import read_image, write_image


VIEW_TERM_NAMES = ("vx", "vy", "vxx", "vxy", "vyy")  # render/layout.py VIEW_TERMS (capture/ imports no fit/)


def write_param_maps(folder: Path, params: np.ndarray, layout) -> dict[str, str]:
    """Parameter maps as float EXR: rho_d.exr (RGB), per lobe lobe{j}_rho_s.exr (RGB) and
    lobe{j}_shape.exr ([c_xy, c_z, n] or, anisotropic, RGBA [c_x, c_y, c_z, n]); a radiance
    layout (render/layout.py) writes radiance.exr (RGB L), and the view-dependent one also
    view_{term}.exr (RGB coefficient of each view term, e.g. view_vx.exr); a layout with an ambient radiance
    (``ambient_offset`` >= 0) also ambient.exr (RGB), one with the room light (``room_offset`` >= 0)
    room_irradiance.exr (RGB S)."""

    if getattr(layout, "is_radiance", False):
        write_image(folder / "radiance.exr", params[..., 0:3], bits=32)
        files = {"radiance": "radiance.exr"}
        for k in range(getattr(layout, "view_terms", 0)):
            name = f"view_{VIEW_TERM_NAMES[k]}"
            o = layout.view_offset(k)
            write_image(folder / f"{name}.exr", params[..., o:o + 3], bits=32)
            files[name] = f"{name}.exr"
        return files
    files = {"rho_d": "rho_d.exr"}
    write_image(folder / "rho_d.exr", params[..., 0:3], bits=32)
    for j in range(layout.n_lobes):
        o = layout.lobe_offset(j)
        write_image(folder / f"lobe{j}_rho_s.exr", params[..., o:o + 3], bits=32)
        write_image(folder / f"lobe{j}_shape.exr", params[..., o + 3:o + layout.lobe_stride], bits=32)
        files[f"lobe{j}_rho_s"] = f"lobe{j}_rho_s.exr"
        files[f"lobe{j}_shape"] = f"lobe{j}_shape.exr"
    o = getattr(layout, "ambient_offset", -1)
    if o >= 0:
        write_image(folder / "ambient.exr", params[..., o:o + 3], bits=32)
        files["ambient"] = "ambient.exr"
    o = getattr(layout, "room_offset", -1)
    if o >= 0:  # the room light's per-texel irradiance factor S = pi T.L (the light itself is in model.json)
        write_image(folder / "room_irradiance.exr", params[..., o:o + 3], bits=32)
        files["room_irradiance"] = "room_irradiance.exr"
    return files


def read_param_maps(folder: str | os.PathLike, layout) -> np.ndarray:
    """(H, W, P) float32 parameter grid from the EXR maps :func:`write_param_maps` wrote."""

    g = Path(folder)
    if getattr(layout, "is_radiance", False):
        maps = [read_image(g / "radiance.exr", channels=3)]
        maps += [read_image(g / f"view_{VIEW_TERM_NAMES[k]}.exr", channels=3)
                 for k in range(getattr(layout, "view_terms", 0))]
        return np.concatenate(maps, axis=-1).astype(np.float32)
    maps = [read_image(g / "rho_d.exr", channels=3)]
    for j in range(layout.n_lobes):
        maps.append(read_image(g / f"lobe{j}_rho_s.exr", channels=3))
        maps.append(read_image(g / f"lobe{j}_shape.exr", channels=layout.lobe_stride - 3))
    if getattr(layout, "ambient_offset", -1) >= 0:
        maps.append(read_image(g / "ambient.exr", channels=3))
    if getattr(layout, "room_offset", -1) >= 0:
        maps.append(read_image(g / "room_irradiance.exr", channels=3))
    return np.concatenate(maps, axis=-1).astype(np.float32)
