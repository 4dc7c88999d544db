"""render/sh.py: the order-2 SH convention of environment lighting (texstream.render.sh's docstring).

Ground truth is numerical integration on a fine latitude-longitude grid: float64 quadrature of smooth
integrands converges fast, so the tolerances below are set by the grid (documented per test)."""

import math

import numpy as np
import pytest
import warp as wp

from texstream.render import sh

# a 256 x 512 grid integrates the band-limited products below to ~1e-5 (midpoint rule in theta, exact in phi)
GRID = (256, 512)


def test_basis_is_orthonormal_over_the_sphere():
    dirs, omega = sh.latlong_directions(*GRID)
    assert abs(omega.sum() - 4.0 * math.pi) < 1e-12  # exact band solid angles
    basis = sh.sh9_basis(dirs)
    gram = np.einsum("hwk,hwj,hw->kj", basis, basis, omega)
    np.testing.assert_allclose(gram, np.eye(9), atol=1e-4)


def test_projection_round_trips_a_band_limited_light():
    rng = np.random.default_rng(3)
    coeffs = rng.normal(size=(9, 3))
    env = sh.latlong_from_sh(coeffs, *GRID)
    np.testing.assert_allclose(sh.project_latlong(env), coeffs, atol=1e-4)


def test_unoccluded_transfer_is_the_clamped_cosine_projection():
    """T_k(n) = (1/pi) * integral max(0, n.w) Y_k(w) dw, integrated numerically for a few normals; the
    clamped cosine's kink makes the quadrature converge slower (~1e-4 at this grid)."""
    dirs, omega = sh.latlong_directions(*GRID)
    basis = sh.sh9_basis(dirs)
    normals = np.array([[0, 0, 1.0], [1.0, 0, 0], [0.3, -0.5, 0.8]])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    for n in normals:
        cos = np.maximum(dirs @ n, 0.0)
        numeric = np.einsum("hwk,hw->k", basis, cos * omega) / math.pi
        np.testing.assert_allclose(sh.unoccluded_transfer(n), numeric, atol=5e-4)


def test_constant_environment_gives_albedo_times_radiance():
    coeffs = np.zeros((9, 3))
    coeffs[0] = 0.7 * math.sqrt(4.0 * math.pi)  # radiance 0.7 everywhere: L_00 = 0.7 / Y_00
    n = np.array([[0.0, 0.6, 0.8]])
    out = sh.diffuse_radiance(np.array([[0.5, 0.25, 1.0]]), sh.unoccluded_transfer(n), coeffs)
    np.testing.assert_allclose(out, [[0.35, 0.175, 0.7]], rtol=1e-12)  # exact: only Y_00 is non-zero


@wp.kernel
def _basis_kernel32(dirs: wp.array(dtype=wp.vec3f), out: wp.array2d(dtype=wp.float32)):
    i, k = wp.tid()
    out[i, k] = sh.sh9_basis_component(dirs[i], k, wp.float32(1.0))


@wp.kernel
def _basis_kernel64(dirs: wp.array(dtype=wp.vec3d), out: wp.array2d(dtype=wp.float64)):
    i, k = wp.tid()
    out[i, k] = sh.sh9_basis_component(dirs[i], k, wp.float64(1.0))


@pytest.mark.parametrize("precision", ["float32", "float64"])
def test_warp_basis_matches_numpy(device, precision):
    rng = np.random.default_rng(0)
    d = rng.normal(size=(64, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    vec, scalar, kernel = ((wp.vec3f, wp.float32, _basis_kernel32) if precision == "float32"
                           else (wp.vec3d, wp.float64, _basis_kernel64))
    out = wp.zeros((64, 9), dtype=scalar, device=device)
    wp.launch(kernel, dim=(64, 9), inputs=[wp.array(d, dtype=vec, device=device), out], device=device)
    tol = 1e-6 if precision == "float32" else 1e-14  # float32 round-off of products of O(1) terms
    np.testing.assert_allclose(out.numpy(), sh.sh9_basis(d), atol=tol)
