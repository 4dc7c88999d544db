"""Order-2 real spherical harmonics (9 coefficients per colour channel): environment light as few numbers.

One convention for everything that lights a surface by an environment (the synthetic captures under
environment maps, the relightable model's estimated light, ``texstream relight``):

- **Basis**: real SH in the order (l, m) = (0,0), (1,-1), (1,0), (1,1), (2,-2), (2,-1), (2,0), (2,1), (2,2),
  with Ramamoorthi and Hanrahan's constants ("An efficient representation for irradiance environment
  maps", 2001); orthonormal over the sphere.
- **Light**: an environment's radiance L(w) ~ sum_k L[k, c] Y_k(w), ``L`` of shape (9, 3), w the unit
  direction *towards* the light, in world coordinates (texstream's world has +z up).
- **Latitude-longitude maps**: row 0 is the zenith (+z), theta = pi (v + 0.5) / H from +z; column u has
  phi = 2 pi (u + 0.5) / W from +x towards +y; direction (sin t cos p, sin t sin p, cos t).
- **Diffuse transfer**: a Lambertian texel of albedo a (in [0, 1]) under L sends radiance
  a * sum_k T[k] L[k, c], with T[k] = (1 / pi) * integral V(w) max(0, n.w) Y_k(w) dw its transfer vector
  (V the visibility of the environment from the texel). Unoccluded, T[k] = A_l Y_k(n) / pi with
  A_0 = pi, A_1 = 2 pi / 3, A_2 = pi / 4 (the clamped cosine's SH); a constant environment of radiance c
  then gives a * c, as it should.

Everything here is numpy except :func:`sh9_basis_component`, a Warp function (generic over float32 and
float64) for kernels that need the basis at a direction.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import warp as wp

SH_COUNT = 9
SH_BAND = (0, 1, 1, 1, 2, 2, 2, 2, 2)
"""The band l of each coefficient."""
COSINE_LOBE_SH = (math.pi, 2.0 * math.pi / 3.0, math.pi / 4.0)
"""A_l: the clamped cosine max(0, cos) in SH, per band (its irradiance convolution)."""

_C0 = 0.28209479177387814  # 1 / (2 sqrt(pi))
_C1 = 0.4886025119029199  # sqrt(3 / (4 pi))
_C2 = 1.0925484305920792  # sqrt(15 / (4 pi))
_C20 = 0.31539156525252005  # sqrt(5 / (16 pi))
_C22 = 0.5462742152960396  # sqrt(15 / (16 pi))


def sh9_basis(directions: np.ndarray) -> np.ndarray:
    """(..., 9) basis values at unit directions (..., 3); float64."""
    d = np.asarray(directions, dtype=np.float64)
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    return np.stack([np.full_like(x, _C0), _C1 * y, _C1 * z, _C1 * x, _C2 * x * y, _C2 * y * z,
                     _C20 * (3.0 * z * z - 1.0), _C2 * x * z, _C22 * (x * x - y * y)], axis=-1)


@wp.func
def sh9_basis_component(d: Any, k: int, one: Any):
    """Y_k at the unit direction ``d`` (a vec3 of float32 or float64; ``one`` is 1 of its scalar type), in the
    order of :func:`sh9_basis`."""
    if k == 0:
        return type(one)(_C0)
    if k == 1:
        return type(one)(_C1) * d[1]
    if k == 2:
        return type(one)(_C1) * d[2]
    if k == 3:
        return type(one)(_C1) * d[0]
    if k == 4:
        return type(one)(_C2) * d[0] * d[1]
    if k == 5:
        return type(one)(_C2) * d[1] * d[2]
    if k == 6:
        return type(one)(_C20) * (type(one)(3.0) * d[2] * d[2] - one)
    if k == 7:
        return type(one)(_C2) * d[0] * d[2]
    return type(one)(_C22) * (d[0] * d[0] - d[1] * d[1])


def band_factors(values: tuple | list) -> np.ndarray:
    """(9,) a per-band tuple (l = 0, 1, 2) spread over the 9 coefficients."""
    return np.array([values[b] for b in SH_BAND], dtype=np.float64)


def latlong_directions(height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """((H, W, 3) unit directions of a latitude-longitude map's pixel centres, (H, W) their solid angles)."""
    theta = math.pi * (np.arange(height, dtype=np.float64) + 0.5) / height
    phi = 2.0 * math.pi * (np.arange(width, dtype=np.float64) + 0.5) / width
    st, ct = np.sin(theta)[:, None], np.cos(theta)[:, None]
    dirs = np.stack([st * np.cos(phi)[None, :], st * np.sin(phi)[None, :], np.broadcast_to(ct, (height, width))],
                    axis=-1)
    # the exact solid angle of each row's band, split over its columns (sums to 4 pi to round-off)
    edges = math.pi * np.arange(height + 1, dtype=np.float64) / height
    band = (np.cos(edges[:-1]) - np.cos(edges[1:])) * (2.0 * math.pi / width)
    return dirs, np.broadcast_to(band[:, None], (height, width)).copy()


def project_latlong(env: np.ndarray) -> np.ndarray:
    """(9, C) SH coefficients of a latitude-longitude environment map (H, W, C) of linear radiance."""
    env = np.asarray(env, dtype=np.float64)
    if env.ndim != 3 or not np.all(np.isfinite(env)):
        raise ValueError(f"an environment map must be a finite (H, W, C) array, not shape {env.shape}")
    dirs, omega = latlong_directions(env.shape[0], env.shape[1])
    basis = sh9_basis(dirs) * omega[..., None]
    return np.einsum("hwk,hwc->kc", basis, env)


def latlong_from_sh(coeffs: np.ndarray, height: int, width: int) -> np.ndarray:
    """(H, W, C) the radiance an SH light (9, C) gives in each latitude-longitude pixel's direction."""
    dirs, _ = latlong_directions(height, width)
    return sh9_basis(dirs) @ np.asarray(coeffs, dtype=np.float64)


def unoccluded_transfer(normals: np.ndarray) -> np.ndarray:
    """(..., 9) diffuse transfer vectors A_l Y_k(n) / pi of unit normals (..., 3): no self-occlusion."""
    return sh9_basis(normals) * (band_factors(COSINE_LOBE_SH) / math.pi)


def diffuse_radiance(albedo: np.ndarray, transfer: np.ndarray, coeffs: np.ndarray) -> np.ndarray:
    """(..., C) radiance of Lambertian texels of ``albedo`` (..., C) with transfer (..., 9) under light (9, C)."""
    return np.asarray(albedo, dtype=np.float64) * (np.asarray(transfer, dtype=np.float64) @ np.asarray(coeffs))
