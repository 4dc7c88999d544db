"""What every peer shares: the data set, the per-texel sample arrays, held-out scoring, traces, memory.

Data: the synthetic ornament (capture/synthetic/scenes/ornament.json) rendered by texstream at ``scale``,
noise-free float photos ("clean") or 8-bit sRGB photos with Gaussian camera noise ("noisy8");
every 8th photo is held out (:func:`texstream.fit.stages.stage.split_holdout`), and of the rest
(the training photos) every 8th again is the validation split: no method fits it, and it alone
decides where each method stops (:func:`early_stop`). Scores: the PSNR of the pooled (mean over
views) MSE on foreground pixels and the worst view's PSNR, of the held-out and of the validation
views, from texstream's own renderer for the Lafortune peers
(:func:`texstream.fit.stages.stage.heldout_psnr`).

Stopping rule, the same for every method (:func:`early_stop`): the method's parameters are checked
on the validation views at its snapshots (iterations 0..20, then 5 per doubling); it stops at
the first check whose iteration count reaches ``max(2 k, k + 4)``, k the iteration of the best
validation PSNR so far (a check improves on the best only by more than 0.01 dB), or at its budget,
and hands back the parameters of iteration k. The held-out views score that model; they choose nothing.

Samples (the two-step approach's step 1, the seed's Table 4.1): every training photo resampled
once at every texel centre with texstream's own distribution step (``stream.observe``, bilinear
photo filter, its visibility, shadow, grazing-angle and saturation tests), kept as flat arrays
grouped by texel: photo value y (RGB), weight w = exposure E cos(theta_i) (RGB), local light and
view directions u, v. A texel's model predicts ``w * m(p; u, v)`` for y, exactly texstream's
radiance-space residual with ``StreamConfig.photo_sampling = "bilinear"``.
"""

from __future__ import annotations

import ctypes
import dataclasses
import math
import os
import resource
import threading
import time
from typing import Any

import numpy as np
import warp as wp

from texstream.fit.kernels import stream

HOLDOUT_EVERY = 8
VALIDATION_EVERY = 8
"""of the training photos (those not held out), every 8th is the validation split: seen by the stopping rule only"""
PATIENCE_FACTOR = 2.0
PATIENCE_MIN = 4
"""the rule stops at iteration max(PATIENCE_FACTOR k, k + PATIENCE_MIN), k the best validation check's"""
MIN_DELTA_DB = 0.01
"""a validation check improves on the best only by more than this (dB): ties and rounding do not restart patience"""
NOISE_SIGMA = 0.01
"""camera noise of the noisy data set, linear units (1% of the white photo level: a few 8-bit codes)"""
DATASETS = ("clean", "noisy8")


# ------------------------------------------------------------------------------------------ data


@dataclasses.dataclass
class PeerData:
    """One data set: the rendered scene split into fitted and held-out views."""

    scene: Any
    """the :class:`texstream.capture.synthetic.synth.RenderedScene` (mesh, bake, ground truth)"""
    train_frames: list
    train_images: list
    train_masks: list
    held_frames: list
    held_images: list
    held_masks: list
    val_frames: list
    val_images: list
    val_masks: list
    dataset: str
    scale: float


def synth_config(dataset: str, scale: float, photos: int = 0, device: str = "cpu"):
    """The SynthConfig of a data set (``load_data`` renders it in memory, the default-fit peer writes it)."""
    from texstream.capture.synthetic.synth import SynthConfig

    if dataset not in DATASETS:
        raise ValueError(f"dataset {dataset!r}: use one of {DATASETS}")
    cfg = SynthConfig(scale=scale, device=device, progress=False, preview=False, photos=photos)
    if dataset == "noisy8":
        cfg.noise, cfg.bits = NOISE_SIGMA, 8
    return cfg


def split_every(n: int, every: int) -> np.ndarray:
    """The held-back mask of ``n`` items: every ``every``-th (texstream.fit.stages.stage.split_holdout's rule)."""
    return np.arange(n) % every == every - 1


def load_data(dataset: str, scale: float, photos: int = 0, device: str = "cpu") -> PeerData:
    """Render the ornament at ``scale`` with ``photos`` photos (0: the scene's count x scale), clean
    float photos or 8-bit with ``NOISE_SIGMA`` noise; split off every ``HOLDOUT_EVERY``-th photo (held
    out), then every ``VALIDATION_EVERY``-th of the rest (validation); the others are fitted."""
    from texstream.capture.synthetic.synth import render_scene

    sc = render_scene("ornament", synth_config(dataset, scale, photos, device))
    held = split_every(len(sc.frames), HOLDOUT_EVERY)
    val = np.zeros_like(held)
    val[~held] = split_every(int((~held).sum()), VALIDATION_EVERY)
    fit = ~held & ~val
    pick = lambda xs, m: [x for x, k in zip(xs, m) if k]  # noqa: E731
    return PeerData(sc, pick(sc.frames, fit), pick(sc.images, fit), pick(sc.masks, fit),
                    pick(sc.frames, held), pick(sc.images, held), pick(sc.masks, held),
                    pick(sc.frames, val), pick(sc.images, val), pick(sc.masks, val), dataset, scale)


def shadow_map_size(data: PeerData) -> int:
    """Shadow map side for the data: twice the photos' side, 128 to 512 (texstream's default 512 is sized
    for the full ornament's 430x430 photos; on 61x61 photos it made building the photo set, on one core,
    the largest part of every method's process time)."""
    side = max(max(im.shape[:2]) for im in data.train_images)
    return int(min(512, max(128, 2 * side)))


def fit_config(data: PeerData, photo_sampling: str = "filtered", **kw):
    """texstream's default FitConfig (LM) with the given photo sampling and the data's shadow map size
    (:func:`shadow_map_size`); what every Lafortune peer shares of it: the model layout (lobes, lobe
    shape), bounds, initial guess and the distribution step's options."""
    from texstream.fit.optim.fitter import FitConfig
    from texstream.fit.stream.config import StreamConfig

    return FitConfig(stream=StreamConfig(photo_sampling=photo_sampling, shadow_map_size=shadow_map_size(data)), **kw)


def build_problem(data: PeerData, cfg, device: str):
    from texstream.fit.stages.stage import build_problem as build

    sc = data.scene
    return build(sc.mesh, sc.bake, data.train_frames, data.train_images, data.train_masks, cfg, device)


# --------------------------------------------------------------------------------------- samples


@wp.kernel(enable_backward=False)
def count_samples_kernel(tex: stream.TexelFrames, images: wp.array3d(dtype=wp.vec3),
                         depth: wp.array3d(dtype=wp.float32), shadow: wp.array3d(dtype=wp.float32),
                         infos: wp.array(dtype=stream.ImageInfo), n_photos: int, opt: stream.SampleOptions,
                         count: wp.array(dtype=wp.int32)):
    """Per texel, the number of photos whose distribution step accepts it."""
    i = wp.tid()
    n = int(0)
    for k in range(n_photos):
        ok, y, w, u, v, xs, ys = stream.observe(images, depth, shadow, infos, k, tex, i, opt)
        if ok:
            n = n + 1
    count[i] = n


@wp.kernel(enable_backward=False)
def write_samples_kernel(tex: stream.TexelFrames, images: wp.array3d(dtype=wp.vec3),
                         depth: wp.array3d(dtype=wp.float32), shadow: wp.array3d(dtype=wp.float32),
                         infos: wp.array(dtype=stream.ImageInfo), n_photos: int, opt: stream.SampleOptions,
                         offset: wp.array(dtype=wp.int32), y_out: wp.array(dtype=wp.vec3),
                         w_out: wp.array(dtype=wp.vec3), u_out: wp.array(dtype=wp.vec3),
                         v_out: wp.array(dtype=wp.vec3)):
    """Each accepted (texel, photo) sample at the texel's slot range ``offset[i]..``, photos in order."""
    i = wp.tid()
    s = offset[i]
    for k in range(n_photos):
        ok, y, w, u, v, xs, ys = stream.observe(images, depth, shadow, infos, k, tex, i, opt)
        if ok:
            y_out[s] = y
            w_out[s] = w
            u_out[s] = u
            v_out[s] = v
            s = s + 1


@dataclasses.dataclass
class Samples:
    """Per-texel sample arrays (texel-major: texel i owns rows ``start[i]:start[i + 1]``)."""

    texel: np.ndarray
    """(S,) int64 compact texel index of each sample"""
    start: np.ndarray
    """(N + 1,) int64 row offsets"""
    y: np.ndarray
    """(S, 3) float32 photo value (bilinear at the texel centre's projection)"""
    w: np.ndarray
    """(S, 3) float32 exposure * irradiance * cos(theta_i)"""
    u: np.ndarray
    """(S, 3) float32 unit light direction in the texel's tangent frame (x tangent, z normal)"""
    v: np.ndarray
    """(S, 3) float32 unit view direction, same frame"""
    n_texels: int

    @property
    def counts(self) -> np.ndarray:
        return np.diff(self.start)


def resample(problem) -> Samples:
    """Step 1 of the two-step approach: every photo resampled once into per-texel sample arrays
    (texstream's distribution step, the problem's own photos, depth and shadow maps and options;
    build the problem with ``photo_sampling="bilinear"``)."""
    if problem.photos.streamed:
        raise ValueError("resample needs every photo resident (photos_per_window 0)")
    dev, n = problem.device, problem.n
    ph = problem.photos
    if ph.images.dtype != wp.vec3:
        raise ValueError("resample needs fp32 photos (image_precision fp32)")
    count = wp.zeros(n, dtype=wp.int32, device=dev)
    args = [problem.tex, ph.images, ph.depth, ph.shadow, ph.infos, ph.n, problem.opt]
    wp.launch(count_samples_kernel, dim=n, device=dev, inputs=args, outputs=[count])
    cnt = count.numpy().astype(np.int64)
    start = np.concatenate([[0], np.cumsum(cnt)])
    total = int(start[-1])
    outs = [wp.zeros(max(total, 1), dtype=wp.vec3, device=dev) for _ in range(4)]
    wp.launch(write_samples_kernel, dim=n, device=dev,
              inputs=[*args, wp.array(start[:-1].astype(np.int32), dtype=wp.int32, device=dev)], outputs=outs)
    y, w, u, v = (o.numpy()[:total] for o in outs)
    return Samples(np.repeat(np.arange(n), cnt), start, y, w, u, v, n)


# ---------------------------------------------------------------------------------- Lafortune model


def free_columns(layout) -> np.ndarray:
    """Indices of the layout's fitted (non-frozen) columns."""
    return np.flatnonzero(~layout.frozen())


def check_supported(layout) -> None:
    """The peers' numpy / torch models cover texstream's isotropic Lafortune with at most 2 lobes."""
    if layout.kind != "lafortune" or layout.anisotropic:
        raise ValueError(f"the peers implement the isotropic Lafortune model, not {layout}")


def lafortune_numpy(p: np.ndarray, layout, u: np.ndarray, v: np.ndarray, jac: bool = False):
    """texstream's isotropic Lafortune BRDF (fit/kernels/lafortune_grad.py) per sample, float64.

    Args:
        p: (S, P) parameters of each sample's texel (layout columns).
        u, v: (S, 3) local light / view directions.
        jac: also return dm/dp.

    Returns:
        m (S, 3) and, with ``jac``, J (S, 3, P) (zero in frozen columns is left to the caller).
    """
    wx, wz = u[:, 0] * v[:, 0] + u[:, 1] * v[:, 1], u[:, 2] * v[:, 2]
    m = p[:, 0:3].copy()
    J = None
    if jac:
        J = np.zeros((p.shape[0], 3, p.shape[1]))
        for c in range(3):
            J[:, c, c] = 1.0
    for j in range(layout.n_lobes):
        o = layout.lobe_offset(j)
        s = p[:, o + 3] * wx + p[:, o + 4] * wz
        n = p[:, o + 5]
        pos = s > 0
        ls = np.log(np.where(pos, s, 1.0))
        nls = n * ls
        capped = nls > 30.0  # texstream caps the lobe at e^30 with a flat (zero-derivative) top
        lobe = np.where(pos, np.exp(np.minimum(nls, 30.0)), 0.0)
        m += p[:, o:o + 3] * lobe[:, None]
        if jac:
            dlds = np.where(pos & ~capped, n * lobe / np.where(pos, s, 1.0), 0.0)
            dldn = np.where(pos & ~capped, lobe * ls, 0.0)
            for c in range(3):
                J[:, c, o + c] = lobe
                J[:, c, o + 3] = p[:, o + c] * dlds * wx
                J[:, c, o + 4] = p[:, o + c] * dlds * wz
                J[:, c, o + 5] = p[:, o + c] * dldn
    return (m, J) if jac else m


def projected_model(x: np.ndarray, layout, u: np.ndarray, v: np.ndarray, lobe_albedo_max: float, jac: bool = False):
    """The model at the projection of ``x`` (box bounds, then the energy bound) and, with ``jac``,
    the Jacobian with respect to ``x`` through that projection (zero along clipped or capped
    coordinates; a capped rho_s follows n): the feasible model for optimizers without constraints.
    ``x`` (S, P) per sample, as :func:`lafortune_numpy`."""
    lo, hi = layout.lower(), layout.upper()
    pc = np.clip(x, lo, hi)
    inside = (x >= lo) & (x <= hi)
    pe = pc.copy()
    capped = []
    for j in range(layout.n_lobes):
        o = layout.lobe_offset(j)
        cap = lobe_albedo_max * (pc[:, o + 5] + 2.0) / (2.0 * np.pi)
        cj = (pc[:, o:o + 3] > cap[:, None]) if lobe_albedo_max > 0 else np.zeros((x.shape[0], 3), bool)
        pe[:, o:o + 3] = np.where(cj, cap[:, None], pc[:, o:o + 3])
        capped.append(cj)
    if not jac:
        return lafortune_numpy(pe, layout, u, v)
    m, J = lafortune_numpy(pe, layout, u, v, jac=True)
    for j in range(layout.n_lobes):
        o = layout.lobe_offset(j)
        for c in range(3):
            cj = capped[j][:, c]
            # rho_s,c = cap(n): its column moves n instead (d cap / dn = albedo_max / 2 pi)
            J[:, :, o + 5] += np.where(cj, lobe_albedo_max / (2.0 * np.pi), 0.0)[:, None] * J[:, :, o + c]
            J[:, :, o + c] *= ~cj[:, None]
    J *= inside[:, None, :]
    return m, J


def project(p: np.ndarray, layout, lobe_albedo_max: float) -> np.ndarray:
    """Box bounds of the layout, then texstream's energy bound (models.energy_bound_numpy)."""
    from texstream.render.layout import energy_bound_numpy

    return energy_bound_numpy(np.clip(p, layout.lower(), layout.upper()), layout, lobe_albedo_max)


# --------------------------------------------------------------------------------- held-out score


class HeldOut:
    """Scoring of per-texel Lafortune parameters with texstream's renderer, on the held-out views and on the
    validation views (the one renderer, its BVH built once, reused for every snapshot)."""

    def __init__(self, data: PeerData, problem, layout, device: str = "cpu"):
        from texstream.fit.common.setup import ModelRenders

        self.data, self.layout, self.device = data, layout, device
        self.grid_index = problem.texels.grid_index
        self.bake = data.scene.bake
        self.renders = ModelRenders(data.scene.mesh, layout, device)
        self.val_seconds: list[float] = []

    def grid(self, params: np.ndarray) -> np.ndarray:
        lay, bake = self.layout, self.bake
        g = np.tile(lay.defaults().astype(np.float32), (bake.height * bake.width, 1))
        g[self.grid_index] = params
        return bake.fill_padding(g.reshape(bake.height, bake.width, -1))

    def score(self, params: np.ndarray) -> dict:
        """Pooled and worst-view PSNR (dB) on the held-out and on the validation views (a trace row's fields);
        the validation scoring's wall time is kept in ``val_seconds`` (what a check costs the rule)."""
        from texstream.fit.stages.stage import heldout_psnr

        d = self.data
        grid = self.grid(params)
        t0 = time.perf_counter()
        val_views, val_pooled = heldout_psnr(d.scene.mesh, grid, self.layout, d.val_frames, d.val_images,
                                             d.val_masks, self.device, self.renders)
        self.val_seconds.append(time.perf_counter() - t0)
        views, pooled = heldout_psnr(d.scene.mesh, grid, self.layout, d.held_frames, d.held_images, d.held_masks,
                                     self.device, self.renders)
        return {"heldout_psnr_db": float(pooled), "worst_psnr_db": float(min(views)),
                "val_psnr_db": float(val_pooled), "val_worst_psnr_db": float(min(val_views))}

    def check_seconds(self) -> float | None:
        """Median wall time of one validation check (rendering and scoring the validation views)."""
        return float(np.median(self.val_seconds)) if self.val_seconds else None


# ------------------------------------------------------------------------------------- recording


def cpu_seconds() -> float:
    """CPU time of this process and its waited-for children, user and system (every method runs one thread:
    on a shared box this is the time an idle core would take, whatever the other jobs' load)."""
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


class Recorder:
    """Snapshots of the parameters against wall time and CPU time, the snapshotting itself left out of both.

    ``start()`` once the method's set-up is done; ``snap(params)`` copies what to score later (host
    copy timed and subtracted); :meth:`trace` scores every snapshot afterwards."""

    def __init__(self, sync=None):
        self.sync = sync or (lambda: None)
        self.t0 = self.c0 = None
        self.paused = self.paused_cpu = 0.0
        self.snaps: list[tuple[float, int, Any, dict]] = []

    def start(self) -> None:
        self.sync()
        self.t0, self.c0 = time.perf_counter(), cpu_seconds()
        self.paused = self.paused_cpu = 0.0

    def elapsed(self) -> float:
        return time.perf_counter() - self.t0 - self.paused

    def snap(self, iteration: int, params, **extra) -> None:
        self.sync()
        t, c = self.elapsed(), cpu_seconds() - self.c0 - self.paused_cpu
        t1, c1 = time.perf_counter(), cpu_seconds()
        self.snaps.append((t, iteration, np.array(params, dtype=np.float64, copy=True), {"cpu_s": c, **extra}))
        self.paused += time.perf_counter() - t1
        self.paused_cpu += cpu_seconds() - c1

    def trace(self, scorer, train_psnr=None) -> list[dict]:
        """Every snapshot scored: the held-out and validation PSNRs (``scorer(params)``, :meth:`HeldOut.score`)
        and, given ``train_psnr(params)``, the PSNR of the fitted samples."""
        out = []
        for t, it, p, extra in self.snaps:
            row = {"time_s": t, "iteration": it, **scorer(p), **extra}
            if train_psnr is not None:
                row["train_psnr_db"] = train_psnr(p)
            out.append(row)
        return out


def sample_psnr(samples: Samples, layout, lobe_albedo_max: float, max_samples: int = 200_000):
    """``psnr(params)``: PSNR (peak 1) of the radiance-space residuals of the fitted samples (a fixed random
    subset of ``max_samples`` when there are more: the GPU study has ~10^7, scored at every snapshot)."""
    pick = np.arange(samples.y.shape[0])
    if pick.size > max_samples:
        pick = np.sort(np.random.default_rng(0).choice(pick, max_samples, replace=False))
    u, v = samples.u[pick].astype(np.float64), samples.v[pick].astype(np.float64)
    w, y, texel = samples.w[pick], samples.y[pick], samples.texel[pick]

    def psnr(params: np.ndarray) -> float:
        m = projected_model(params[texel], layout, u, v, lobe_albedo_max)
        mse = float(np.mean((w * m - y) ** 2))
        return 10 * math.log10(1.0 / mse) if mse > 0 else float("inf")

    return psnr


def schedule(max_iterations: int, dense: int = 20, per_doubling: int = 5) -> set[int]:
    """Iterations to check (snapshot): every one up to ``dense``, then ``per_doubling`` per doubling
    (bounded scoring cost; the methods whose every check is a run of its own check more sparsely)."""
    its = set(range(0, min(max_iterations, dense) + 1))
    x = float(dense)
    while x < max_iterations:
        x *= 2 ** (1.0 / per_doubling)
        its.add(min(int(round(x)), max_iterations))
    its.add(max_iterations)
    return its


def early_stop(trace: list[dict], key: str = "val_psnr_db") -> dict:
    """The stopping rule every method gets (module doc), on the trace's validation PSNR only.

    Walks the checks in order keeping k, the iteration of the best validation PSNR so far (improved on only
    by more than ``MIN_DELTA_DB``); stops at the first check at iteration >= max(PATIENCE_FACTOR k,
    k + PATIENCE_MIN), else at the last check (the budget). Returns the indices into ``trace`` of the check
    handed back (``best``) and of the one where the method stopped (``stop``), and ``by`` ("patience" or
    "budget")."""
    best = None
    for i, r in enumerate(trace):
        v = r.get(key)
        if v is not None and math.isfinite(v) and (best is None or v > trace[best][key] + MIN_DELTA_DB):
            best = i
        if best is None:
            continue
        k = trace[best]["iteration"]
        if r["iteration"] >= max(PATIENCE_FACTOR * k, k + PATIENCE_MIN):
            return {"best": best, "stop": i, "by": "patience"}
    return {"best": best, "stop": len(trace) - 1, "by": "budget"}


def summarise_trace(trace: list[dict]) -> dict:
    """The method as the rule hands it back (:func:`early_stop`): its held-out and validation scores at the
    check handed back, the wall and CPU time to the stop (the patience run included) and to that check, and for
    reference the best held-out PSNR anywhere on the trace (what choosing on the test views would give)."""
    rule = early_stop(trace)
    if rule["best"] is None:
        return {"heldout_psnr_at_stop_db": None, "time_to_stop_s": None}
    b, st = trace[rule["best"]], trace[rule["stop"]]
    ok = [r for r in trace if math.isfinite(r["heldout_psnr_db"])]
    return {"stopped_by": rule["by"], "iteration_handed_back": b["iteration"], "iteration_stopped": st["iteration"],
            "time_to_stop_s": st["time_s"], "time_to_handed_back_s": b["time_s"],
            "cpu_to_stop_s": st.get("cpu_s"), "cpu_to_handed_back_s": b.get("cpu_s"),
            "heldout_psnr_at_stop_db": b["heldout_psnr_db"], "worst_view_at_stop_db": b["worst_psnr_db"],
            "val_psnr_at_stop_db": b["val_psnr_db"], "val_worst_at_stop_db": b.get("val_worst_psnr_db"),
            "oracle_best_heldout_psnr_db": max(r["heldout_psnr_db"] for r in ok) if ok else None,
            "final_heldout_psnr_db": trace[-1]["heldout_psnr_db"], "checks_to_stop": rule["stop"] + 1}


# ---------------------------------------------------------------------------------------- memory


def host_rss_mb() -> float:
    """Current resident set size (MB) of this process."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def peak_host_mb() -> float:
    """Peak resident set size (MB) of this process so far."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


class DeviceMemoryPoller:
    """Peak GPU memory in use (MB, NVML, the whole device) above the level at start, sampled every 20 ms.

    Library-neutral (Warp, PyTorch and Dr.Jit allocate through their own pools); the GPU machine
    runs one method per process, so the difference is the method's own use, CUDA context included.
    """

    def __init__(self, device: str):
        self.ok = False
        self.peak = 0
        if not device.startswith("cuda"):
            return
        try:
            self.nvml = ctypes.CDLL("libnvidia-ml.so.1")
            self.nvml.nvmlInit_v2()
            self.handle = ctypes.c_void_p()
            index = int(device.split(":")[1]) if ":" in device else 0
            self.nvml.nvmlDeviceGetHandleByIndex_v2(index, ctypes.byref(self.handle))
            self.base = self._used()
            self.ok = True
        except (OSError, AttributeError):  # no NVML (driver library or symbol): no device figure
            return
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _used(self) -> int:
        class Memory(ctypes.Structure):
            _fields_ = [("total", ctypes.c_ulonglong), ("free", ctypes.c_ulonglong), ("used", ctypes.c_ulonglong)]

        m = Memory()
        self.nvml.nvmlDeviceGetMemoryInfo(self.handle, ctypes.byref(m))
        return int(m.used)

    def _run(self) -> None:
        while not self.stop.is_set():
            self.peak = max(self.peak, self._used() - self.base)
            time.sleep(0.02)

    def result_mb(self) -> float | None:
        if not self.ok:
            return None
        self.stop.set()
        self.thread.join()
        self.peak = max(self.peak, self._used() - self.base)
        return self.peak / 2 ** 20


def machine() -> str:
    import platform

    return f"{platform.node()} ({os.cpu_count()} CPUs)"
