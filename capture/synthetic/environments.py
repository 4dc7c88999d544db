"""Procedural environment maps: linear HDR latitude-longitude light for synthetic captures under one environment.

Three built-in lightings, each a closed-form function of direction (so any resolution is the same light,
and every run the same numbers), in render/sh.py's lat-long convention (row 0 the zenith +z, phi from +x
towards +y; radiance in photo values per unit exposure):

- ``sky``: a clear sky (bluish zenith, paler horizon, brown ground) with a soft warm sun 40 degrees up.
- ``room``: an indoor room (warm-grey walls, dark floor, light ceiling) lit by a bright cool window on one
  wall and a warm lamp high on the other side.
- ``studio``: a dark studio with two coloured softboxes (a warm key high behind-left, a cyan rim low in front)
  and a low white bounce card.

Their brightness is set so that a white Lambertian object's brightest photo pixel is about 1 under each (as a
photographer would expose), and their key lights come from different sides: the photos under one, scaled per
channel, score well under 30 dB against the photos under another (benchmarks/relight_env.py's unrelit baseline),
so relighting is needed to reach the issue's 30 dB.

They are kept smooth on purpose (soft edges of 10 degrees or more, a sun some 16 degrees wide): an order-2
SH light (render/sh.py, what the relightable model estimates) then reproduces their diffuse shading to a
few percent (:func:`irradiance_sh_error` measures it), so a relighting benchmark measures the fit, not the
truncation. Sharper maps (a real HDR file) are read with :func:`read_environment`.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
from texstream.capture.imageio import read_image, write_image
from texstream.core.errors import ConfigError, InputError
from texstream.render import sh

ENV_HEIGHT = 128
"""Rows of a built-in map as written to a file (width twice that): 1.4 degree pixels, finer than any feature."""
_SUPERSAMPLE = 4  # sub-pixels per side when a built-in map is made at a given size (area average, not point samples)


def _smoothstep(e0: float, e1: float, x: np.ndarray) -> np.ndarray:
    t = np.clip((x - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _unit(elevation_deg: float, azimuth_deg: float) -> np.ndarray:
    el, az = math.radians(elevation_deg), math.radians(azimuth_deg)
    return np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])


def _soft_disk(d: np.ndarray, elevation_deg: float, azimuth_deg: float, radius_deg: float,
               soft_deg: float) -> np.ndarray:
    """1 inside a cone of ``radius_deg`` about a direction, 0 outside, a smoothstep ``soft_deg`` wide between."""
    ang = np.degrees(np.arccos(np.clip(d @ _unit(elevation_deg, azimuth_deg), -1.0, 1.0)))
    return 1.0 - _smoothstep(radius_deg - soft_deg / 2, radius_deg + soft_deg / 2, ang)


def _soft_rect(d: np.ndarray, elevation_deg: tuple, azimuth_deg: tuple, soft_deg: float) -> np.ndarray:
    """1 inside an elevation x azimuth window (degrees, azimuth not wrapping past +-180), soft edges."""
    el = np.degrees(np.arcsin(np.clip(d[..., 2], -1.0, 1.0)))
    az = np.degrees(np.arctan2(d[..., 1], d[..., 0]))
    s = soft_deg / 2

    def window(x, lo, hi):
        return _smoothstep(lo - s, lo + s, x) * (1 - _smoothstep(hi - s, hi + s, x))

    return window(el, *elevation_deg) * window(az, *azimuth_deg)


def _sky(d: np.ndarray) -> np.ndarray:
    z = d[..., 2:3]
    up = np.clip(z, 0.0, 1.0)
    sky = np.array([0.75, 0.82, 0.92]) * (1 - up) + np.array([0.32, 0.45, 0.75]) * up  # pale horizon, blue zenith
    ground = np.array([0.22, 0.19, 0.15])
    horizon = _smoothstep(-0.17, 0.17, z)  # a 20-degree blend, no crease at the horizon
    # the sun: a von Mises-Fisher lobe exp(k (cos - 1)), k = 25 (1/e half-width 16 degrees)
    sun = np.exp(25.0 * (d @ _unit(40.0, 30.0) - 1.0))[..., None] * np.array([9.0, 8.0, 6.5])
    return ground * (1 - horizon) + sky * horizon + sun


def _room(d: np.ndarray) -> np.ndarray:
    z = d[..., 2:3]
    walls = np.array([0.34, 0.31, 0.26])
    floor = np.array([0.15, 0.12, 0.085])
    ceiling = np.array([0.44, 0.43, 0.41])
    out = (floor * (1 - _smoothstep(-0.45, -0.25, z)) + ceiling * _smoothstep(0.55, 0.75, z)
           + walls * _smoothstep(-0.45, -0.25, z) * (1 - _smoothstep(0.55, 0.75, z)))
    window = _soft_rect(d, (0.0, 40.0), (-90.0, -35.0), 20.0)[..., None] * np.array([3.7, 4.25, 5.1])
    lamp = np.exp(20.0 * (d @ _unit(50.0, 150.0) - 1.0))[..., None] * np.array([7.6, 5.1, 2.2])
    return out + window + lamp


def _studio(d: np.ndarray) -> np.ndarray:
    back = np.full(d.shape[:-1] + (3,), 0.09)
    key = _soft_disk(d, 35.0, -120.0, 22.0, 24.0)[..., None] * np.array([6.6, 3.7, 2.0])
    rim = _soft_disk(d, 10.0, 20.0, 18.0, 24.0)[..., None] * np.array([1.3, 3.3, 5.7])
    fill = _soft_disk(d, -20.0, 120.0, 30.0, 20.0)[..., None] * np.array([1.1, 1.1, 1.1])  # a bounce card, low
    return back + key + rim + fill


ENVIRONMENTS = {"sky": _sky, "room": _room, "studio": _studio}
"""Built-in environments: name -> radiance as a function of (..., 3) unit directions."""


def environment_names() -> list[str]:
    """Names of the built-in environments."""
    return sorted(ENVIRONMENTS)


def make_environment(name: str, height: int = ENV_HEIGHT, width: int | None = None) -> np.ndarray:
    """(height, width, 3) float32 lat-long map of a built-in environment (width: 2 x height unless given),
    each pixel the solid-angle-weighted mean of the closed form over its area (supersampled)."""
    if name not in ENVIRONMENTS:
        raise ConfigError(f"unknown environment {name!r}", fix=f"use one of {environment_names()} or an EXR path")
    width = 2 * height if width is None else width
    dirs, _ = sh.latlong_directions(height * _SUPERSAMPLE, width * _SUPERSAMPLE)
    fine = ENVIRONMENTS[name](dirs)
    return downsample_latlong(fine, height, width)


def downsample_latlong(env: np.ndarray, height: int, width: int) -> np.ndarray:
    """(height, width, C) float32 area average of a lat-long map whose sides are integer multiples of these,
    each source pixel weighted by its solid angle (so the map's integral over the sphere is kept)."""
    env = np.asarray(env, dtype=np.float64)
    h, w = env.shape[:2]
    if h % height or w % width:
        raise ConfigError(f"a {h}x{w} environment map does not divide into {height}x{width}",
                          fix="give a map whose height and width are multiples of the integration grid's "
                              "(e.g. 2:1 maps of 256, 512, 1024 rows' width), or change --env-grid")
    _, omega = sh.latlong_directions(h, w)
    fy, fx = h // height, w // width
    weighted = (env * omega[..., None]).reshape(height, fy, width, fx, -1).sum(axis=(1, 3))
    area = omega.reshape(height, fy, width, fx).sum(axis=(1, 3))
    return (weighted / area[..., None]).astype(np.float32)


def write_environment(path: str | os.PathLike, env: np.ndarray) -> Path:
    """Write a lat-long map as a float32 EXR (any HDR viewer or glTF tool loads it)."""
    return write_image(path, np.asarray(env, dtype=np.float32), bits=32)


def read_environment(path: str | os.PathLike) -> np.ndarray:
    """(H, W, 3) float32 lat-long map from an EXR / HDR file (render/sh.py's convention: row 0 the zenith).

    Raises:
        InputError: unreadable, not 2:1, or negative / non-finite values.
    """
    p = Path(path)
    if not p.is_file():
        raise InputError("environment map not found", p, "give an EXR / HDR lat-long map or a built-in name "
                                                           f"({', '.join(environment_names())})")
    env = read_image(p, channels=3)
    if env.shape[1] != 2 * env.shape[0]:
        raise InputError(f"environment map is {env.shape[1]}x{env.shape[0]}, not a 2:1 latitude-longitude map", p,
                         "convert it to an equirectangular (2:1) map with the zenith in row 0")
    if not np.all(np.isfinite(env)) or env.min() < 0:
        raise InputError("environment map holds negative or non-finite radiance", p, "clip it to [0, inf)")
    return env


def load_environment(name_or_path: str, height: int = ENV_HEIGHT) -> tuple[np.ndarray, str]:
    """(map, name): a built-in environment made at ``height`` rows, or a map file as stored."""
    if name_or_path in ENVIRONMENTS:
        return make_environment(name_or_path, height), name_or_path
    return read_environment(name_or_path), Path(name_or_path).stem


def irradiance(env: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """(N, C) unoccluded irradiance E(n) = integral L(w) max(0, n.w) dw of a lat-long map at unit normals (N, 3),
    by quadrature over its pixels."""
    dirs, omega = sh.latlong_directions(env.shape[0], env.shape[1])
    cos = np.maximum(np.asarray(normals, np.float64) @ dirs.reshape(-1, 3).T, 0.0)
    return cos @ (np.asarray(env, np.float64).reshape(-1, env.shape[2]) * omega.reshape(-1, 1))


def irradiance_sh_error(env: np.ndarray, normal_rows: int = 32) -> dict:
    """How well order-2 SH reproduces a map's diffuse shading: irradiance from the SH-9 projection
    (pi x unoccluded transfer . L, render/sh.py) against the map's own, over normals on a lat-long grid
    (``normal_rows`` x twice that), weighted by their solid angles.

    Returns:
        ``{"rms_relative": ..., "max_relative": ...}``: RMS and largest error over normals and channels,
        relative to the channel's mean irradiance (a dark side's relative error would say nothing).
    """
    normals, omega = sh.latlong_directions(normal_rows, 2 * normal_rows)
    normals, weight = normals.reshape(-1, 3), omega.reshape(-1, 1) / omega.sum()
    exact = irradiance(env, normals)
    coeffs = sh.project_latlong(env)
    approx = math.pi * sh.diffuse_radiance(np.ones_like(exact), sh.unoccluded_transfer(normals), coeffs)
    scale = (exact * weight).sum(axis=0)
    rel = (approx - exact) / scale
    return {"rms_relative": float(np.sqrt(((rel * rel) * weight).sum(axis=0).max())),
            "max_relative": float(np.abs(rel).max())}
