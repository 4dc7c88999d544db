"""Steepest descent: d = -grad (seed 3.3.1), the robust baseline; with ``precondition`` the
scaled gradient d = -M^-1 grad, M the Gauss-Newton diagonal at the current point (+ a tiny floor)."""

from __future__ import annotations

import warp as wp

from texstream.fit.kernels import optim_kernels as K
from texstream.fit.optim.base import FitState


class SteepestDescent:
    name = "sd"

    def __init__(self, precondition: bool = False, precondition_floor: float = 1e-10):
        self.precondition = precondition
        self.floor = precondition_floor

    def reset_memory(self, state: FitState) -> None:
        pass

    def direction(self, state: FitState) -> None:
        pr = state.problem
        if self.precondition:
            state.want_diag = True
        wp.launch(K.steepest_direction_kernel, dim=pr.n, device=pr.device,
                  inputs=[state.g, state.free, int(self.precondition), state.diag, pr.layout.n_params,
                          pr.scalar(self.floor)], outputs=[state.d])

    def after_step(self, state: FitState) -> None:
        pass
