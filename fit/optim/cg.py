"""Nonlinear conjugate gradient (seed 3.3.2, 4.5.1): Fletcher-Reeves or Polak-Ribiere with
restart (beta = max(beta_PR, 0)), the descent safeguard of Alg. 10, and an optional steepest
descent restart every ``restart_every`` iterations.

``precondition=True``: Jacobi-preconditioned CG (N&W 5.2; z = M^-1 g with M the Gauss-Newton
diagonal + a tiny floor, see optim_kernels.cg_direction_kernel). M is held per texel between
restarts (CG's recurrences assume a fixed metric) and refreshed from the current point's
diagonal whenever the texel restarts (rejected step, PR+ clip, safeguard, periodic restart).
"""

from __future__ import annotations

import warp as wp

from texstream.fit.kernels import optim_kernels as K
from texstream.fit.optim.base import FitState

# no kernel here is differentiated (the fit writes its own derivatives): skipping Warp's adjoint
# code generation roughly halves compile time
wp.set_module_options({"enable_backward": False})


class ConjugateGradient:
    name = "cg"

    def __init__(self, variant: str = "pr", restart_every: int = 0, eps: float = 1e-6,
                 precondition: bool = False, precondition_floor: float = 1e-10, refresh_always: bool = False):
        self.precondition = precondition
        self.refresh_always = refresh_always  # M from every iteration's point (see the kernel)
        self.floor = precondition_floor
        self.minv = None
        self.variant = variant
        self.restart_every = restart_every
        self.eps = eps
        self.g_prev = None
        self.d_prev = None
        self.restart = None

    def _alloc(self, state: FitState) -> None:
        if self.g_prev is None:
            pr = state.problem
            self.g_prev = pr.new_vec()
            self.d_prev = pr.new_vec()
            self.restart = wp.ones(pr.n, dtype=wp.int32, device=pr.device)
            self.minv = pr.new_vec()
        if self.precondition:
            state.want_diag = True

    def reset_memory(self, state: FitState) -> None:
        self._alloc(state)
        self.restart.fill_(1)

    def direction(self, state: FitState) -> None:
        self._alloc(state)
        pr = state.problem
        if self.restart_every > 0 and state.iteration % self.restart_every == 0:
            self.restart.fill_(1)
        wp.launch(K.cg_direction_kernel, dim=pr.n, device=pr.device,
                  inputs=[state.g, self.g_prev, self.d_prev, self.restart, int(self.variant == "pr"),
                          pr.scalar(self.eps), state.free, int(self.precondition), state.diag, self.minv,
                          pr.layout.n_params, pr.scalar(self.floor), int(self.refresh_always)], outputs=[state.d])

    def after_step(self, state: FitState) -> None:
        # texels that did not move keep their gradient: beta then compares g with itself
        # (PR gives 0, a restart); FR would repeat the direction, so restart those too.
        wp.copy(self.g_prev, state.g_old)
        wp.copy(self.d_prev, state.d)
        wp.launch(_restart_rejected_kernel, dim=state.problem.n, device=state.problem.device,
                  inputs=[state.accepted, self.restart])


@wp.kernel
def _restart_rejected_kernel(accepted: wp.array(dtype=wp.int32), restart: wp.array(dtype=wp.int32)):
    i = wp.tid()
    if accepted[i] == 0:
        restart[i] = 1
