"""Streamed Gauss-Newton / Levenberg-Marquardt per texel.

The seed ruled LM out for its O(n^2) storage (3.5), but a texel's problem is tiny (one lobe:
9 parameters, 45 distinct J^T J entries), so J^T J and J^T r are accumulated per texel over the
photos in one streaming pass and the damped system (J^T J + lambda diag(J^T J)) delta = -J^T r is
solved per texel in a kernel (Cholesky). Each iteration is one pass: the trial point's J^T J is
accumulated while its objective is, and adopted if the step is accepted (the Alg. 9 idea).
Bounds are enforced by projection of the trial point; penalties are not supported by LM.
"""

from __future__ import annotations

import warp as wp

from ..kernels import optim_kernels as K
from .base import FitState


class LevenbergMarquardt:
    name = "lm"

    def __init__(self, lambda0: float = 1e-3):
        self.lambda0 = lambda0
        self.ready = False

    def _alloc(self, state: FitState) -> None:
        if not self.ready:
            pr = state.problem
            self.jtj = wp.zeros(pr.n, dtype=pr.mat, device=pr.device)
            self.jtj_trial = wp.zeros(pr.n, dtype=pr.mat, device=pr.device)
            self.lam = pr.new_scalar(self.lambda0)
            self.pred = pr.new_scalar()
            self.one = pr.new_scalar(1.0)
            self.ready = True

    def start(self, state: FitState) -> None:
        self._alloc(state)
        pr = state.problem
        pr.evaluate_lm(state.storage, state.f, state.g, self.jtj, state.stats)

    def reset_memory(self, state: FitState) -> None:
        self._alloc(state)
        self.lam.fill_(self.lambda0)

    def step(self, state: FitState) -> None:
        pr = state.problem
        n = pr.n
        wp.launch(K.lm_solve_kernel, dim=n, device=pr.device,
                  inputs=[self.jtj, state.g, self.lam, pr.layout.n_params, state.free, pr.like],
                  outputs=[state.d, self.pred])
        wp.copy(state.active, state.valid)
        wp.launch(K.trial_kernel, dim=n, device=pr.device,
                  inputs=[state.p, state.d, self.one, state.lower, state.upper, state.free, state.active,
                          pr.layout.n_params], outputs=[state.trial, state.storage])
        pr.evaluate_lm(state.storage, state.f_trial, state.g_trial, self.jtj_trial, state.stats_trial,
                       active=state.active)
        wp.launch(K.lm_accept_kernel, dim=n, device=pr.device,
                  inputs=[state.p, state.f, state.g, self.jtj, state.trial, state.f_trial, state.g_trial,
                          self.jtj_trial, self.pred, self.lam, state.active, state.stats, state.stats_trial,
                          state.accepted])
