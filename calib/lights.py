"""Lights: a lights file per photo, and a light fixed to the camera (flash / co-located).

Lights file (JSON, world frame, conventions of :mod:`texstream.capture.conventions`)::

    {"default": {"type": "point", "position": [x, y, z], "intensity": [r, g, b]},
     "frames": {"IMG_0001": {"type": "directional", "direction": [..], "intensity": [..]}}}

Frames are matched by file name or stem; ``default`` applies to the others. A co-located light
(``--colocated-light INTENSITY``) is a point light at the camera centre, or at ``offset`` in the
camera's OpenCV axes (a flash beside the lens), derived from each registered pose.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from texstream.capture.capture_json import Light
from texstream.pipelines.errors import InputError


def load_lights_file(path: str | os.PathLike) -> tuple[Light | None, dict[str, Light]]:
    """Read a lights file: (default light or None, {frame name or stem: light})."""
    from texstream.capture.capture_json import _light_from
    from texstream.pipelines.stage import read_json

    p = Path(path)
    data = read_json(p, what="lights file")
    if not isinstance(data, dict) or not ("default" in data or "frames" in data):
        raise InputError("lights file needs a 'default' light and/or a 'frames' mapping", p,
                         'write {"default": {"type": "point", "position": [..], "intensity": [..]}}')
    default = _light_from(data["default"], "default", p) if data.get("default") else None
    frames = {str(k): _light_from(v, f"frames[{k!r}]", p) for k, v in (data.get("frames") or {}).items()}
    return default, frames


def colocated_light(r: np.ndarray, t: np.ndarray, intensity, offset=(0.0, 0.0, 0.0)) -> Light:
    """Point light fixed to a camera with world-to-camera (R, t): at the centre plus ``offset`` (camera axes)."""
    r = np.asarray(r, dtype=np.float64)
    pos = r.T @ (np.asarray(offset, dtype=np.float64).reshape(3) - np.asarray(t, dtype=np.float64).reshape(3))
    inten = np.broadcast_to(np.asarray(intensity, dtype=np.float64), (3,))
    return Light.point(pos, inten)
