"""Streamed sums as the fit's passes accumulate them, for the summation study (benchmarks/summation.py)
and the automatic accumulation choice (``StreamConfig.accumulate`` "auto", fit/stream/config.py).

A pass's thread adds one texel's terms photo after photo in registers (fit/kernels/accumulate.py
``accumulate_kernel``): a serial sum in the accumulate precision, optionally Kahan-compensated with the
pass's own :func:`stream.kahan_add`. These kernels do the same to rows of float32 terms, one row per
thread: naive float32, Kahan float32, float64, and a pairwise (tree) float32 sum for comparison.
"""

from __future__ import annotations

import warp as wp

from texstream.fit.kernels.stream import kahan_add

wp.set_module_options({"enable_backward": False})


@wp.kernel
def serial_sum_float32(terms: wp.array2d(dtype=wp.float32), out: wp.array(dtype=wp.float32)):
    """out[t] = terms[t, 0] + terms[t, 1] + ... left to right in float32 (the fp32 pass)."""
    t = wp.tid()
    s = wp.float32(0.0)
    for i in range(terms.shape[1]):
        s = s + terms[t, i]
    out[t] = s


@wp.kernel
def kahan_sum_float32(terms: wp.array2d(dtype=wp.float32), out: wp.array(dtype=wp.float32)):
    """The same sum Kahan-compensated in float32 (the fp32 pass with ``StreamConfig.kahan``)."""
    t = wp.tid()
    s = wp.float32(0.0)
    c = wp.float32(0.0)
    for i in range(terms.shape[1]):
        s, c = kahan_add(s, c, terms[t, i])
    out[t] = s


@wp.kernel
def serial_sum_float64(terms: wp.array2d(dtype=wp.float32), out: wp.array(dtype=wp.float64)):
    """The same sum in float64 (the fp64 pass)."""
    t = wp.tid()
    s = wp.float64(0.0)
    for i in range(terms.shape[1]):
        s = s + wp.float64(terms[t, i])
    out[t] = s


@wp.kernel
def pairwise_step_float32(src: wp.array2d(dtype=wp.float32), n: int, dst: wp.array2d(dtype=wp.float32)):
    """One level of a pairwise sum: dst[t, i] = src[t, 2i] + src[t, 2i + 1] (the last alone when n is odd)."""
    t, i = wp.tid()
    a = src[t, 2 * i]
    if 2 * i + 1 < n:
        a = a + src[t, 2 * i + 1]
    dst[t, i] = a


SERIAL_SUMS = {"fp32": serial_sum_float32, "fp32_kahan": kahan_sum_float32, "fp64": serial_sum_float64}
"""the pass accumulations, by name"""


def streamed_sums(terms, method: str, device: str = "cpu"):
    """Sum each row of a (trials, n) float32 numpy array with ``method`` ("fp32", "fp32_kahan", "fp64" or
    "pairwise"): a float64 numpy array of the row sums as the device computed them."""
    import numpy as np

    a = wp.array(np.ascontiguousarray(terms, np.float32), dtype=wp.float32, device=device)
    trials, n = a.shape
    if method == "pairwise":
        while n > 1:
            half = (n + 1) // 2
            b = wp.empty((trials, half), dtype=wp.float32, device=device)
            wp.launch(pairwise_step_float32, dim=(trials, half), inputs=[a, n], outputs=[b], device=device)
            a, n = b, half
        return a.numpy()[:, 0].astype(np.float64)
    kernel = SERIAL_SUMS[method]
    out = wp.zeros(trials, dtype=wp.float64 if method == "fp64" else wp.float32, device=device)
    wp.launch(kernel, dim=trials, inputs=[a], outputs=[out], device=device)
    return out.numpy().astype(np.float64)


# the chapter-6 sign mixes: per texel, 3 channel terms per photo
ERROR_SUMS = ("error_gaussian", "error_near_constant", "error_wide")
"""all-positive error terms r^2 / 2 (seed eq. 6.6): Gaussian residuals; a residual biased to 0.1 with 1%
noise (every term nearly equal: the worst case for a serial sum); residuals spanning 10^-3 to 10
(dark texels to highlights)"""
GRADIENT_SUMS = ("gradient_zero_mean", "gradient_biased")
"""mixed-sign gradient terms r dm/dp (seed eq. 6.12), dm/dp uniform in [0, 1]: zero-mean residuals (near
convergence: the sum cancels to ~0) and residuals biased by +0.3 (far from it)"""


def study_terms(kind: str, trials: int, n: int, seed: int = 0):
    """(trials, n) float32 terms of one sign mix (:data:`ERROR_SUMS`, :data:`GRADIENT_SUMS`)."""
    import numpy as np

    rng = np.random.default_rng(seed)
    shape = (trials, n)
    if kind == "error_gaussian":
        r = rng.standard_normal(shape, np.float32)
    elif kind == "error_near_constant":
        r = np.float32(0.1) * (1 + np.float32(0.01) * rng.standard_normal(shape, np.float32))
    elif kind == "error_wide":
        r = rng.standard_normal(shape, np.float32) * (10.0 ** rng.uniform(-3, 1, shape)).astype(np.float32)
    elif kind in GRADIENT_SUMS:
        r = rng.standard_normal(shape, np.float32) + np.float32(0.3 if kind == "gradient_biased" else 0.0)
        return (r * rng.uniform(0, 1, shape).astype(np.float32)).astype(np.float32)
    else:
        raise ValueError(f"term kind {kind!r} unknown")
    return (np.float32(0.5) * r * r).astype(np.float32)
