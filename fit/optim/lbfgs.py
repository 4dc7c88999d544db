"""Limited-memory BFGS (seed 3.3.4) with the two-loop recursion of Nocedal & Wright (Alg. 7.4),
m history pairs per texel in ring buffers, H0 = gamma_k I (3.9, 3.10), and pairs with
y^T s <= 0 skipped so the implied inverse Hessian stays positive definite.

``precondition=True``: H0 = gamma_k M^-1 instead of gamma_k I, M the Gauss-Newton diagonal
(+ a tiny floor) at the current point, refreshed every iteration (N&W allow H0_k to vary), and
gamma_k = s^T y / y^T M^-1 y of the newest pair (N&W 7.20 in the M-metric; 1 before any pair),
the scaling that did best on the ornament (docs/accuracy.md).
"""

from __future__ import annotations

import warp as wp

from texstream.fit.kernels import optim_kernels as K
from texstream.fit.optim.base import FitState


class LBFGS:
    name = "lbfgs"

    def __init__(self, history: int = 5, eps: float = 1e-8, precondition: bool = False,
                 precondition_floor: float = 1e-10, gamma_scaled: bool = True):
        self.precondition = precondition
        self.gamma_scaled = gamma_scaled  # H0 = gamma_k M^-1 (default), else M^-1 unscaled
        self.floor = precondition_floor
        self.m = history
        self.eps = eps
        self.buffers = None

    def _alloc(self, state: FitState) -> None:
        if self.precondition:
            state.want_diag = True
        if self.buffers is None:
            pr = state.problem
            shape = (self.m, pr.n)
            self.s_hist = wp.zeros(shape, dtype=pr.vec, device=pr.device)
            self.y_hist = wp.zeros(shape, dtype=pr.vec, device=pr.device)
            self.rho = wp.zeros(shape, dtype=pr.scalar, device=pr.device)
            self.alpha_buf = wp.zeros(shape, dtype=pr.scalar, device=pr.device)
            self.count = wp.zeros(pr.n, dtype=wp.int32, device=pr.device)
            self.head = wp.zeros(pr.n, dtype=wp.int32, device=pr.device)
            self.buffers = True

    def reset_memory(self, state: FitState) -> None:
        self._alloc(state)
        self.count.zero_()
        self.head.zero_()

    def direction(self, state: FitState) -> None:
        self._alloc(state)
        pr = state.problem
        wp.launch(K.lbfgs_direction_kernel, dim=pr.n, device=pr.device,
                  inputs=[state.g, self.s_hist, self.y_hist, self.rho, self.count, self.head, self.m,
                          pr.scalar(self.eps), state.free, int(self.precondition), state.diag,
                          pr.layout.n_params, pr.scalar(self.floor), int(self.gamma_scaled), self.alpha_buf,
                          state.p, state.lower, state.upper],
                  outputs=[state.d])

    def after_step(self, state: FitState) -> None:
        pr = state.problem
        wp.launch(K.lbfgs_update_kernel, dim=pr.n, device=pr.device,
                  inputs=[state.p_old, state.g_old, state.p, state.g, state.accepted, self.m, state.free,
                          self.s_hist, self.y_hist, self.rho, self.count, self.head])
