"""Line searches (seed 3.4, 4.5.2; Nocedal & Wright ch. 3), batched per texel.

- ``backtracking``: alpha0 (N&W 3.60 from the previous step), then alpha *= shrink until Armijo.
- ``hessian``: one-sided quadratic alpha = -g.d / d^T H d (3.13) with d^T H d streamed in an
  extra pass (4.3.3); checked by Armijo, backtracking if it fails.
- ``quadratic``: two-sided quadratic interpolation (3.15, Alg. 3).
Every trial computes objective and gradient together (Alg. 9), so the Wolfe curvature test
(3.12) is available at no extra pass; with a preconditioned optimizer (``state.want_diag``) the
trial pass also accumulates the Gauss-Newton diagonal, adopted with the accepted point. Acceptance is per texel by conditional assignment
(Alg. 11), or ``global``: one alpha for all texels, accepted on the summed objective.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import warp as wp

from texstream.core.config import option
from texstream.fit.kernels import optim_kernels as K
from texstream.fit.stream.penalties import Penalties
from texstream.fit.optim.base import FitState

LINE_SEARCHES = ("backtracking", "hessian", "quadratic")


@dataclasses.dataclass
class LineSearchConfig:
    """Line search options."""

    kind: str = option("hessian", "backtracking, hessian (one-sided quadratic with the streamed d^T H d) or "
                                  "quadratic (two-sided, seed Alg. 3)", choices=("backtracking", "hessian", "quadratic"))
    max_trials: int = option(6, "trial steps per iteration (each is one streaming pass)", min=1)
    sigma1: float = option(1e-4, "Armijo sufficient-decrease constant (seed 3.11)", min=0.0, max=1.0)
    sigma2: float = option(0.9, "Wolfe curvature constant (seed 3.12), used with --linesearch.wolfe", min=0.0, max=1.0)
    wolfe: bool = option(False, "also require the curvature condition (seed 3.12)")
    shrink: float = option(0.3, "backtracking factor", min=0.0, max=1.0)
    alpha0: float = option(1.0, "first trial step of the first iteration", min=0.0)
    full_hessian: bool = option(False, "d^T H d with the r d^T (Hess r) d term (else Gauss-Newton, always >= 0)")
    acceptance: str = option("texel", "texel (per-texel conditional assignment, seed Alg. 11) or global (one step "
                                      "for all texels)", choices=("texel", "global"))

def evaluate_trial(state: FitState, penalties: Penalties, active: wp.array) -> None:
    """Objective and gradient at state.trial (already in state.storage), penalties included."""
    pr = state.problem
    pr.evaluate(state.storage, state.f_trial, state.g_trial, state.stats_trial, active=active,
                diag=state.diag_out(trial=True))
    penalties.add(state, state.trial, state.f_trial, state.g_trial)


def line_search(state: FitState, cfg: LineSearchConfig, penalties: Penalties, first: bool) -> None:
    """Move every valid texel along state.d by an accepted step (or leave it where it is)."""
    pr = state.problem
    n = pr.n
    dev = pr.device
    s = pr.scalar
    wp.launch(K.initial_alpha_kernel, dim=n, device=dev,
              inputs=[state.g, state.d, state.prev_alpha, state.prev_slope, 1 if first else 0, s(cfg.alpha0), state.free],
              outputs=[state.alpha, state.slope])
    if cfg.kind == "hessian":
        # d^T H d needs d in the storage dtype for the streaming pass
        # the direction and the current point in the storage dtype (inactive texels copy p as is)
        state.launch_trial(state.d, state.d, state.alpha, _zeros_i(state), state.g_trial, _dir_storage(state))
        state.launch_trial(state.p, state.d, state.alpha, _zeros_i(state), state.trial, state.storage)
        pr.evaluate(state.storage, state.f_trial, state.g_trial, state.stats_trial, direction=_dir_storage(state),
                    dhd=state.dhd, full_hessian=cfg.full_hessian)
        penalties.add_dhd(state, state.p, state.d, state.dhd)
        fallback = state.alpha
        wp.launch(K.hessian_alpha_kernel, dim=n, device=dev,
                  inputs=[state.g, state.d, state.dhd, fallback, state.free], outputs=[state.alpha])
    wp.copy(state.active, state.valid)
    state.accepted.zero_()
    if cfg.acceptance == "global":
        _global_search(state, cfg, penalties)
    else:
        for _ in range(cfg.max_trials):
            state.launch_trial(state.p, state.d, state.alpha, state.active, state.trial, state.storage)
            evaluate_trial(state, penalties, state.active)
            wp.launch(K.accept_kernel, dim=n, device=dev,
                      inputs=[state.p, state.f, state.g, state.d, state.trial, state.f_trial, state.g_trial, state.alpha,
                              state.active, s(cfg.sigma1), s(cfg.sigma2), int(cfg.wolfe), s(cfg.shrink),
                              int(cfg.kind == "quadratic"), state.free, state.stats, state.stats_trial,
                              state.accepted, int(state.want_diag), state.diag, state.diag_trial])
    wp.copy(state.prev_alpha, state.alpha)
    wp.copy(state.prev_slope, state.slope)


def _global_search(state: FitState, cfg: LineSearchConfig, penalties: Penalties) -> None:
    """One alpha for all texels (comparison mode; reads three sums to the host per trial)."""
    pr = state.problem
    n = pr.n
    a = float(np.median(state.alpha.numpy()[state.valid.numpy() > 0])) if n else 1.0
    f0 = float(state.f.numpy().sum())
    sl = float(state.slope.numpy().sum())
    for _ in range(cfg.max_trials):
        state.alpha.fill_(a)
        state.launch_trial(state.p, state.d, state.alpha, state.valid, state.trial, state.storage)
        evaluate_trial(state, penalties, state.valid)
        ft = float(state.f_trial.numpy().sum())
        if np.isfinite(ft) and ft <= f0 + cfg.sigma1 * a * sl:
            wp.copy(state.p, state.trial)
            wp.copy(state.f, state.f_trial)
            wp.copy(state.g, state.g_trial)
            wp.copy(state.stats, state.stats_trial)
            if state.want_diag:
                wp.copy(state.diag, state.diag_trial)
            wp.copy(state.accepted, state.valid)
            return
        a *= cfg.shrink


def _zeros_i(state: FitState) -> wp.array:
    pr = state.problem
    if not hasattr(pr, "_zeros_i"):
        pr._zeros_i = wp.zeros(pr.n, dtype=wp.int32, device=pr.device)
    return pr._zeros_i


def _dir_storage(state: FitState) -> wp.array:
    pr = state.problem
    if not hasattr(pr, "_dir_storage"):
        pr._dir_storage = pr.new_storage()
    return pr._dir_storage
