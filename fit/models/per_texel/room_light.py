"""The room's light as one global environment light in order-2 SH (``FitConfig.ambient`` room; render/layout.py
``ModelLayout.room``): the physically right alternative to a free per-texel ambient radiance.

A texel's radiance is rho_d E_flash cos + lobes + pi rho_d T_t . L_c per channel c (T_t its visibility transfer,
geometry/sh_transfer.py, render/sh.py's convention): the room lights the same albedo as the flash, 27 global
unknowns instead of 3 per texel. With the flash at the camera a free ambient and rho_d are only weakly separable
(both are constant per texel up to the flash's cosine and distance); tied to rho_d through a light shared by every
texel, the room's term is fixed by the texels' differing normals and visibility.

**The fit, by alternation.** For a fixed L the per-texel fit is the existing LM fit with a known extra diffuse
irradiance: each texel's S_c = pi T_t . L_c sits in its frozen room columns (fit/kernels/lafortune_grad.py), so
nothing but those columns is new to the kernels. For fixed per-texel parameters the light's objective is
quadratic in L (S is linear in L, the prediction linear in S), and one streaming LM pass gives every texel's
J^T r and J^T J over its samples, the room columns included: the per-block partial sums of the light's normal
equations, which :func:`light_step` reduces over the texels into a 27 x 27 system. The step on L is the
Gauss-Newton step of the joint problem with each texel's own parameters eliminated (their Schur complement), not
the light alone with the albedos held: holding them would make the alternation crawl along the rho_d / room
valley (rho_d absorbs the room in the first fit, and at rho_d fixed the light has no reason to grow); eliminating
them lets the step see how each texel's albedo moves with the light, so a few rounds converge (the round trace
in model.json's ``ambient.room.trace``, ``light_step_rel``, documents it). The flash fixes the albedo's scale,
so unlike env_diffuse (fit/models/env_diffuse/solve.py, whose ridge pattern this follows) there is no gauge to fix.

**Measured** (benchmarks/flash_room_light.py, the synthetic flash capture with true cameras, mesh and response,
24 photos of 400 px, 15 iterations; benchmarks/results/flash_room_light_cpu/): albedo median error 6.2% (free
ambient 7.4%, none 58%), 90th percentile 24% (71%, 111%); the lobes the truth has found (median rho_s 0.236 and
n 37 against 0.2 and 40, where the free ambient empties them: 0.006) but held out 32.8 dB against 38.8 dB, the
per-texel lobes of 21 flash-at-camera photos mispredicting the held-out views (with the lobes zeroed the room
model's held-out error is below the free ambient's in every view). Not yet within the issue's 2%.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import warp as wp

from texstream.core.progress import say
from texstream.fit.optim.fitter import FitStart, run_fit
from texstream.fit.stream.problem import StreamProblem
from texstream.geometry.sh_transfer import sh_transfer
from texstream.render import sh

ROOM_ROUNDS = 5
"""outer rounds (per-texel fit, light step) before the last per-texel fit: the joint Gauss-Newton step converges about
quadratically, the light's relative step 1, 0.47, 0.18, 0.039 in rounds 0-3 on the recovery test's sphere"""
TRANSFER_SAMPLES = 256
"""ray directions per texel for the transfer vectors (env_diffuse's default)"""
LIGHT_RIDGE = 1e-6
"""ridge on the light's bands 1-2, relative to the system's mean diagonal: directions no texel faces (behind a
captured object's back) stay near 0 instead of blowing up"""


@dataclasses.dataclass
class RoomLight:
    """The fitted room light: ``light`` (9, 3) SH radiance coefficients (render/sh.py), the per-round ``trace``."""

    light: np.ndarray
    trace: list

    def to_json(self) -> dict:
        """model.json's ``ambient.room``."""
        return {"sh_order": 2, "coefficients": self.light.tolist(), "convention": "render/sh.py; a texel's room "
                "radiance is pi rho_d (T_t . L_c), T_t its visibility transfer (geometry/sh_transfer.py)",
                "mean_radiance": [float(v) for v in self.light[0] * sh.sh9_basis(np.array([0.0, 0.0, 1.0]))[0]],
                "trace": self.trace}


def texel_transfer(problem: StreamProblem, mesh, device: str, samples: int = TRANSFER_SAMPLES) -> np.ndarray:
    """(N, 9) the problem's texels' transfer vectors with the mesh's self-occlusion."""
    tx = problem.texels
    return sh_transfer(mesh.vertices, mesh.faces, tx.position, tx.normal, tx.face_normal, samples, True, device)


def with_room(params: np.ndarray, layout, transfer: np.ndarray, light: np.ndarray) -> np.ndarray:
    """``params`` with each texel's room columns S = pi T_t . L (nonnegative: irradiance; SH ringing aside)."""
    out = np.array(params, dtype=np.float64, copy=True)
    o = layout.room_offset
    out[:, o:o + 3] = np.maximum(np.pi * transfer @ light, 0.0)
    return out


def texel_blocks(problem: StreamProblem, params: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """(J^T r (N, P), J^T J (N, P, P), objective) at ``params``: one streaming LM pass (the renderer's lookup held
    at ``params``)."""
    storage = problem.new_storage(params)
    problem.refresh_lookup(storage)
    f, g = problem.new_scalar(), problem.new_vec()
    jtj = wp.zeros(problem.n, dtype=problem.mat, device=problem.device)
    stats = wp.zeros(problem.n, dtype=wp.vec4d, device=problem.device)
    problem.evaluate_lm(storage, f, g, jtj, stats)
    return g.numpy().astype(np.float64), jtj.numpy().astype(np.float64), float(np.sum(f.numpy(), dtype=np.float64))


def reduced_room_blocks(layout, g: np.ndarray, jtj: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R (N, 3, 3), q (N, 3)): each texel's J^T J and J^T r on its room columns S with its own free parameters
    eliminated (Schur complement, module doc): the texel's objective's change for a change dS of its S, its
    parameters re-fitted, is q . dS + dS^T R dS / 2 to second order."""
    o = layout.room_offset
    room = np.arange(o, o + 3)
    own = np.flatnonzero(~layout.frozen())
    r, q = np.zeros((len(g), 3, 3)), np.zeros((len(g), 3))
    trace = np.trace(jtj[:, own[:, None], own[None, :]], axis1=1, axis2=2)
    seen = np.flatnonzero(trace > 0)  # a texel no sample reaches has all-zero blocks: nothing to reduce
    h_pp = jtj[seen[:, None, None], own[None, :, None], own[None, None, :]]
    h_ps = jtj[seen[:, None, None], own[None, :, None], room[None, None, :]]
    # a relative ridge keeps rank-deficient blocks (a lobe no highlight constrains) solvable
    ridge = 1e-9 * trace[seen][:, None, None] * np.eye(len(own))
    rhs = np.concatenate([h_ps, g[seen][:, own, None]], axis=2)
    sol = np.linalg.solve(h_pp + ridge, rhs)
    r[seen] = jtj[seen][:, room[:, None], room[None, :]] - np.einsum("npi,npj->nij", h_ps, sol[:, :, :3])
    q[seen] = g[seen][:, room] - np.einsum("npi,np->ni", h_ps, sol[:, :, 3])
    return r, q


def light_step(layout, g: np.ndarray, jtj: np.ndarray, transfer: np.ndarray, light: np.ndarray) -> np.ndarray:
    """(9, 3) the Gauss-Newton step on the light from the texels' LM blocks (module doc): S_tc = pi T_t . L_c,
    so the 27 x 27 normal equations are sum_t pi^2 (T_t T_t^T) (x) R_t and sum_t pi T_t (x) q_t. Texels whose S is
    clamped at 0 (SH ringing below zero) do not move with the light and are left out."""
    r, q = reduced_room_blocks(layout, g, jtj)
    live = (transfer @ light > 0) | (np.abs(light).max() == 0)
    r = r * live[:, :, None] * live[:, None, :]
    q = q * live
    tt = np.pi * transfer
    # index (k, c): coefficient k of channel c, flattened k-major like light.reshape(-1)
    a = np.einsum("nk,nl,nij->kilj", tt, tt, r).reshape(27, 27)
    b = np.einsum("nk,ni->ki", tt, q).reshape(27)
    scale = max(float(np.trace(a)) / 27.0, 1e-300)
    pull = np.repeat(np.r_[0.0, np.ones(sh.SH_COUNT - 1)], 3)
    step = np.linalg.solve(a + np.diag(LIGHT_RIDGE * scale * pull + 1e-12 * scale), -b)
    return step.reshape(sh.SH_COUNT, 3)


def fit_room(problem: StreamProblem, fit_cfg, start: FitStart, transfer: np.ndarray, rounds: int = ROOM_ROUNDS,
             light0: np.ndarray | None = None) -> tuple[FitStart, RoomLight]:
    """(start, RoomLight): ``rounds`` rounds of the alternation (module doc), each a per-texel fit at the current
    light and a step on the light, each fit continuing from the previous round's; ``start`` is the last fit's
    parameters with the room columns at the final light, from which the caller's last per-texel fit starts
    (restarting every round from the initial guess instead was measured worse on the flash capture: held out
    31.1 dB against 33.0 dB, benchmarks/flash_room_light.py at 10 iterations). ``problem``'s layout has the room
    columns; ``start`` (the argument) its starting parameters and sample counts."""
    layout = problem.layout
    light = np.zeros((sh.SH_COUNT, 3)) if light0 is None else np.asarray(light0, np.float64)
    params, counts = start.numpy()
    trace = []
    for round_ in range(rounds):
        res = run_fit(problem, fit_cfg, p0=with_room(params, layout, transfer, light), start=(params, counts))
        params = res.params
        g, jtj, objective = texel_blocks(problem, params)
        step = light_step(layout, g, jtj, transfer, light)
        light = light + step
        rel = float(np.abs(step).max() / max(np.abs(light).max(), 1e-300))
        trace.append({"round": round_, "objective_before_step": objective, "iterations": len(res.trace) - 1,
                      "light_step_rel": rel, "mean_radiance": [float(v) for v in light[0] * sh.sh9_basis(
                          np.array([0.0, 0.0, 1.0]))[0]]})
        say("fit", f"room light round {round_}: objective {objective:.6g}, light step {rel:.2e} of the light")
    return FitStart.of((with_room(params, layout, transfer, light), counts), problem), RoomLight(light, trace)
