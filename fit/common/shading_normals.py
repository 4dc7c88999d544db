"""Shading normals fitted to the photos under known lights (``FitStageConfig.shading_normals``,
``--shading-normals.mode on``; off by default).

Why: under a light at the camera a texel's radiance is its BRDF times cos(theta_i), and the fit takes theta_i from
the mesh's interpolated normal. A mesh whose normals are a few degrees off turns that into albedo error and a lobe
broadened to cover the misplaced highlight. The photos themselves say where the normal points: how a texel's
brightness changes with the light's direction across its photos.

How (the fitted reflectance held, the normals moved, the reflectance fitted again; ``rounds`` times at most):

1. Per texel, the objective on the fitted photos (:func:`~texstream.fit.common.setup.per_texel_objective`) at its
   normal and at the normal turned by +-``step_degrees`` about its two tangent axes: five streaming passes, the
   parameters held. A parabola through each axis's three values gives the texel's tilt (its minimum, at most
   ``2 * step_degrees``; where the parabola opens downwards, the better side's step if it is lower) and its
   curvature, the tilt's confidence. A texel whose sample count changes between the passes (a grazing sample
   crossing the cosine limit) has no confidence on that axis: its objective jumped for another reason.
2. The vertex normals move by the least-squares solution of giving every texel its tilt, weighted by the curvatures,
   with a ridge on each vertex's share (:func:`vertex_moves`: conjugate gradients from the weighted mean of its texels'
   tilts; the copies of a vertex along the atlas's seams as one), each move at most ``2 * step_degrees`` and no normal
   farther than ``max_tilt_degrees`` from the mesh's own. The vertices of a texel whose objective the move would raise
   by more than :data:`HARM_SHARE` of the whole keep their normals. The texels' normals are the renderer's
   interpolation of the vertex normals, so the fitted model and its renders (and the exported mesh) agree.
3. The round is kept when the objective, the reflectance still held, fell by more than ``min_gain`` relative; the
   reflectance is then fitted again (``refit_iterations`` Levenberg-Marquardt iterations at most). Otherwise its
   normals are undone (no parameter had changed) and the rounds stop; where no round is kept the problem gets its
   own texel arrays back, bit for bit.

The held-out photos play no part. The model folder's mesh.obj and bake.npz carry the fitted normals, and model.json's
``shading_normals`` says what moved and by how much. Where it helps and where it hurts: docs/real-data.md (a mesh
made from the photos absorbs its surface's errors into the normals, so ``texstream run`` leaves it off).

Imports only numpy and warp (the fit's rule); the streaming passes are the fit's own.
"""

from __future__ import annotations

import dataclasses
import math
import time

import numpy as np

from texstream.core.config import option
from texstream.fit.common.setup import per_texel_objective_and_samples
from texstream.fit.stream.texels import surface_derivatives

NORMAL_MODES = ("off", "on")


@dataclasses.dataclass
class NormalsConfig:
    """The fitted shading normals (fit/common/shading_normals.py)."""

    mode: str = option("off", "fit the mesh's shading normals to the photos under known lights (Lafortune and "
                              "diffuse models): on (rounds of per-texel tilts from the photos, solved for the vertex "
                              "normals, then the reflectance fitted again; a round is kept only when it lowers the "
                              "objective) or off. For a given mesh whose surface is right and whose normals are a few "
                              "degrees off (decimated or smoothed scans); not for meshes made from the photos, whose "
                              "position errors the normals then absorb (docs/real-data.md)", choices=NORMAL_MODES)
    rounds: int = option(6, "rounds of tilt, vertex normals and refit at most", min=1, max=50)
    step_degrees: float = option(0.5, "the tilt probed about each tangent axis (the parabola's half width); a texel "
                                      "moves at most twice this a round. Small because a glossy texel's objective is "
                                      "stiff in its normal: on the sphere_room scene +-2 degrees raised it 20-25x and "
                                      "the parabolas' steps made the normals worse, +-0.5 degrees 2.5x and they "
                                      "brought the normals from 3.2 to 0.8 degrees off", min=0.05, max=20.0)
    max_tilt_degrees: float = option(15.0, "no vertex normal ends farther than this from the mesh's own",
                                     min=0.1, max=90.0)
    solver_iterations: int = option(30, "conjugate-gradient iterations of the vertex normals' least-squares moves "
                                        "a round (0: the weighted mean of each vertex's texels' tilts)", min=0,
                                    max=1000)
    refit_iterations: int = option(6, "Levenberg-Marquardt iterations of the reflectance's refit after each round "
                                      "(the fit's own stopping rule may end it sooner)", min=1, max=200)
    min_gain: float = option(1e-4, "a round is kept when the fit's objective falls by more than this, relative",
                             min=0.0, max=1.0)


@dataclasses.dataclass
class NormalsOutcome:
    """What :func:`fit_shading_normals` returns: the fit after its kept rounds, the vertex normals (None: none kept),
    model.json's report and, per kept round, (its probes' seconds, its refit's trace)."""

    result: object
    vertex_normals: np.ndarray | None
    report: dict
    traces: list


def applies(cfg, problem, frames) -> tuple[bool, str]:
    """(whether the shading normals are fitted, why): ``cfg`` the fit stage's config, ``problem`` the fitted
    StreamProblem. The layout must be lit (its light's cosine is what the normals change; a lit problem has already
    refused photos without a light), the fit Levenberg-Marquardt (the refits), and the photos on one device (the
    other devices' parts of split photos hold texel arrays of their own, which the probes do not move)."""
    layout = problem.layout
    if cfg.shading_normals.mode != "on":
        return False, f"shading_normals.mode {cfg.shading_normals.mode}"
    if getattr(problem, "peers", None):
        return False, "the photos are split over devices (stream.device_split photos), whose parts the probes miss"
    if layout.is_radiance or layout.view_terms:
        return False, f"the {layout.kind} model has no light, so the normals change nothing it predicts"
    if cfg.fit.optimizer != "lm":
        return False, f"refits need the Levenberg-Marquardt fit, not {cfg.fit.optimizer}"
    if not frames:
        return False, "no fitted photo"
    return True, "shading_normals.mode on"


def texel_faces(problem, bake) -> tuple[np.ndarray, np.ndarray]:
    """(face (N,), barycentrics (N, 3)) of ``problem``'s compact texels in the bake."""
    index = problem.texels.grid_index
    return bake.face.reshape(-1)[index].astype(np.int64), bake.bary.reshape(-1, 3)[index].astype(np.float64)


def interpolated_normals(vertex_normals: np.ndarray, faces: np.ndarray, face: np.ndarray,
                         bary: np.ndarray) -> np.ndarray:
    """Unit normals at barycentrics ``bary`` of faces ``face``, as the renderer interpolates them
    (render/shading.py ``surface_frame``)."""
    n = np.einsum("nj,njk->nk", bary, vertex_normals[faces[face]])
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)


def tangent_axes(normal: np.ndarray, tangent: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(t1, t2): the texel's tangent made orthogonal to ``normal`` and normal x t1 (an arbitrary perpendicular
    where the tangent is parallel to the normal)."""
    t1 = tangent - normal * np.sum(tangent * normal, axis=1, keepdims=True)
    length = np.linalg.norm(t1, axis=1, keepdims=True)
    bad = length[:, 0] < 1e-6
    if bad.any():
        other = np.where(np.abs(normal[bad, 0:1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
        t1[bad] = np.cross(normal[bad], other)
        length[bad] = np.linalg.norm(t1[bad], axis=1, keepdims=True)
    t1 = t1 / np.maximum(length, 1e-300)
    return t1, np.cross(normal, t1)


def parabola_tilts(f0: np.ndarray, f_plus: np.ndarray, f_minus: np.ndarray, step: float,
                   valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(tilt (N,) in radians, confidence (N,)) along one axis from the objective at -step, 0 and +step.

    Curvature h = (f+ - 2 f0 + f-) / step^2 > 0: the parabola's minimum -g / h (g = (f+ - f-) / 2 step), at most
    2 step either way, confidence h. Otherwise (flat or concave) the better side's step when it is lower than f0,
    with the confidence of a parabola whose minimum is there (|g| / step). ``valid`` False: no tilt, no confidence."""
    g = (f_plus - f_minus) / (2.0 * step)
    h = (f_plus - 2.0 * f0 + f_minus) / (step * step)
    convex = h > 0
    tilt = np.where(convex, -g / np.where(convex, h, 1.0), 0.0)
    tilt = np.clip(tilt, -2.0 * step, 2.0 * step)
    side = np.where(f_plus < f_minus, step, -step)
    lower = np.minimum(f_plus, f_minus) < f0
    tilt = np.where(convex, tilt, np.where(lower, side, 0.0))
    conf = np.where(convex, h, np.where(lower, np.abs(g) / step, 0.0))
    ok = valid & np.isfinite(tilt) & np.isfinite(conf)
    return np.where(ok, tilt, 0.0), np.where(ok, conf, 0.0)


def vertex_tilts(texel_tilt: np.ndarray, confidence: np.ndarray, faces: np.ndarray, face: np.ndarray,
                 bary: np.ndarray, weld: np.ndarray) -> np.ndarray:
    """(V, 3) each vertex's move: the mean of ``texel_tilt`` (N, 3) over the texels on its faces, weighted by
    barycentric weight times ``confidence`` (N,), the copies of a welded vertex (``weld``, per vertex) as one."""
    corner = faces[face].reshape(-1)              # (3N,) vertex of each texel corner
    w = (bary * confidence[:, None]).reshape(-1)  # (3N,)
    welded = weld[corner]
    n_welded = int(weld.max()) + 1 if weld.size else 0
    num = np.zeros((n_welded, 3))
    den = np.zeros(n_welded)
    np.add.at(num, welded, w[:, None] * np.repeat(texel_tilt, 3, axis=0))
    np.add.at(den, welded, w)
    move = np.where(den[:, None] > 0, num / np.maximum(den, 1e-300)[:, None], 0.0)
    return move[weld]


def vertex_moves(tilts, curvatures, axes, faces: np.ndarray, face: np.ndarray, bary: np.ndarray, weld: np.ndarray,
                 iterations: int, max_move: float, ridge: float = 0.1) -> np.ndarray:
    """(V, 3) the vertex normals' moves that best give each texel its tilt: the least-squares solution of

        sum_t sum_a h_a,t (axis_a,t . sum_v b_t,v m_v - tilt_a,t)^2 + ridge sum_v d_v |m_v|^2

    (a texel's normal moves by the barycentric mix of its vertices' moves; h its parabolas' curvatures, d_v the
    vertex's share of them, so a vertex few texels constrain stays near its normal) by ``iterations`` of
    Jacobi-preconditioned conjugate gradients from the weighted mean of its texels' tilts (:func:`vertex_tilts`, the
    exact answer where every texel of a vertex wants the same), the copies of a vertex along seams as one; each move
    at most ``max_move`` radians. ``tilts``, ``curvatures``: per tangent axis (N,); ``axes``: the (N, 3) axes."""
    n_welded = int(weld.max()) + 1 if weld.size else 0
    corner = weld[faces[face]]                                         # (N, 3) welded vertex of each corner

    def spread(x):  # (welded, 3) -> per texel, its normal's move (N, 3)
        return np.einsum("nk,nkj->nj", bary, x[corner])

    def gather(z):  # per texel (N, 3) -> (welded, 3), the transpose of spread
        out = np.zeros((n_welded, 3))
        np.add.at(out, corner.reshape(-1), (bary[:, :, None] * z[:, None, :]).reshape(-1, 3))
        return out

    def weigh(y):  # each texel's quadratic form: sum_a h_a axis_a (axis_a . y)
        return sum(h[:, None] * ax * np.sum(ax * y, axis=1, keepdims=True) for h, ax in zip(curvatures, axes))

    conf = curvatures[0] + curvatures[1]
    d = np.zeros(n_welded)
    np.add.at(d, corner.reshape(-1), (bary ** 2 * conf[:, None]).reshape(-1))
    d = np.maximum(d, 1e-300)
    lam = ridge * d[:, None]
    rhs = gather(sum(h[:, None] * t[:, None] * ax for h, t, ax in zip(curvatures, tilts, axes)))
    apply = lambda x: gather(weigh(spread(x))) + lam * x  # noqa: E731
    tilt = sum(t[:, None] * ax for t, ax in zip(tilts, axes))
    x = vertex_tilts(tilt, conf, faces, face, bary, weld)[np.unique(weld, return_index=True)[1]]
    r = rhs - apply(x)
    z = r / ((1.0 + ridge) * d[:, None])
    p = z.copy()
    rz = float(np.sum(r * z))
    for _ in range(iterations):
        if rz <= 0:
            break
        ap = apply(p)
        alpha = rz / max(float(np.sum(p * ap)), 1e-300)
        x += alpha * p
        r -= alpha * ap
        z = r / ((1.0 + ridge) * d[:, None])
        rz_new = float(np.sum(r * z))
        p = z + (rz_new / rz) * p
        rz = rz_new
    length = np.linalg.norm(x, axis=1, keepdims=True)
    x *= np.minimum(1.0, max_move / np.maximum(length, 1e-300))
    return x[weld]


def limit_tilt(normals: np.ndarray, reference: np.ndarray, max_angle: float) -> np.ndarray:
    """``normals`` turned back towards ``reference`` (both unit, (V, 3)) where they are more than ``max_angle``
    radians apart, to that angle."""
    cos = np.clip(np.sum(normals * reference, axis=1), -1.0, 1.0)
    angle = np.arccos(cos)
    far = angle > max_angle
    if not far.any():
        return normals
    out = normals.copy()
    perp = normals[far] - reference[far] * cos[far, None]
    perp /= np.maximum(np.linalg.norm(perp, axis=1, keepdims=True), 1e-300)
    out[far] = reference[far] * math.cos(max_angle) + perp * math.sin(max_angle)
    return out


class TexelNormals:
    """The fitted problem's normals, moved together: the texels' (``TexelSet`` and the kernels' arrays), the normal
    Jacobians of point sampling and the mesh's vertex normals of traced taps."""

    def __init__(self, problem, mesh, bake):
        self.problem, self.mesh = problem, mesh
        self.faces = np.asarray(mesh.faces, np.int64)
        self.points = np.asarray(mesh.vertices, np.float64)
        self.face, self.bary = texel_faces(problem, bake)
        self.tangent = np.asarray(problem.texels.tangent, np.float64)

    def snapshot(self):
        """A function that puts back the problem's texels and texel arrays and the traced taps' vertex normals as they
        are now, bit for bit."""
        pr, photos = self.problem, self.problem.photos
        texels = pr.texels
        arrays = [(a, a.numpy().copy()) for a in (pr.nrm, pr.tan, pr.bit, pr.tex.dn_dp)]
        mesh_normals = getattr(photos, "mesh_normals", None)
        saved_normals = None if mesh_normals is None else mesh_normals.numpy().copy()
        mesh_arrays = getattr(photos, "mesh_arrays", None)

        def restore() -> None:
            pr.texels = texels
            for a, values in arrays:
                a.assign(values)
            if saved_normals is not None:
                photos.mesh_normals.assign(saved_normals)
            if mesh_arrays is not None:
                photos.mesh_arrays = mesh_arrays

        return restore

    def texel_normals(self, vertex_normals: np.ndarray) -> np.ndarray:
        return interpolated_normals(vertex_normals, self.faces, self.face, self.bary)

    def probe(self, normals: np.ndarray) -> None:
        """The kernels' texel normals alone set to ``normals`` (N, 3): a probe of the objective."""
        self.problem.nrm.assign(np.ascontiguousarray(normals, np.float32))

    def set_vertex_normals(self, vertex_normals: np.ndarray) -> None:
        """Everything the passes read set from ``vertex_normals`` (V, 3): texel normals, tangent frames, normal
        Jacobians, the traced taps' vertex normals."""
        pr = self.problem
        n = self.texel_normals(vertex_normals)
        t1, t2 = tangent_axes(n, self.tangent)
        _, jac = surface_derivatives(self.points, self.faces, vertex_normals, self.face, self.bary)
        f32 = lambda a: np.ascontiguousarray(a, np.float32)  # noqa: E731
        pr.texels = dataclasses.replace(pr.texels, normal=f32(n), tangent=f32(t1), bitangent=f32(t2),
                                        normal_jacobian=f32(jac))
        pr.nrm.assign(pr.texels.normal)
        pr.tan.assign(pr.texels.tangent)
        pr.bit.assign(pr.texels.bitangent)
        pr.tex.dn_dp.assign(pr.texels.normal_jacobian)
        photos = pr.photos
        if getattr(photos, "mesh_normals", None) is not None:
            photos.mesh_normals.assign(f32(vertex_normals))
        arrays = getattr(photos, "mesh_arrays", None)
        if arrays is not None:
            photos.mesh_arrays = (arrays[0], arrays[1], f32(vertex_normals), arrays[3])


def probe_objectives(normals: TexelNormals, params: np.ndarray, texel_normal: np.ndarray,
                     step: float) -> tuple[np.ndarray, list, np.ndarray, tuple]:
    """(objective at the normals (N,), [(f+, f-) per tangent axis], whether each axis's sample counts agree with
    the normals' (N, 2), the tangent axes (t1, t2)): five streaming passes at ``params``."""
    t1, t2 = tangent_axes(texel_normal, normals.tangent)
    normals.probe(texel_normal)
    f0, count0 = per_texel_objective_and_samples(normals.problem, params)
    pairs, same = [], np.ones((texel_normal.shape[0], 2), bool)
    for a, axis in enumerate((t1, t2)):
        values = []
        for sign in (1.0, -1.0):
            turned = texel_normal * math.cos(step) + sign * axis * math.sin(step)
            normals.probe(turned)
            f, count = per_texel_objective_and_samples(normals.problem, params)
            values.append(f)
            same[:, a] &= np.rint(3.0 * count) == np.rint(3.0 * count0)  # a count sums 1/3 per channel
        pairs.append(tuple(values))
    normals.probe(texel_normal)
    return f0, pairs, same, (t1, t2)


HARM_SHARE = 0.01
"""a texel whose objective a round's proposal raises (the parameters held) by more than this share of the whole
objective keeps its vertices' normals: on the photos-only flash capture a few such texels raised the whole fit's
objective 40-75x in one round. Smaller rises are the rule on glossy texels whose lobe has not yet followed its
normal (4-5% of the sphere_room's texels rise tenfold in a round whose total falls 10-30%): holding those back too
(a first version of the rule, with vertex averaging) left the turned normals 1.7 degrees off instead of 0.8"""


def _without_harmful_moves(normals: TexelNormals, proposed: np.ndarray, current: np.ndarray, weld: np.ndarray,
                           params: np.ndarray, f0: np.ndarray) -> tuple[np.ndarray, float]:
    """(``proposed`` vertex normals less the moves of the vertices of texels they harm (:data:`HARM_SHARE`), the
    objective at them with ``params`` held), the normals set on the problem; one streaming pass, two where some
    harm."""
    normals.set_vertex_normals(proposed)
    f = per_texel_objective_and_samples(normals.problem, params)[0]
    harmed = f - f0 > HARM_SHARE * float(np.sum(f0))
    if not harmed.any():
        return proposed, float(np.sum(f))
    kept_back = np.zeros(int(weld.max()) + 1, bool)
    kept_back[weld[normals.faces[normals.face[harmed]]].reshape(-1)] = True
    proposed = np.where(kept_back[weld][:, None], current, proposed)
    normals.set_vertex_normals(proposed)
    return proposed, float(np.sum(per_texel_objective_and_samples(normals.problem, params)[0]))


def fit_shading_normals(problem, result, mesh, bake, cfg, refit, log=lambda m: None) -> NormalsOutcome:
    """The shading normals' rounds (module doc) from the fit ``result`` on ``problem`` (set up on ``mesh`` and
    ``bake``); ``cfg``: the fit stage's config; ``refit(params)``: the reflectance fitted again from ``params`` on
    the problem as it now is (a FitResult). Returns the kept fit and vertex normals (the problem left with them)."""
    ncfg = cfg.shading_normals
    t0 = time.perf_counter()
    normals = TexelNormals(problem, mesh, bake)
    restore = normals.snapshot()
    reference = np.asarray(mesh.vertex_normals(), np.float64)
    reference = reference / np.maximum(np.linalg.norm(reference, axis=1, keepdims=True), 1e-300)
    weld = np.asarray(mesh.weld_key(), np.int64)
    step = math.radians(ncfg.step_degrees)
    current, kept_result = reference.copy(), result
    rounds = []
    seen = result.samples > 0
    traces = []
    for r in range(ncfg.rounds):
        t_round = time.perf_counter()
        texel_normal = normals.texel_normals(current)
        f0, pairs, same, axes = probe_objectives(normals, kept_result.params, texel_normal, step)
        tilts, curvatures = zip(*(parabola_tilts(f0, pairs[a][0], pairs[a][1], step, same[:, a] & seen)
                                  for a in range(2)))
        move = vertex_moves(tilts, curvatures, axes, normals.faces, normals.face, normals.bary, weld,
                            ncfg.solver_iterations, 2.0 * step)
        proposed = current + move
        proposed /= np.maximum(np.linalg.norm(proposed, axis=1, keepdims=True), 1e-300)
        proposed = limit_tilt(proposed, reference, math.radians(ncfg.max_tilt_degrees))
        # the normals' own effect, the reflectance held: the refit after it gains whatever the normals do
        proposed, at_new_normals = _without_harmful_moves(normals, proposed, current, weld, kept_result.params, f0)
        before = float(np.sum(f0))
        gain = (before - at_new_normals) / max(abs(before), 1e-300)
        moved = np.degrees(np.arccos(np.clip(np.sum(normals.texel_normals(proposed) * texel_normal, axis=1),
                                             -1.0, 1.0)))[seen]
        row = {"round": r + 1, "objective": before, "objective_new_normals": at_new_normals, "relative_gain": gain,
               "texels_turned_degrees_median": float(np.median(moved)) if moved.size else 0.0,
               "texels_turned_degrees_p90": float(np.percentile(moved, 90)) if moved.size else 0.0}
        if not gain > ncfg.min_gain:
            normals.set_vertex_normals(current)  # undone: the problem as the kept rounds left it
            rounds.append({**row, "kept": False, "seconds": time.perf_counter() - t_round})
            log(f"shading normals: round {r + 1} lowered the objective by {100 * gain:.3f}% with the reflectance "
                f"held (not more than {100 * ncfg.min_gain:.3f}%): undone, the rounds stop")
            break
        probe_s = time.perf_counter() - t_round
        kept_result = refit(kept_result.params)
        current = proposed
        row.update(kept=True, objective_refitted=float(kept_result.trace[-1]["objective"]),
                   seconds=time.perf_counter() - t_round)
        rounds.append(row)
        traces.append((probe_s, kept_result.trace))
        log(f"shading normals: round {r + 1}: texels turned {row['texels_turned_degrees_median']:.2f} degrees median "
            f"({row['texels_turned_degrees_p90']:.2f} at p90), the objective {100 * gain:.2f}% lower with the "
            f"reflectance held, {row['objective_refitted'] / before:.4f}x after its refit")
    kept = sum(row["kept"] for row in rounds)
    if not kept:
        restore()  # the arrays the fit ran on, not their recomputation from the mesh's normals
    total = np.degrees(np.arccos(np.clip(np.sum(normals.texel_normals(current)
                                                * normals.texel_normals(reference), axis=1), -1.0, 1.0)))[seen]
    report = {"mode": ncfg.mode, "rounds_kept": kept, "rounds": rounds,
              "from_mesh_degrees_median": float(np.median(total)) if total.size else 0.0,
              "from_mesh_degrees_p90": float(np.percentile(total, 90)) if total.size else 0.0,
              "seconds": time.perf_counter() - t0, "config": dataclasses.asdict(ncfg)}
    return NormalsOutcome(kept_result, current if kept else None, report, traces)


def bake_with(bake, problem):
    """A copy of ``bake`` whose covered texels' normal, tangent and bitangent are ``problem``'s texels' (after
    :meth:`TexelNormals.set_vertex_normals`): the bake.npz of a model with fitted normals."""
    index = problem.texels.grid_index
    grids = {}
    for name in ("normal", "tangent", "bitangent"):
        grid = np.array(getattr(bake, name), np.float32).reshape(-1, 3)
        grid[index] = getattr(problem.texels, name)
        grids[name] = grid.reshape(bake.height, bake.width, 3)  # uncovered texels keep the bake's zeros
    return dataclasses.replace(bake, **grids)
