"""Time PCA's rank-K factorization of vertex light-field matrices (fit/lfm_baselines.py): numpy's thin SVD
of the (ring slots r x view directions M) matrices against the route through the smaller Gram matrix
(``_truncated_svd``), on random matrices of temple-like shapes (batch of v vertices x 3 channels).

    python benchmarks/lfm_factor_speed.py                          # OpenBLAS's default threads
    OPENBLAS_NUM_THREADS=1 python benchmarks/lfm_factor_speed.py   # one thread (small LAPACK calls)

Prints one line per shape: seconds for the thin SVD and for the Gram route, and the largest difference
of their rank-K products.
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--shapes", default="3000x8,600x40,300x100,14x2168", help="comma list of VxR (M = 64)")
    ap.add_argument("--terms", type=int, default=1)
    a = ap.parse_args()
    from texstream.fit.models.lfm.baselines import _truncated_svd

    rng = np.random.default_rng(0)
    for shape in a.shapes.split(","):
        v, r = (int(x) for x in shape.split("x"))
        F = np.ascontiguousarray(np.moveaxis(rng.random((v, r, 64, 3)), 3, 1))   # (v, 3, r, M) as PCA factors
        t0 = time.perf_counter()
        U, S, Vt = np.linalg.svd(F, full_matrices=False)
        t_svd = time.perf_counter() - t0
        t0 = time.perf_counter()
        W, H = _truncated_svd(F, a.terms)
        t_gram = time.perf_counter() - t0
        k = a.terms
        ref = np.einsum("vcrk,vck,vckm->vcrm", U[..., :k], S[..., :k], Vt[..., :k, :])
        diff = float(np.abs(ref - np.einsum("vcrk,vckm->vcrm", W, H)).max())
        print(f"{v} x {r} x 64 (x3 channels): thin SVD {t_svd:.2f} s, Gram route {t_gram:.2f} s, max diff {diff:.1e}",
              flush=True)


if __name__ == "__main__":
    main()
