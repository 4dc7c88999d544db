"""Steepest descent: d = -grad (seed 3.3.1), the robust baseline."""

from __future__ import annotations

import warp as wp

from ..kernels import optim_kernels as K
from .base import FitState


class SteepestDescent:
    name = "sd"

    def reset_memory(self, state: FitState) -> None:
        pass

    def direction(self, state: FitState) -> None:
        wp.launch(K.steepest_direction_kernel, dim=state.problem.n, device=state.problem.device,
                  inputs=[state.g, state.free], outputs=[state.d])

    def after_step(self, state: FitState) -> None:
        pass
