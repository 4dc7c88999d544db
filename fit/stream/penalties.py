"""Penalty terms (seed 3.6, 4.4): quadratic bounds (3.19) and Laplacian regularisation on the
texel grid with masked stencils (Alg. 7), each with its gradient and d^T H d term.

Hard bounds are enforced by projection (clamping the trial point, as the seed did "for most
constraints"); the quadratic bounds penalty is for soft bounds (``bounds_weight`` > 0).
The Laplacian couples neighbouring texels; per-texel acceptance evaluates it with the
neighbours' trial values, a documented approximation of the seed's implementation.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import warp as wp

from texstream.core.config import option

from texstream.fit.kernels import optim_kernels as K


@dataclasses.dataclass
class PenaltyConfig:
    """Penalty weights (saved with the fit config)."""

    bounds_weight: float = option(0.0, "mu of the quadratic bounds penalty (3.19); 0 = hard bounds by projection only",
                                  min=0.0)
    laplacian_weight: float = option(0.0, "lambda of the Laplacian penalty (4.12) for sd, cg and lbfgs; 0 = off",
                                     min=0.0)
    laplacian_params: str = option("all", "which parameters the Laplacian regularises",
                                   choices=("all", "diffuse", "specular"))
    smooth_weight: float = option(0.0, "lm only: weight of the edge-aware membrane smoothness between neighbouring "
                                       "texels, sum over neighbour pairs of e_ij sum_k w_k (p_ik - p_jk)^2, in the "
                                       "objective's units; 0 = off (texels independent)", min=0.0)
    smooth_params: str = option("shape", "which parameters the smoothness term couples: shape (the lobes' C and "
                                         "n), specular (also rho_s), diffuse or all",
                                choices=("shape", "specular", "diffuse", "all"))
    smooth_edge_sigma: float = option(0.1, "edge stopping: e_ij = exp(-(d_ij / sigma)^2), d_ij the relative "
                                           "difference of the initial diffuse albedos; 0 = no edge stopping",
                                           min=0.0)
    smooth_exponent_scale: float = option(50.0, "the exponent n enters the smoothness as n / this (its typical "
                                                "spread), so it weighs like an albedo", min=1e-9)

    def parameter_weights(self, layout, which: str) -> np.ndarray:
        """(n_params,) column weights of a penalty for ``which`` parameters of ``layout``."""
        w = np.zeros(layout.n_params)
        if which in ("diffuse", "all"):
            w[:3] = 1.0
        if which in ("specular", "all", "shape"):
            w[3:layout.n_params] = 1.0
            for j in range(layout.n_lobes):
                if which == "shape":
                    w[layout.lobe_offset(j):layout.lobe_offset(j) + 3] = 0.0
            for j in range(layout.n_lobes):
                w[layout.lobe_offset(j) + layout.lobe_stride - 1] /= max(self.smooth_exponent_scale, 1e-12) ** 2
        return w


class Penalties:
    """Adds penalty values, gradients and curvature to per-texel arrays (kernels only)."""

    def __init__(self, problem, config: PenaltyConfig):
        self.problem = problem
        self.cfg = config
        lay = problem.layout
        w = config.parameter_weights(lay, config.laplacian_params)
        self.weights = problem.vec(*w)
        if config.laplacian_weight > 0:
            self.lp = problem.new_vec()
            self.llp = problem.new_vec()
            self.ld = problem.new_vec()

    @property
    def active(self) -> bool:
        return self.cfg.bounds_weight > 0 or self.cfg.laplacian_weight > 0

    def add(self, state, p: wp.array, f: wp.array, g: wp.array) -> None:
        self._add(state, p, None, f, g, None)

    def add_dhd(self, state, p: wp.array, d: wp.array, dhd: wp.array) -> None:
        """Only the curvature terms d^T H_P d (f, g of the dHd pass are scratch)."""
        scratch_f = state.f_trial
        scratch_g = state.g_trial
        self._add(state, p, d, scratch_f, scratch_g, dhd)

    def _add(self, state, p, d, f, g, dhd) -> None:
        pr = self.problem
        s = pr.scalar
        n = pr.n
        want = 1 if dhd is not None else 0
        dd = d if d is not None else p
        hh = dhd if dhd is not None else f
        if self.cfg.bounds_weight > 0:
            wp.launch(K.bounds_penalty_kernel, dim=n, device=pr.device,
                      inputs=[p, dd, state.lower, state.upper, s(self.cfg.bounds_weight), state.free, want,
                              pr.layout.n_params], outputs=[f, g, hh])
        if self.cfg.laplacian_weight > 0:
            wp.launch(K.laplacian_kernel, dim=n, device=pr.device, inputs=[p, pr.neighbors], outputs=[self.lp])
            wp.launch(K.laplacian_kernel, dim=n, device=pr.device, inputs=[self.lp, pr.neighbors], outputs=[self.llp])
            if want:
                wp.launch(K.laplacian_kernel, dim=n, device=pr.device, inputs=[dd, pr.neighbors], outputs=[self.ld])
            wp.launch(K.laplacian_penalty_kernel, dim=n, device=pr.device,
                      inputs=[self.lp, self.llp, self.ld if want else self.lp, self.weights,
                              s(self.cfg.laplacian_weight), want], outputs=[f, g, hh])
