"""Batched per-texel optimizer state and the protocol every optimizer follows.

Each texel is an independent small problem (the seed's texel-sized patches), coupled only by the
optional Laplacian penalty. All state lives on the device as (N,) arrays of fixed-length
parameter vectors; optimizers launch kernels over texels and never loop over them in Python.
"""

from __future__ import annotations

import dataclasses
from typing import Protocol

import numpy as np
import warp as wp

from texstream.fit.kernels import optim_kernels as K
from texstream.fit.stream.problem import StreamProblem


@dataclasses.dataclass
class FitState:
    """Device state of a fit: iterate, objective, gradient, direction and line-search scratch."""

    problem: StreamProblem
    p: wp.array
    f: wp.array
    g: wp.array
    stats: wp.array
    d: wp.array
    alpha: wp.array
    prev_alpha: wp.array
    slope: wp.array
    prev_slope: wp.array
    dhd: wp.array
    trial: wp.array
    f_trial: wp.array
    g_trial: wp.array
    stats_trial: wp.array
    storage: wp.array
    active: wp.array
    accepted: wp.array
    valid: wp.array
    p_old: wp.array
    g_old: wp.array
    free: object
    lower: object
    upper: object
    lobe_albedo_max: float = 0.0
    iteration: int = 0
    diag: wp.array | None = None
    """(N,) Gauss-Newton diagonal diag(J^T J) at ``p`` (valid while ``want_diag``)"""
    diag_trial: wp.array | None = None
    """the same at ``trial``; adopted with the trial point on acceptance"""
    want_diag: bool = False
    """accumulate the diagonal in every gradient pass (the optimizer preconditions with it)"""

    @staticmethod
    def create(problem: StreamProblem, p0, free_mask: np.ndarray, lobe_albedo_max: float = 0.0,
               counts: wp.array | None = None) -> "FitState":
        """State at ``p0`` ((N, n_params) float64, a NumPy array or a Warp array on the problem's device),
        projected onto the bounds and the lobe energy bound on the device. ``counts``: samples per texel
        (``valid`` is 1 where positive); None: every texel valid."""
        pr = problem
        lay = pr.layout
        vec = pr.vec
        lo, hi = lay.lower(), lay.upper()
        fr = free_mask.astype(float)
        n = pr.n
        dev = pr.device
        if not isinstance(p0, wp.array):
            p0 = wp.array(np.ascontiguousarray(p0, dtype=np.float64), dtype=wp.float64, device=dev)
        if p0.shape != (n, lay.n_params) or p0.dtype != wp.float64:
            raise ValueError(f"start of shape {p0.shape} ({p0.dtype.__name__}); the fit needs ({n}, {lay.n_params}) float64")
        p = wp.empty(n, dtype=vec, device=dev)  # every element written by the start kernel
        storage = wp.empty((n, lay.n_params), dtype=pr.storage_dtype, device=dev)
        valid = wp.empty(n, dtype=wp.int32, device=dev)
        if counts is None:
            counts = wp.ones(n, dtype=wp.int32, device=dev)
        wp.launch(K.start_point_kernel, dim=n, device=dev,
                  inputs=[p0, wp.array(lo, dtype=wp.float64, device=dev), wp.array(hi, dtype=wp.float64, device=dev),
                          lay.n_lobes, lay.lobe_stride, wp.float64(lobe_albedo_max), wp.float64(2.0 * np.pi), counts],
                  outputs=[p, storage, valid])
        # the trial and previous points start as device copies of the first point
        st = FitState(
            problem=pr, p=p, f=pr.new_scalar(), g=pr.new_vec(),
            stats=wp.zeros(n, dtype=wp.vec4d, device=dev), d=pr.new_vec(), alpha=pr.new_scalar(1.0),
            prev_alpha=pr.new_scalar(1.0), slope=pr.new_scalar(), prev_slope=pr.new_scalar(),
            dhd=pr.new_scalar(), trial=wp.clone(p), f_trial=pr.new_scalar(), g_trial=pr.new_vec(),
            stats_trial=wp.zeros(n, dtype=wp.vec4d, device=dev), storage=storage,
            active=wp.zeros(n, dtype=wp.int32, device=dev), accepted=wp.zeros(n, dtype=wp.int32, device=dev),
            valid=valid, p_old=wp.clone(p), g_old=pr.new_vec(),
            free=vec(*fr), lower=vec(*lo), upper=vec(*hi), lobe_albedo_max=float(lobe_albedo_max),
            diag=pr.new_vec(), diag_trial=pr.new_vec())
        return st

    def diag_out(self, trial: bool = False) -> wp.array | None:
        """The diagonal output of a gradient pass at ``p`` (or at the trial), None when not wanted."""
        if not self.want_diag:
            return None
        return self.diag_trial if trial else self.diag

    def launch_trial(self, p: wp.array, d: wp.array, alpha: wp.array, active: wp.array,
                     trial: wp.array, storage: wp.array) -> None:
        """trial = project(p + alpha d) on active texels (bounds, energy bound), also into ``storage``."""
        pr = self.problem
        lay = pr.layout
        wp.launch(K.trial_kernel, dim=pr.n, device=pr.device,
                  inputs=[p, d, alpha, self.lower, self.upper, self.free, active, lay.n_params, lay.n_lobes,
                          lay.lobe_stride, float(self.lobe_albedo_max)], outputs=[trial, storage])

    def store_current(self) -> None:
        """Write the current parameters ``p`` into ``storage`` (which holds the last trial point
        after a step), e.g. to evaluate the objective at ``p`` again."""
        pr = self.problem
        if not hasattr(self, "_no_step"):
            self._no_step = pr.new_scalar()
        self.launch_trial(self.p, self.d, self._no_step, pr.all_active, self.trial, self.storage)

    def set_free(self, free_mask: np.ndarray) -> None:
        self.free = self.problem.vec(*free_mask.astype(float))

    def params_numpy(self) -> np.ndarray:
        return self.p.numpy().astype(np.float64)


class Optimizer(Protocol):
    """One iteration of a fit method: direction + line search (or a damped Gauss-Newton step)."""

    name: str

    def start(self, state: FitState) -> None:
        """Evaluate the objective at the starting point and set up method memory."""

    def step(self, state: FitState) -> None:
        """Advance every texel by at most one accepted step (per-texel acceptance, Alg. 11)."""

    def reset_memory(self, state: FitState) -> None:
        """Forget curvature/direction memory (after the free-parameter set changes)."""
