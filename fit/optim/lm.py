"""Streamed Gauss-Newton / Levenberg-Marquardt per texel, with optional edge-aware smoothness.

The seed ruled LM out for its O(n^2) storage (3.5), but a texel's problem is tiny (one lobe:
9 parameters, 45 distinct J^T J entries), so J^T J and J^T r are accumulated per texel over the
photos in one streaming pass and the damped system (J^T J + lambda diag(J^T J)) delta = -J^T r is
solved per texel in a kernel (Cholesky). Each iteration is one pass: the trial point's J^T J is
accumulated while its objective is, and adopted if the step is accepted (the Alg. 9 idea).
Bounds are enforced by projection of the trial point.

Why smoothness: a texel sees its specular highlight in only a few photos of a sparse capture
(a lobe of n = 30 covers ~1% of the view sphere), so rho_s and n of a lone texel are poorly
determined and independent fits overfit the training photos. ``PenaltyConfig.smooth_weight``
couples neighbouring texels by a membrane term e_ij |W (p_i - p_j)|^2 whose edge weights e_ij
stop at jumps of the (well determined) initial diffuse albedo, so material boundaries stay
sharp. The coupling keeps the per-texel solve: texels are updated in red-black order on the atlas
grid, each solving its own block with its neighbours held (block Gauss-Seidel), which is exact
for the block and keeps every accepted step a decrease of the global objective.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from texstream.fit.kernels import optim_kernels as K
from texstream.fit.stream.penalties import PenaltyConfig
from texstream.fit.optim.base import FitState


class LevenbergMarquardt:
    name = "lm"

    def __init__(self, lambda0: float = 1e-3, penalties: PenaltyConfig | None = None):
        self.lambda0 = lambda0
        self.pen = penalties or PenaltyConfig()
        self.smooth = self.pen.smooth_weight > 0
        self.ready = False
        self.steps = 0

    def _alloc(self, state: FitState) -> None:
        if self.ready:
            return
        pr = state.problem
        dev = pr.device
        self.jtj = wp.zeros(pr.n, dtype=pr.mat, device=dev)
        self.jtj_trial = wp.zeros(pr.n, dtype=pr.mat, device=dev)
        self.lam = pr.new_scalar(self.lambda0)
        self.pred = pr.new_scalar()
        self.one = pr.new_scalar(1.0)
        if self.smooth:
            # data-term parts; state.f / state.g hold the local objective (data + smoothness)
            self.f_data, self.f_data_trial = pr.new_scalar(), pr.new_scalar()
            self.g_data, self.g_data_trial = pr.new_vec(), pr.new_vec()
            self.jtj_eff = wp.zeros(pr.n, dtype=pr.mat, device=dev)
            self.weights = pr.vec(*self.pen.parameter_weights(pr.layout, self.pen.smooth_params))
            self.s_lam = pr.scalar(self.pen.smooth_weight)
            self.edge_w = wp.array(edge_weights(state.params_numpy()[:, :3], pr.texels.neighbors,
                                                self.pen.smooth_edge_sigma), dtype=wp.vec4, device=dev)
            tx = pr.texels
            ys, xs = np.divmod(tx.grid_index, tx.width)
            self.parity = wp.array(((ys + xs) % 2).astype(np.int32), dtype=wp.int32, device=dev)
        self.ready = True

    def _smooth(self, state: FitState, p, f_in, g_in, h_in, f_out, g_out, h_out, f_scale: float,
                derivatives: bool) -> None:
        pr = state.problem
        wp.launch(K.smooth_local_kernel, dim=pr.n, device=pr.device,
                  inputs=[p, state.p, pr.neighbors, self.edge_w, self.weights, self.s_lam, pr.scalar(f_scale),
                          f_in, g_in, h_in, pr.layout.n_params, 1 if derivatives else 0],
                  outputs=[f_out, g_out, h_out])

    def _report_totals(self, state: FitState) -> None:
        """state.f = data + the texel's half share of the pair terms (sums to the global objective)."""
        self._smooth(state, state.p, self.f_data, self.g_data, self.jtj, state.f, state.g, self.jtj_eff, 0.5, True)

    def start(self, state: FitState) -> None:
        self._alloc(state)
        pr = state.problem
        if self.smooth:
            pr.evaluate_lm(state.storage, self.f_data, self.g_data, self.jtj, state.stats)
            self._report_totals(state)
        else:
            pr.evaluate_lm(state.storage, state.f, state.g, self.jtj, state.stats)

    def reset_memory(self, state: FitState) -> None:
        self._alloc(state)
        self.lam.fill_(self.lambda0)

    def step(self, state: FitState) -> None:
        pr = state.problem
        n = pr.n
        self.steps += 1
        if self.smooth:
            # local objective of the block with neighbours held: f, g and H of data + smoothness
            self._smooth(state, state.p, self.f_data, self.g_data, self.jtj, state.f, state.g, self.jtj_eff,
                         1.0, True)
            wp.launch(K.parity_active_kernel, dim=n, device=pr.device,
                      inputs=[state.valid, self.parity, self.steps % 2], outputs=[state.active])
            system = self.jtj_eff
        else:
            wp.copy(state.active, state.valid)
            system = self.jtj
        wp.launch(K.lm_solve_kernel, dim=n, device=pr.device,
                  inputs=[system, state.g, self.lam, pr.layout.n_params, state.free, pr.like, state.p, state.lower,
                          state.upper],
                  outputs=[state.d, self.pred])
        state.launch_trial(state.p, state.d, self.one, state.active, state.trial, state.storage)
        if self.smooth:
            pr.evaluate_lm(state.storage, self.f_data_trial, self.g_data_trial, self.jtj_trial, state.stats_trial,
                           active=state.active)
            self._smooth(state, state.trial, self.f_data_trial, self.g_data_trial, self.jtj_trial, state.f_trial,
                         state.g_trial, self.jtj_trial, 1.0, False)
            wp.launch(K.lm_accept_kernel, dim=n, device=pr.device,
                      inputs=[state.p, self.f_data, self.g_data, self.jtj, state.trial, self.f_data_trial,
                              self.g_data_trial, self.jtj_trial, state.f, state.f_trial, self.pred, self.lam,
                              state.active, state.stats, state.stats_trial, state.accepted])
            self._report_totals(state)
        else:
            pr.evaluate_lm(state.storage, state.f_trial, state.g_trial, self.jtj_trial, state.stats_trial,
                           active=state.active)
            wp.launch(K.lm_accept_kernel, dim=n, device=pr.device,
                      inputs=[state.p, state.f, state.g, self.jtj, state.trial, state.f_trial, state.g_trial,
                              self.jtj_trial, state.f, state.f_trial, self.pred, self.lam, state.active,
                              state.stats, state.stats_trial, state.accepted])


def edge_weights(rho_d: np.ndarray, neighbors: np.ndarray, sigma: float) -> np.ndarray:
    """(N, 4) float32 e_ij = exp(-(d_ij / sigma)^2), d_ij = |rho_i - rho_j| / mean(|rho_i|, |rho_j|).

    Computed once from the initial diffuse guess (so the objective is a fixed function); 0 where a
    neighbour is missing; 1 everywhere when ``sigma`` is 0.
    """
    nb = np.asarray(neighbors)
    has = nb >= 0
    e = np.where(has, 1.0, 0.0)
    if sigma > 0:
        rho = np.asarray(rho_d, dtype=np.float64)
        other = rho[np.where(has, nb, 0)]  # (N, 4, 3)
        num = np.linalg.norm(rho[:, None, :] - other, axis=-1)
        den = 0.5 * (np.linalg.norm(rho, axis=-1)[:, None] + np.linalg.norm(other, axis=-1)) + 1e-3
        e = np.where(has, np.exp(-(num / den / sigma) ** 2), 0.0)
    return e.astype(np.float32)
