"""The fit loop: initial guess, iterations of an optimizer, trace and stopping.

Everything inside an iteration is kernel launches on one device. Per iteration the host only
waits for the device to finish (for honest wall times) and, every ``sync_every`` iterations,
reads the small trace buffer to test the stopping rules.
"""

from __future__ import annotations

import dataclasses
import math
import time

import numpy as np
import warp as wp

from texstream.core.errors import ConfigError
from texstream.core.config import option

from texstream.fit.kernels import optim_kernels as K
from texstream.fit.kernels import stream
from texstream.render.layout import ModelLayout, layout_traits
from texstream.fit.optim.base import FitState
from texstream.fit.optim.cg import ConjugateGradient
from texstream.fit.optim.lbfgs import LBFGS
from texstream.fit.optim.linesearch import LineSearchConfig, line_search
from texstream.fit.optim.lm import LevenbergMarquardt
from texstream.fit.optim.steepest import SteepestDescent
from texstream.fit.stream.penalties import PenaltyConfig, Penalties
from texstream.fit.optim.env_config import EnvDiffuseConfig
from texstream.fit.optim.lfm_config import LFMConfig
from texstream.fit.stream.config import StreamConfig
from texstream.fit.stream.problem import StreamProblem, no_light_error

OPTIMIZERS = ("sd", "cg", "lbfgs", "lm")
TRACE_CHUNKS = 4096
"""the trace's first reduction level: chunks of texels, each summed in order by one thread, then the chunks
in order (a fixed summation order, so the trace is the same on every run and device)"""


@dataclasses.dataclass
class FitConfig:
    """What to fit and how (saved as fit_config.json beside the model)."""

    model: str = option("lafortune", "appearance model, a kind of the model registry (fit/models/; `texstream fit "
                                     "--help` lists them): lafortune or diffuse (reflectance, need a known light per "
                                     "photo), radiance (view-independent radiance under the photos' one fixed, "
                                     "unknown lighting; ignores lights), view_radiance (that radiance as a "
                                     "biquadratic of the view direction), lfm (light field mapping: vertex light "
                                     "fields of surface maps x view maps; options --lfm.*), env_diffuse (albedo under an "
                                     "estimated order-2 SH environment light, relightable; options --env.*), or "
                                     "auto: the model "
                                     "choice (fit/stages/choice.py) fits the candidates the capture calls for and "
                                     "keeps the one that predicts a validation split of the fitted photos best")
    view_prior: float = option(0.5, "view_radiance: ridge prior pulling each texel's view terms to 0, in samples' "
                                    "worth of squared residual per unit coefficient (a texel seen from few directions "
                                    "stays view-independent); 0 = none", min=0.0)
    lobes: int = option(1, "specular lobes K (0..2)", min=0, max=2)
    anisotropic: bool = option(False, "general C_x, C_y, C_z lobes instead of isotropic C_xy, C_z")
    lobe_shape: str = option("auto", "free fits each lobe's c_z, phong holds it at 1; auto picks phong when every "
                                     "photo's light-view angle lies within lobe_shape_spread_deg of the others "
                                     "(a light beside the camera: c_z and rho_s cannot be told apart, render/layout.py)",
                             choices=("auto", "free", "phong"))
    ambient: str = option("off", "a per-texel ambient radiance beside the lit reflectance (lafortune, diffuse: the "
                                 "room's light, seen the same from every view, render/layout.py): off, on, or auto "
                                 "(fitted with and without it on a validation split of the fitted photos, "
                                 "materials.validation_every, and kept where it predicts them better; "
                                 "fit/models/per_texel/ambient.py); room: the room's light as one global SH "
                                 "environment lighting the same albedo (27 unknowns, fit/models/per_texel/"
                                 "room_light.py), which auto also weighs", choices=("off", "on", "room", "auto"))
    lobe_shape_spread_deg: float = option(10.0, "auto lobe shape: the spread of light-view angles below which c_z is held",
                                          min=0.0, max=180.0)
    optimizer: str = option("lm", "sd, cg, lbfgs or lm (per-texel Levenberg-Marquardt)", choices=OPTIMIZERS)
    cg_variant: str = option("pr", "conjugate gradient beta: pr (Polak-Ribiere+) or fr (Fletcher-Reeves)", choices=("pr", "fr"))
    cg_restart_every: int = option(0, "steepest-descent restart every m CG iterations (0 = never)", min=0)
    lbfgs_history: int = option(5, "L-BFGS history pairs m", min=1)
    precondition: str = option("jacobi", "sd, cg and lbfgs: jacobi scales the gradient by the inverse Gauss-Newton "
                                         "diagonal diag(J^T J) of each texel (accumulated in the gradient pass; "
                                         "CG holds it between restarts, L-BFGS uses it as H0), none = raw gradient",
                               choices=("none", "jacobi"))
    precondition_refresh: str = option("restart", "cg with jacobi: take M from the current point at each texel's "
                                                  "restart (CG theory: a fixed metric between restarts) or every "
                                                  "iteration", choices=("restart", "iteration"))
    precondition_floor: float = option(1e-10, "Jacobi preconditioner M = D + this * mean(D over free columns): "
                                              "guards columns no sample constrains; keep it tiny, the exponent's "
                                              "D is ~1e-7 of the albedos'", min=0.0, max=1.0)
    lm_lambda0: float = option(1e-3, "initial Levenberg-Marquardt damping", min=0.0)
    lookup_refresh_every: int = option(0, "stream.model_lookup bilinear: hold the neighbours at the current "
                                          "parameters again every k iterations (each refresh costs a pass and "
                                          "restarts CG / L-BFGS memory); 0 = 1 for lm, 10 for the others",
                                          min=0)
    lookup_relaxation: float = option(1.0, "stream.model_lookup bilinear: a refresh moves the held neighbours this "
                                           "fraction of the way to the current parameters (damped Jacobi: texels a "
                                           "pixel or less wide, whose taps read their neighbours as much as "
                                           "themselves, oscillate at 1: use 0.5; docs/accuracy.md)",
                                           min=1e-6, max=1.0)
    max_iterations: int = option(100, "iteration cap", min=1)
    time_budget_s: float = option(0.0, "stop after this many seconds (0 = no limit)", min=0.0)
    rel_tol: float = option(1e-7, "stop when the objective's relative decrease over sync_every iterations is below this",
                            min=0.0, max=1.0)
    sync_every: int = option(5, "iterations between reads of the trace buffer (stopping tests)", min=1)
    diffuse_free_iterations: int = option(-1, "seed's schedule: diffuse free for the first k iterations then fixed (-1 = always free)",
                                          min=-1)
    init: str = option("percentile", "initial guess: percentile (McAllister low percentile diffuse) or defaults",
                       choices=("percentile", "defaults"))
    init_rank: int = option(1, "which smallest reflectance sample (0..3) estimates the diffuse part",
                            min=0, max=3)
    lobe_albedo_max: float = option(1.0, "energy bound: each lobe's rho_s <= this * (n + 2) / (2 pi), the largest "
                                          "albedo a normalised lobe may have (stops one highlight sample from "
                                          "producing a broad, enormously bright lobe); 0 = off", min=0.0)
    robust_loss: str = option("auto", "loss of each channel residual r: none (least squares, r^2 / 2), huber or "
                                      "cauchy (robust, iteratively reweighted in the passes); auto: cauchy for the "
                                      "radiance model (a highlight or other outlier seen in a few photos hardly "
                                      "moves a texel's radiance), none for the others (the view-dependent radiance "
                                      "fits the photos' disagreement across directions)",
                              choices=("auto", "none", "huber", "cauchy"))
    robust_scale: float = option(0.0, "the robust loss's scale k in residual units (photo values in radiance "
                                       "space): residuals well below k are least squares, above it down-weighted; "
                                       "0 = auto: robust_scale_fraction x the mean photo value the texels see "
                                       "(read once before the iterations)", min=0.0)
    robust_scale_fraction: float = option(0.1, "robust_scale 0: the scale as a fraction of the mean sampled photo "
                                               "value (0.1: noise and shading a radiance model cannot express, a few "
                                               "percent, stay least squares; a highlight twice the diffuse level "
                                               "weighs ~1/100 under cauchy)", min=0.0)
    psnr_peak: float = option(1.0, "peak pixel value for the trace's PSNR", min=1e-12)
    linesearch: LineSearchConfig = option(default_factory=LineSearchConfig, help="line search")
    penalties: PenaltyConfig = option(default_factory=PenaltyConfig, help="penalties")
    stream: StreamConfig = option(default_factory=StreamConfig, help="streaming and numerics")
    lfm: LFMConfig = option(default_factory=LFMConfig, help="light field mapping (--model lfm)")
    env: EnvDiffuseConfig = option(default_factory=EnvDiffuseConfig,
                                   help="relightable diffuse model under one unknown environment (--model env_diffuse)")

    def loss(self, layout: ModelLayout) -> str:
        """The robust loss the fit uses for ``layout`` (``robust_loss`` with auto resolved)."""
        if self.robust_loss == "auto":
            # the view-dependent radiance fits what cauchy would discount as outliers (the photos'
            # disagreement across directions), so it stays least squares
            return layout_traits(layout.kind).robust_loss
        if self.robust_loss not in ("none", "huber", "cauchy"):
            raise ConfigError(f"robust_loss {self.robust_loss!r} unknown", fix="use auto, none, huber or cauchy")
        return self.robust_loss

    def layout(self, frames=None, centre=None) -> ModelLayout:
        """The model layout; ``lobe_shape`` "auto" is decided from the photos' ``frames``
        (:class:`PhotoFrame`) seen from ``centre`` (:func:`choose_lobe_shape`)."""
        shape = self.lobe_shape
        traits = layout_traits(self.model)
        if not traits.lit:
            return ModelLayout(kind=self.model)
        if frames is not None:
            unlit = sum(getattr(f, "light_kind", None) == "none" for f in frames)
            if unlit:
                raise no_light_error(unlit, len(frames), self.model)
        if not traits.lobes:
            shape = "free"  # no lobe: nothing to hold
        elif shape == "auto":
            if frames is None:
                raise ConfigError("lobe_shape auto needs the photos to decide", fix="pass frames, or set free or phong")
            shape = choose_lobe_shape(frames, centre, self.lobe_shape_spread_deg)
        return ModelLayout(kind=self.model, n_lobes=self.lobes if traits.lobes else 0,
                           anisotropic=self.anisotropic, lobe_shape=shape, ambient=self.ambient == "on",
                           room=self.ambient == "room")


def light_view_angles(frames, centre) -> np.ndarray:
    """Angle (degrees) between the directions from ``centre`` to each lit photo's camera and light. A photo whose
    light is 0 (taken with the flash off, wherever the capture places its light) shows no highlight and is left
    out."""
    centre = np.asarray(centre, dtype=np.float64)
    frames = [f for f in frames if float(np.max(np.asarray(f.light_intensity, np.float64))) > 0]
    if len(frames) == 0:
        return np.empty(0)
    rot = np.array([f.R for f in frames], np.float64).reshape(-1, 3, 3)
    trans = np.array([f.t for f in frames], np.float64).reshape(-1, 3)
    light = np.array([f.light_vec for f in frames], np.float64).reshape(-1, 3)
    point = np.array([f.light_kind == "point" for f in frames])
    to_cam = -np.einsum("nji,nj->ni", rot, trans) - centre
    # a directional light's vector points the way the light travels (shading.incident_light)
    to_light = np.where(point[:, None], light - centre, -light)
    cos = np.einsum("ni,ni->n", to_cam, to_light) / np.maximum(
        np.linalg.norm(to_cam, axis=1) * np.linalg.norm(to_light, axis=1), 1e-30)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def choose_lobe_shape(frames, centre, spread_deg: float) -> str:
    """"phong" when the light-view angles of all photos lie within ``spread_deg`` of each other, else "free".

    Every highlight is then seen at about one half-angle theta_h, where the lobe's height is
    rho_s (sin^2 theta_h + c_z cos^2 theta_h)^n: the photos fix that height, not rho_s and c_z apart
    (render/layout.py), and a free c_z lets rho_s wander by factors along it. Holding c_z at 1 keeps
    every prediction at the captured geometry and makes rho_s the height.
    """
    angles = light_view_angles(frames, centre)
    if angles.size == 0 or float(angles.max() - angles.min()) >= spread_deg:
        return "free"
    return "phong"


@dataclasses.dataclass
class FitResult:
    """Fitted parameters per texel, per-texel sample counts, and the trace."""

    params: np.ndarray
    samples: np.ndarray
    trace: list[dict]
    layout: ModelLayout
    passes: int
    robust_loss: str = "none"
    """the data term's loss (``FitConfig.loss``)"""
    robust_scale: float = 0.0
    """its scale in residual units (resolved when ``FitConfig.robust_scale`` is 0)"""

    @property
    def seen(self) -> np.ndarray:
        return self.samples > 0


def make_optimizer(cfg: FitConfig):
    if cfg.penalties.smooth_weight > 0 and cfg.optimizer != "lm":
        raise ConfigError(f"penalties.smooth_weight is implemented for lm, not {cfg.optimizer}",
                          fix="use --optimizer lm, or --penalties.laplacian_weight with sd, cg and lbfgs")
    if cfg.precondition not in ("none", "jacobi"):
        raise ConfigError(f"precondition {cfg.precondition!r} unknown", fix="use none or jacobi")
    pc = dict(precondition=cfg.precondition == "jacobi", precondition_floor=cfg.precondition_floor)
    if cfg.optimizer == "sd":
        return SteepestDescent(**pc)
    if cfg.optimizer == "cg":
        if cfg.precondition_refresh not in ("restart", "iteration"):
            raise ConfigError(f"precondition_refresh {cfg.precondition_refresh!r} unknown",
                              fix="use restart or iteration")
        return ConjugateGradient(cfg.cg_variant, cfg.cg_restart_every, **pc,
                                 refresh_always=cfg.precondition_refresh == "iteration")
    if cfg.optimizer == "lbfgs":
        return LBFGS(cfg.lbfgs_history, **pc)
    if cfg.optimizer == "lm":
        return LevenbergMarquardt(cfg.lm_lambda0, cfg.penalties)
    raise ConfigError(f"optimizer {cfg.optimizer!r} unknown", fix=f"use one of {OPTIMIZERS}")


@dataclasses.dataclass
class FitStart:
    """Where a fit starts, on the problem's device: ``params`` the (N, n_params) float64 starting parameters
    (before the projection onto the bounds, :meth:`FitState.create`) and ``counts`` the (N,) int32 samples
    per texel (0: no photo sees it)."""

    params: wp.array
    counts: wp.array

    def numpy(self) -> tuple[np.ndarray, np.ndarray]:
        """(parameters, sample counts) as NumPy arrays."""
        return self.params.numpy(), self.counts.numpy()

    @staticmethod
    def of(start, problem: StreamProblem) -> "FitStart":
        """``start`` as a FitStart on the problem's device: a FitStart, or (parameters, counts) arrays."""
        if isinstance(start, FitStart):
            return start
        guess, counts = start
        dev = problem.device
        return FitStart(wp.array(np.ascontiguousarray(guess, dtype=np.float64), dtype=wp.float64, device=dev),
                        wp.array(np.ascontiguousarray(counts, dtype=np.int32), dtype=wp.int32, device=dev))


def fit_start(problem: StreamProblem, cfg: FitConfig) -> FitStart:
    """The initial guess's streaming pass and the starting parameters made from it, on the device (no host
    round trip): with ``init`` "percentile", a low percentile of each texel's samples as its diffuse term (or
    radiance) and the brightest sample's excess as its lobes' rho_s; else the layout's defaults."""
    lay = problem.layout
    n = problem.n
    dev = problem.device
    low = wp.zeros(n, dtype=wp.vec3, device=dev)
    high = wp.zeros(n, dtype=wp.vec3, device=dev)
    count = wp.zeros(n, dtype=wp.int32, device=dev)
    kernel = stream.initial_guess_kernel_for(lay.is_radiance)
    if problem.peers:
        problem.split_initial_guess(kernel, int(cfg.init_rank), low, high, count)
    else:
        # streamed windows carry each texel's 4 smallest samples per channel from one window to the next, so
        # the percentile is the one-pass value whatever the windows
        windowed = problem.photos.window < problem.photos.n
        lists = wp.empty(n if windowed else 1, dtype=wp.mat44, device=dev)
        for k, (images, depth, shadow, infos, b, e) in enumerate(problem.photos.windows()):
            keep = 0 if not windowed else (1 if k == 0 else 2)
            wp.launch(kernel, dim=n, device=dev,
                      inputs=[problem.tex, images, depth, shadow, infos, b, e,
                              problem.opt, int(cfg.init_rank), keep], outputs=[low, high, count, lists])
    guess = wp.empty((n, lay.n_params), dtype=wp.float64, device=dev)
    as_f64 = {name: wp.array(v, dtype=wp.float64, device=dev)
              for name, v in (("defaults", lay.defaults()), ("lower", lay.lower()), ("upper", lay.upper()))}
    # rho_d in [0, 10], L in [0, 1000]; a lobe peaks at rho_s (max(s,0)^n <= 1 at c_z = 1), so it starts at the
    # excess of the brightest sample
    wp.launch(K.guess_from_samples_kernel, dim=n, device=dev,
              inputs=[low, high, count, as_f64["defaults"], as_f64["lower"], as_f64["upper"],
                      int(cfg.init == "percentile"), lay.n_lobes, lay.lobe_stride, wp.float64(0.05)], outputs=[guess])
    return FitStart(guess, count)


def initial_guess(problem: StreamProblem, cfg: FitConfig) -> tuple[np.ndarray, np.ndarray]:
    """Parameters to start from and the per-texel sample counts (one streaming pass): :func:`fit_start`
    as NumPy arrays."""
    return fit_start(problem, cfg).numpy()


def start_arrays(start, problem: StreamProblem, cfg: FitConfig) -> tuple[np.ndarray, np.ndarray]:
    """(parameters, sample counts) as NumPy arrays from ``start`` (a :class:`FitStart`, arrays, or None: the
    initial guess's pass)."""
    if start is None:
        return initial_guess(problem, cfg)
    return start.numpy() if isinstance(start, FitStart) else start


def resumable(cfg: FitConfig) -> bool:
    """Whether a fit with ``cfg`` resumes from a checkpoint to the bit: LM without smoothness or the
    renderer's lookup, whose whole state between iterations is the parameters and the damping."""
    return (cfg.optimizer == "lm" and cfg.penalties.smooth_weight <= 0 and cfg.stream.model_lookup == "texel"
            and cfg.diffuse_free_iterations < 0)


def run_fit(problem: StreamProblem, cfg: FitConfig, p0: np.ndarray | None = None,
            progress=None, checkpoint=None, resume: dict | None = None,
            start: "FitStart | tuple[np.ndarray, np.ndarray] | None" = None) -> FitResult:
    """Fit the problem's model; returns parameters, sample counts and the per-iteration trace.

    ``checkpoint(state_dict)`` is called at every stopping-test sync (every ``sync_every``
    iterations) with what ``resume`` takes to continue the fit from there; for :func:`resumable`
    configs the resumed fit takes the same iterations to the same parameters, to the last bit, on
    one device. ``start``: :func:`fit_start`'s :class:`FitStart` (or :func:`initial_guess`'s arrays) when
    the caller has already streamed that pass.
    """
    run = FitRun(problem, cfg, p0=p0, checkpointed=checkpoint is not None, resume=resume, start=start)
    if resume is None and run.needs_scale_pass():
        run.begin(robust_scale_from_stats(run.scale_pass_stats(), cfg))
    else:
        run.begin()
    last_obj = run.last_obj
    it_done = run.first - 1
    for it in range(run.first, cfg.max_iterations + 1):
        run.iterate(it)
        it_done = it
        if progress is not None:
            progress(it)
        if stop_test_due(it, cfg):
            obj = float(run.trace_buf.numpy()[it, 0])
            if converged(last_obj, obj, cfg):
                break
            last_obj = obj
            if checkpoint is not None and it < cfg.max_iterations:
                checkpoint(run.checkpoint_state(it, last_obj))
            if cfg.time_budget_s > 0 and run.times[-1] >= cfg.time_budget_s:
                break
    return run.result(trace_rows(run.trace_buf.numpy()[:it_done + 1], run.times, cfg))


def stop_test_due(it: int, cfg: FitConfig) -> bool:
    """Whether iteration ``it`` ends with a stopping test (every ``sync_every`` iterations, and the last)."""
    return it % max(cfg.sync_every, 1) == 0 or it == cfg.max_iterations


def converged(last_obj: float | None, obj: float, cfg: FitConfig) -> bool:
    """The stopping rule: the objective's relative decrease since the last test is at most ``rel_tol``."""
    return last_obj is not None and abs(last_obj - obj) <= cfg.rel_tol * max(abs(obj), 1e-300)


def robust_scale_from_stats(stats: np.ndarray, cfg: FitConfig) -> float:
    """The robust loss's automatic scale from a pass's (N, 4) per-texel statistics at the starting point:
    ``robust_scale_fraction`` x the mean sampled photo value."""
    st = np.asarray(stats).sum(axis=0)
    mean_y = st[3] / max(3.0 * st[0], 1e-300)
    if not mean_y > 0:
        mean_y = 1.0  # no samples, or black photos: any scale will do
    return cfg.robust_scale_fraction * mean_y


def trace_rows(tb: np.ndarray, times, cfg: FitConfig) -> list[dict]:
    """The trace (one dict per iteration) from the (iterations, 8) trace sums and wall times."""
    trace = []
    for k in range(tb.shape[0]):
        obj, g2, ns, sse, sabs, sy, acc, nvalid = tb[k]
        mse = sse / max(ns * 3.0, 1.0)
        trace.append({"iteration": k, "time_s": times[k], "objective": obj, "grad_norm": math.sqrt(max(g2, 0.0)),
                      "samples": int(round(ns)),
                      "psnr_db": 10.0 * math.log10(cfg.psnr_peak ** 2 / mse) if mse > 0 else float("inf"),
                      "ape_percent": 100.0 * sabs / sy if sy > 0 else 0.0,
                      "accepted_fraction": acc / nvalid if nvalid > 0 else 0.0})
    return trace


class FitRun:
    """One problem's fit between iterations: state, optimizer and the trace buffer on the device.

    :func:`run_fit` drives one; a tiled fit (fit/multi/tiles.py) drives one per tile in lockstep and sums their
    trace rows (every column of a row is a sum over texels) for one stopping test over all texels.
    Call :meth:`begin` once (after :meth:`scale_pass_stats` when :meth:`needs_scale_pass`), then
    :meth:`iterate` for iterations ``first``, ``first + 1``, ...
    """

    def __init__(self, problem: StreamProblem, cfg: FitConfig, p0: np.ndarray | None = None,
                 checkpointed: bool = False, resume: dict | None = None,
                 start: "FitStart | tuple[np.ndarray, np.ndarray] | None" = None):
        self.problem, self.cfg, self.resume = problem, cfg, resume
        lay = problem.layout
        n = problem.n
        dev = problem.device
        self.t_start = time.perf_counter()
        if (checkpointed or resume is not None) and not resumable(cfg):
            raise ConfigError("only Levenberg-Marquardt fits without smoothness, lookup or diffuse schedule resume "
                              "from a checkpoint", fix="drop the checkpoint, or use --optimizer lm")
        start = FitStart.of(start, problem) if start is not None else fit_start(problem, cfg)
        guess = start.params if p0 is None else np.asarray(p0, dtype=np.float64)
        self.counts = start.counts
        """(N,) samples per texel on the device"""
        self.free = ~lay.frozen()
        self.state = state = FitState.create(problem, guess, self.free, lobe_albedo_max=cfg.lobe_albedo_max,
                                             counts=start.counts)
        if resume is not None:
            # exactly the checkpoint's parameters (create() re-projects them in float64), and their storage
            state.p.assign(np.asarray(resume["p"]))
            state.store_current()
        self.penalties = Penalties(problem, cfg.penalties)
        self.opt = opt = make_optimizer(cfg)
        if cfg.linesearch.kind not in ("backtracking", "hessian", "quadratic"):
            raise ConfigError(f"line search {cfg.linesearch.kind!r} unknown", fix="use backtracking, hessian or quadratic")
        # trace buffer: objective, |g|^2, samples, SSE, sum|r|, sum|y|, accepted, valid texels
        # in chunks of ~n / TRACE_CHUNKS texels: one thread sums a chunk, texels far apart in memory, so more,
        # shorter chunks keep the reduction off each iteration's critical path
        self.n_chunks = max(1, min(TRACE_CHUNKS, n))
        self.chunk = math.ceil(n / self.n_chunks)
        self.partial = wp.zeros((self.n_chunks, 8), dtype=wp.float64, device=dev)
        self.trace_buf = wp.zeros((cfg.max_iterations + 1, 8), dtype=wp.float64, device=dev)
        self.times: list[float] = []
        self.stamps: dict[int, float] = {}
        """per trace row, the wall-clock time (time.time) it was recorded"""
        if not isinstance(opt, LevenbergMarquardt):
            state.want_diag = bool(getattr(opt, "precondition", False))
        # the renderer's texture lookup holds the neighbours fixed between refreshes, so each texel's
        # objective stays its own (per-texel steps and acceptance) and changes only at a refresh
        self.refresh_every = cfg.lookup_refresh_every or (1 if isinstance(opt, LevenbergMarquardt) else 10)
        if self.refresh_every < 0:
            raise ConfigError(f"lookup_refresh_every {cfg.lookup_refresh_every} invalid", fix="use 0 (automatic) or k >= 1")
        if not 0.0 < cfg.lookup_relaxation <= 1.0:
            raise ConfigError(f"lookup_relaxation {cfg.lookup_relaxation} invalid", fix="use a fraction in (0, 1]")
        problem.refresh_lookup(state.storage)
        self.loss = cfg.loss(lay)
        self.first = 1
        self.last_obj = None
        self.schedule_switched = False

    def record(self, row: int) -> None:
        """Sum the trace columns over texels into row ``row`` of the trace buffer and note the wall time."""
        state, dev = self.state, self.problem.device
        wp.launch(K.chunk_sums_kernel, dim=self.n_chunks, device=dev,
                  inputs=[state.f, state.g, state.stats, state.accepted, state.valid, self.problem.n, self.chunk],
                  outputs=[self.partial])
        wp.launch(K.final_sums_kernel, dim=8, device=dev, inputs=[self.partial, self.n_chunks, row],
                  outputs=[self.trace_buf])
        wp.synchronize_device(dev)
        self.times.append(time.perf_counter() - self.t_start)
        self.stamps[row] = time.time()  # comparable across processes (a tiled fit's tiles, fit/multi/tiles.py)

    def evaluate_current(self) -> None:
        """f, g (and LM's J^T J) at the current parameters, as each optimizer starts from them."""
        state = self.state
        if isinstance(self.opt, LevenbergMarquardt):
            self.opt.start(state)
        else:
            self.problem.evaluate(state.storage, state.f, state.g, state.stats, diag=state.diag_out())
            self.penalties.add(state, state.p, state.f, state.g)

    def needs_scale_pass(self) -> bool:
        """Whether the robust loss's scale comes from a pass at the starting point (:meth:`scale_pass_stats`)."""
        return self.resume is None and self.loss != "none" and self.cfg.robust_scale <= 0

    def scale_pass_stats(self) -> np.ndarray:
        """One pass at the starting point; returns its (N, 4) per-texel statistics, from which
        :func:`robust_scale_from_stats` reads the mean sampled photo value (before the loop: the
        iterations themselves never wait on the host)."""
        if self.problem.cfg.residual_space != "radiance":
            raise ConfigError("robust_scale auto is in photo values, for radiance-space residuals",
                              fix="set robust_scale (reflectance units) or stream.residual_space radiance")
        self.problem.set_robust_loss(self.loss, 1.0)  # provisional: the photo statistics do not depend on it
        self.evaluate_current()
        return self.state.stats.numpy()

    def begin(self, robust_scale: float | None = None, view_mean_sq: float | None = None) -> None:
        """Set the robust loss (``robust_scale``: the automatic scale, else the config's or the checkpoint's)
        and the view prior (``view_mean_sq``: the photos' mean squared exposure when this problem holds part
        of them), evaluate the starting point and record trace row 0 (or restore a checkpoint's trace)."""
        problem, cfg, state, resume = self.problem, self.cfg, self.state, self.resume
        if resume is not None:
            problem.set_robust_loss(self.loss, float(resume["robust_scale"]))
        elif robust_scale is not None:
            problem.set_robust_loss(self.loss, robust_scale)
        else:
            problem.set_robust_loss(self.loss, cfg.robust_scale)
        problem.set_view_prior(cfg.view_prior, view_mean_sq)
        self.evaluate_current()
        state.accepted.zero_()
        if resume is not None:
            self.first = int(resume["iteration"]) + 1
            self.opt.lam.assign(np.asarray(resume["lam"]))
            self.trace_buf.assign(np.concatenate([np.asarray(resume["trace"]),
                                                  np.zeros((cfg.max_iterations + 1 - self.first, 8))]).astype(np.float64))
            self.times.extend(float(t) for t in resume["times"])
            self.last_obj = None if not np.isfinite(resume["last_obj"]) else float(resume["last_obj"])
        else:
            self.record(0)

    def iterate(self, it: int) -> None:
        """Iteration ``it``: one optimizer step over all texels, then its trace row."""
        self.step(it)
        self.record(it)

    def refresh_totals(self) -> None:
        """Recompute the reported objective of LM's smoothness (each texel's half share of its pair terms)
        after neighbours held in ``state.p`` changed (a tile's halo, fit/multi/tiles.py); no-op otherwise."""
        if isinstance(self.opt, LevenbergMarquardt) and self.opt.smooth:
            self.opt._report_totals(self.state)

    def step(self, it: int) -> None:
        """Iteration ``it``'s optimizer step over all texels (no trace row: :meth:`record`)."""
        cfg, state, opt, problem = self.cfg, self.state, self.opt, self.problem
        state.iteration = it
        if cfg.diffuse_free_iterations >= 0 and not self.schedule_switched and it > cfg.diffuse_free_iterations:
            f2 = self.free.copy()
            f2[0:3] = False
            state.set_free(f2)
            opt.reset_memory(state)
            self.schedule_switched = True
        if problem.lookup and it > 1 and (it - 1) % self.refresh_every == 0:
            state.store_current()
            problem.refresh_lookup(state.storage, cfg.lookup_relaxation)
            self.evaluate_current()
            if not isinstance(opt, LevenbergMarquardt):  # LM keeps its damping: it has no memory of the old objective
                opt.reset_memory(state)
        wp.copy(state.p_old, state.p)
        wp.copy(state.g_old, state.g)
        if isinstance(opt, LevenbergMarquardt):
            opt.step(state)
        else:
            opt.direction(state)
            line_search(state, cfg.linesearch, self.penalties, first=(it == 1))
            opt.after_step(state)

    def checkpoint_state(self, it: int, last_obj: float) -> dict:
        """What ``resume`` takes to continue after iteration ``it``."""
        return {"iteration": it, "p": self.state.p.numpy(), "lam": self.opt.lam.numpy(),
                "trace": self.trace_buf.numpy()[:it + 1], "times": np.asarray(self.times),
                "last_obj": last_obj, "robust_scale": float(self.problem.robust_scale)}

    def result(self, trace: list[dict]) -> FitResult:
        """The fit's parameters and sample counts with ``trace``."""
        return FitResult(params=self.state.params_numpy(), samples=self.counts.numpy(), trace=trace,
                         layout=self.problem.layout, passes=self.problem.passes, robust_loss=self.loss,
                         robust_scale=self.problem.robust_scale)
