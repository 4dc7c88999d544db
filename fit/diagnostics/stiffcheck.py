"""The stiff and extreme fitting suite (``texstream stiffcheck``): synthetic captures with ground truth at
the edges of what the fit must survive, each fitted in the precision the fit would use and again in
float64 (the reference), reporting convergence, the reduced precision's shortfall against the reference,
non-finite and out-of-bounds values, and the safeguard that handles the case.

A case is a built-in scene edited towards one extreme (an exponent of 10,000, lights at grazing
incidence, radiance over seven decades, two photos, ...). Both fits start from the same initial guess,
run the same optimizer with the same caps, and are scored on the samples they fitted (the trace's PSNR
against the capture's own peak); the check is that the reduced precision fits the photos as well as
float64, within the case's tolerance, with no NaN or Inf anywhere (parameters, trace, renders).

``size`` "ci" keeps every case to seconds on one CPU core (the test suite runs it); "full" is the
documented run (docs/numerics.md). Imports only numpy and warp at import time.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import time
from typing import Callable

import numpy as np

from texstream.capture.synthetic.synth import SynthConfig, load_scene, render_scene
from texstream.core.config import option
from texstream.core.errors import ConfigError, InputError
from texstream.core.outputs import write_atomic_with, write_json_atomic
from texstream.fit.common.numerics import FP16_MAX, FP16_MIN_NORMAL, numerics_warnings  # noqa: F401
from texstream.fit.kernels.summation import streamed_sums
from texstream.fit.models.lfm.baselines import fit_pca
from texstream.fit.models.lfm.model_folder import lfm_geometry
from texstream.fit.models.lfm.problem import LFMConfig, LFMProblem, PhotoSamples, fit_lfm
from texstream.fit.optim.fitter import FitConfig, initial_guess, run_fit
from texstream.fit.stages.stage import build_problem, fit_synthetic, params_to_grid, render_model
from texstream.fit.stream.config import FP32_SAFE_PHOTOS, StreamConfig, resolve_accumulate

SIZES = ("ci", "full")


@dataclasses.dataclass
class StiffCase:
    """One case of the suite.

    Attributes:
        name: identifier (``--cases``).
        regime: what is extreme, in words.
        safeguard: what in texstream handles it (bounds, reparameterisation, sample rejection, ...).
        scene: built-in scene the case edits.
        edit: mutates the scene dict in place (materials, cameras, light, photo settings).
        synth: SynthConfig overrides per size ({"ci": {...}, "full": {...}}; "photos", "image_size", ...).
        fit: FitConfig field overrides for both fits (optimizer, lobe_shape, ...).
        stream: StreamConfig overrides of the fit under test (its precision); the reference is fp64.
        stream_both: StreamConfig overrides of both fits (e.g. sample rejection off).
        tolerance_db: the fit under test may fit the samples this much worse than the fp64 reference.
        kind: "fit" (Lafortune/radiance fit), "lfm" (light field mapping against its PCA) or
            "accumulation" (the streamed sum of a fit's residual terms at a million photos).
    """

    name: str
    regime: str
    safeguard: str
    scene: str = "sphere"
    edit: Callable[[dict], None] | None = None
    synth: dict = dataclasses.field(default_factory=dict)
    fit: dict = dataclasses.field(default_factory=dict)
    stream: dict = dataclasses.field(default_factory=dict)
    stream_both: dict = dataclasses.field(default_factory=dict)
    tolerance_db: float = 0.1
    kind: str = "fit"


# ----------------------------------------------------------------------------------------- scene edits


def _exponent(n: float) -> Callable[[dict], None]:
    def edit(sc: dict) -> None:
        m = sc["materials"]["plastic"]
        m["lobes"][0]["n"] = float(n)
        m["gradient"]["n_amount"] = 0.0
        # a normalised lobe: the same energy at every n, so the highlight's peak grows with n
        m["lobes"][0]["rho_s"] = [0.6 * (n + 2) / 32.0] * 3
    return edit


def _narrow_highlight(sc: dict) -> None:
    # a 16x16 atlas over a 2x2 sample: texels 0.125 wide; the n = 5,000 highlight's half-width on the
    # plane is ~0.03 at the cameras' distance, a quarter of a texel
    sc["texture"].update(width=16, height=16)
    sc["materials"]["gold"]["lobes"][0].update(n=5000.0, rho_s=[60.0, 45.0, 19.0])
    sc["materials"]["gold"]["gradient"]["n_amount"] = 0.0


def _grazing_light(sc: dict) -> None:
    # the orbiting light 0.03 above the plane at radius 2.5: 0.5-1.1 degrees over the sample
    sc["light"].update(height=0.03, intensity=400.0)


def _grazing_view(sc: dict) -> None:
    sc["cameras"].update(min_elevation_deg=0.2, max_elevation_deg=1.0)


def _hdr(sc: dict) -> None:
    # paint nearly black (1e-5 / sr), gold a sharp bright lobe: photo values from ~1e-3 to ~1e4
    sc["materials"]["paint"].update(rho_d=[1.0e-5, 2.0e-5, 4.0e-5])
    sc["materials"]["paint"]["lobes"][0].update(rho_s=[1.0e-4] * 3)
    sc["materials"]["gold"]["lobes"][0].update(n=400.0, rho_s=[40.0, 30.0, 12.0])
    sc["light"]["intensity"] = 3000.0


def _clipped(sc: dict) -> None:
    sc["photo"].update(bits=8, exposure=4.0)  # 8-bit sRGB: highlights and the brightest diffuse clip at 1


def _noise_floor(sc: dict) -> None:
    m = sc["materials"]["plastic"]
    m["rho_d"] = [0.0018, 0.0005, 0.0004]  # 1% of the sphere's: ~0.003 photo value, the noise's level
    m["lobes"][0]["rho_s"] = [0.006] * 3
    sc["photo"]["noise_sigma"] = 0.003


def _few_photos(sc: dict) -> None:
    # three cameras 120 degrees apart on the equator: texels seen by none (the caps), one or two of them
    sc["cameras"].update(layout="ring", rings=[0.0])


def _light_at_camera(sc: dict) -> None:
    sc["light"]["offset"] = [0.02, 0.0, 0.0]  # one half-angle for every highlight: rho_s and c_z trade off
    sc["light"]["spin_turns"] = 0.0


def _views_nearly_equal(sc: dict) -> None:
    sc["cameras"].update(min_elevation_deg=89.0, max_elevation_deg=90.0)  # every camera within 1 degree of the pole
    sc["light"] = {"type": "point", "mode": "fixed", "position": [1.5, -1.0, 3.0], "intensity": 12.0}


def default_cases() -> list[StiffCase]:
    """The suite's cases, in the issue's order."""
    fine = {"ci": {"photos": 24, "image_size": 48}, "full": {"photos": 120, "image_size": 128}}
    flat = {"ci": {"photos": 24, "image_size": 48}, "full": {"photos": 80, "image_size": 128}}
    cases = []
    for n in (1, 10, 100, 1000, 10000):
        cases.append(StiffCase(
            f"exponent_{n}", f"Lafortune exponent n = {n} in the truth (a normalised lobe: peak x{(n + 2) / 32:.3g})",
            "n bounded to [1, 1e4] by projection (>= 1 keeps the objective C1); LM's damping and per-texel "
            "acceptance; the lobe energy bound rho_s <= (n + 2) / 2 pi",
            edit=_exponent(n), synth=fine))
    cases += [
        StiffCase("narrow_highlight", "n = 5,000 on a 16x16 atlas: the highlight a quarter of a texel wide",
                  "filtered photo sampling (each tap averages the texel's footprint) and the n bound",
                  scene="flat_sample", edit=_narrow_highlight, synth=flat),
        StiffCase("grazing_light", "point light 0.5-1.1 degrees above the plane (sample rejection off)",
                  "by default sample rejection (stream.cos_light_min 0.1, 84 degrees) leaves such samples out; "
                  "with it off (this case) cos(theta_i) is clamped at 0 and the shadow epsilon is relative to "
                  "the scene", scene="flat_sample", edit=_grazing_light, synth=flat,
                  stream_both={"cos_light_min": 0.0}),
        StiffCase("grazing_view", "cameras 0.2-1 degree above the plane (sample rejection off)",
                  "sample rejection: with stream.cos_view_min off (this case) the visibility test still rejects "
                  "every tap (its depth slack stops at 76 degrees, so a sliver's taps that reach the background "
                  "fail): no samples, the texels keep their start and are flagged unseen",
                  scene="flat_sample", edit=_grazing_view, synth=flat, stream_both={"cos_view_min": 0.0}),
        StiffCase("hdr_range", "photo values from ~1e-3 to ~1e4 in one capture (float EXR)",
                  "fp32 sums of r^2 stay relative (no absolute epsilon); rho bounds [0, 1e5]",
                  scene="flat_sample", edit=_hdr, synth=flat, tolerance_db=0.5),
        StiffCase("clipped_8bit", "8-bit sRGB photos at 4x exposure: highlights clipped at 1",
                  "sample rejection at the saturation level (clipped samples carry no information)",
                  edit=_clipped, synth=fine),
        StiffCase("noise_floor", "diffuse signal ~0.003 with camera noise sigma 0.003",
                  "rho_d >= 0 by projection; least squares averages the noise over the texel's samples",
                  edit=_noise_floor, synth=fine),
        StiffCase("few_photos", "three photos: texels seen by 0, 1 or 2 of them",
                  "unseen texels keep their start and are flagged (samples == 0); LM damping where J^T J is "
                  "singular (one photo cannot separate diffuse from lobe)",
                  edit=_few_photos, synth={"ci": {"photos": 3, "image_size": 48}, "full": {"photos": 3, "image_size": 128}},
                  tolerance_db=0.5),
        StiffCase("scale_redundancy", "light beside the camera: rho_s and c_z trade off (one half-angle per highlight)",
                  "the scale gauge c_xy = -1 and c_z in [0, 1] (render/layout.py); lobe_shape auto holds c_z = 1 "
                  "here (this case forces free to exercise the redundancy); LM damping",
                  edit=_light_at_camera, synth=fine, fit={"lobe_shape": "free"}),
        StiffCase("fp16_storage", "parameters stored in float16 between passes (sums in fp32)",
                  "bounds clamp after rounding; fp16 rounds rho_s and n to 2^-11 relative (3 decimal digits)",
                  synth=fine, stream={"storage": "fp16"}, tolerance_db=0.5),
        StiffCase("lfm_views_nearly_equal", "light field mapping with every camera within 1 degree: rank-deficient view maps",
                  "the view-map Laplacian (unseen view texels follow their neighbours), per-patch acceptance and "
                  "gauge balancing; compared with PCA on the same maps (everything in float64)",
                  edit=_views_nearly_equal, synth={"ci": {"photos": 12, "image_size": 40}, "full": {"photos": 60, "image_size": 96}},
                  kind="lfm", tolerance_db=0.5),
        StiffCase("million_photos", "10^6 photos' worth of accumulation per texel",
                  "StreamConfig.accumulate auto: fp64 sums above 1,000 photos (fp32 for fewer), or --stream.kahan",
                  synth=fine, kind="accumulation"),
    ]
    return cases


# --------------------------------------------------------------------------------------------- running


def _render(case: StiffCase, size: str, device: str):
    scene = copy.deepcopy(load_scene(case.scene))
    if case.edit is not None:
        case.edit(scene)
    over = dict(case.synth.get(size, {}))
    scale = over.pop("scale", 0.1 if size == "ci" else 0.5)
    return render_scene(scene, SynthConfig(scale=scale, progress=False, preview=False, save_clean=True,
                                           device=device, **over))


def _nonfinite(*arrays) -> int:
    return int(sum(int(np.size(a) - np.isfinite(np.asarray(a, np.float64)).sum()) for a in arrays))


def _trace_nonfinite(trace: list[dict]) -> int:
    """NaN anywhere, Inf anywhere but the PSNR (infinite where the samples are fitted exactly)."""
    return sum(1 for row in trace for k, v in row.items() if isinstance(v, float)
               and (math.isnan(v) or (math.isinf(v) and k != "psnr_db")))


PSNR_CAP_DB = 100.0
"""fits closer than this to their samples count as exact when comparing precisions (float32's 24-bit
significand ends near 144 dB; the photos' own float32 rounding near 140)"""


def _photo_peak(images, masks) -> float:
    vals = [img[m] for img, m in zip(images, masks) if m.any()]
    return float(max(np.max(v) for v in vals)) if vals else 1.0


def _fit_record(res, t: float, prob) -> dict:
    last = res.trace[-1] if res.trace else {}
    first = res.trace[0] if res.trace else {}
    e0, e1 = first.get("objective", 0.0), last.get("objective", 0.0)
    window = res.trace[-6:-5] or res.trace[:1]
    return {"accumulate": prob.accumulate, "storage": prob.cfg.storage, "iterations": len(res.trace) - 1,
            "objective": e1, "objective_start": e0, "objective_ratio": e1 / e0 if e0 > 0 else 0.0,
            "last_5_rel_decrease": (window[0]["objective"] - e1) / window[0]["objective"] if window and window[0]["objective"] > 0 else 0.0,
            "sample_psnr_db": min(last.get("psnr_db", PSNR_CAP_DB), PSNR_CAP_DB), "time_s": t}


def _run_fit_case(case: StiffCase, size: str, device: str, iterations: int) -> dict:
    sc = _render(case, size, device)
    fitted = list(range(len(sc.frames)))
    frames = [sc.frames[i] for i in fitted]
    images = [sc.images[i] for i in fitted]
    masks = [sc.masks[i] for i in fitted]
    peak = _photo_peak(images, masks)
    out = {"photos": len(frames), "photo_peak": peak,
           "photo_min_foreground": float(min(np.min(img[m]) for img, m in zip(images, masks) if m.any()))}
    runs, grids, res_by = {}, {}, {}
    p0 = None
    for which in ("test", "reference"):
        stream = dict(shadow_map_size=128, **case.stream_both)
        stream.update(case.stream if which == "test" else {"accumulate": "fp64", "storage": "fp64"})
        cfg = FitConfig(max_iterations=iterations, sync_every=5, psnr_peak=peak, stream=StreamConfig(**stream), **case.fit)
        prob = build_problem(sc.mesh, sc.bake, frames, images, masks, cfg, device)
        if p0 is None:  # one start for both fits: the test precision's initial guess, in float64
            p0 = np.asarray(initial_guess(prob, cfg)[0], np.float64)
        t0 = time.perf_counter()
        res = run_fit(prob, cfg, p0=p0)
        runs[which] = _fit_record(res, time.perf_counter() - t0, prob)
        res_by[which] = (res, prob)
        grids[which] = params_to_grid(res, prob, sc.bake)
    res, prob = res_by["test"]
    lay = res.layout
    seen = res.seen
    lo, hi = lay.lower(), lay.upper()
    # fp16 storage rounds a bound itself by up to 2^-11 relative
    slack = 1e-3 * np.maximum(np.abs(lo), np.abs(hi)) if prob.cfg.storage == "fp16" else 0.0
    out_of_bounds = int(((res.params < lo - slack) | (res.params > hi + slack)).any(axis=1).sum())
    render_nonfinite, render_peak, truth_views = 0, 0.0, []
    truth_peak = max(float(np.max(sc.clean[i][sc.masks[i]])) for i in fitted if sc.masks[i].any())
    # noise-free truth on three fitted views: how well the fit recovered what its photos saw (held-out
    # views measure generalisation, issue 17's subject, not the arithmetic's)
    show = fitted[:: max(1, len(fitted) // 3)][:3]
    for i in show:
        r, m = render_model(sc.mesh, grids["test"], lay, sc.frames[i], device)
        render_nonfinite += _nonfinite(r)
        render_peak = max(render_peak, float(np.max(r)) if r.size else 0.0)
        mm = m.astype(bool) & sc.masks[i]
        if mm.any():
            d = (r[mm] - sc.clean[i][mm]).astype(np.float64)
            truth_views.append((float(np.mean(d * d)), int(mm.sum())))
    mse = sum(a * b for a, b in truth_views) / max(sum(b for _, b in truth_views), 1)
    ref_p, test_p = res_by["reference"][0].params, res.params
    both = seen & res_by["reference"][0].seen
    rel = np.abs(test_p[both] - ref_p[both]) / np.maximum(np.abs(ref_p[both]), 1e-6)
    out.update({
        "texels": int(prob.n), "texels_seen": int(seen.sum()), "test": runs["test"], "reference": runs["reference"],
        "shortfall_db": runs["reference"]["sample_psnr_db"] - runs["test"]["sample_psnr_db"],
        "objective_rel_diff": abs(runs["test"]["objective"] - runs["reference"]["objective"])
        / max(abs(runs["reference"]["objective"]), 1e-300),
        "param_rel_diff_median": float(np.median(rel)) if rel.size else 0.0,
        "nonfinite": _nonfinite(res.params) + _trace_nonfinite(res.trace) + render_nonfinite
        + _nonfinite(ref_p) + _trace_nonfinite(res_by["reference"][0].trace),
        "out_of_bounds_texels": out_of_bounds,
        "render_peak_over_photo_peak": render_peak / max(peak, 1e-30),
        "truth_psnr_db": 10 * math.log10(truth_peak ** 2 / mse) if mse > 0 else float("inf"),
    })
    if case.name == "few_photos":  # one sample per photo that sees a texel: counts 0, 1 and 2
        counts = np.asarray(res.samples)
        out["texels_unseen"] = int((~seen).sum())
        out["texels_by_photo_count"] = {int(k): int((counts == k).sum()) for k in np.unique(counts)}
    if case.name == "scale_redundancy":
        j = lay.lobe_offset(0)
        out["rho_s_spread"] = [float(np.percentile(res.params[seen, j + 1], q)) for q in (5, 50, 95)]
        out["c_z_spread"] = [float(np.percentile(res.params[seen, j + 4], q)) for q in (5, 50, 95)]
    return out


def _run_lfm_case(case: StiffCase, size: str, device: str, iterations: int) -> dict:
    sc = _render(case, size, device)
    cfg = FitConfig(model="radiance", stream=StreamConfig(shadow_map_size=128))
    sp = build_problem(sc.mesh, sc.bake, sc.frames, sc.images, sc.masks, cfg, device)
    geom = lfm_geometry(sc.mesh, sc.bake, sp.texels)
    lcfg = LFMConfig(terms=2, view_res=8 if size == "full" else 4)
    problem = LFMProblem(geom, PhotoSamples(sp, sc.frames), lcfg, device)
    t0 = time.perf_counter()
    res = fit_lfm(problem, max_iterations=iterations)
    t_stream = time.perf_counter() - t0
    err = problem.model_error(problem.new_G(res.params.G), problem.new_H(res.params.H))
    t0 = time.perf_counter()
    pca_params, _ = fit_pca(problem)
    t_pca = time.perf_counter() - t0
    pca = problem.model_error(problem.new_G(pca_params.G), problem.new_H(pca_params.H))
    peak = _photo_peak(sc.images, sc.masks)
    # model_error's PSNR is against a peak of 1; both are rescaled to the capture's peak alike
    shift = 20 * math.log10(peak)
    return {"photos": len(sc.frames), "photo_peak": peak, "texels": int(problem.N), "vertices": int(problem.V),
            "test": {"method": "stream CG (fp64)", "iterations": res.iterations, "sample_psnr_db": err["psnr_db"] + shift,
                     "time_s": t_stream},
            "reference": {"method": "PCA (fp64)", "sample_psnr_db": pca["psnr_db"] + shift, "time_s": t_pca},
            "shortfall_db": pca["psnr_db"] - err["psnr_db"],
            "nonfinite": _nonfinite(res.params.G, res.params.H, res.params.diffuse) + _trace_nonfinite(res.trace)
            + _nonfinite(pca_params.G, pca_params.H),
            "out_of_bounds_texels": 0}


def _run_accumulation_case(case: StiffCase, size: str, device: str, iterations: int) -> dict:
    """The residual terms r^2 / 2 of a converged fit (its renders against its photos, every channel),
    redrawn to 10^6 photos per texel and summed as a pass sums them."""
    sc = _render(case, size, device)
    cfg = FitConfig(max_iterations=iterations, stream=StreamConfig(shadow_map_size=128))
    fit = fit_synthetic(sc, sc, cfg, device)
    resid = []
    for fr, img, m in zip(sc.frames, sc.images, sc.masks):
        r, rm = render_model(sc.mesh, fit.grid, fit.result.layout, fr, device)
        mm = rm.astype(bool) & m
        resid.append((r[mm] - img[mm]).reshape(-1))
    resid = np.concatenate(resid).astype(np.float64)
    photos = 1_000_000 if size == "full" else 333_334
    rows = 4 if size == "full" else 2
    rng = np.random.default_rng(0)
    # one texel sees 3 channel terms per photo; the terms are r^2 / 2 of residuals drawn from the fit's own
    terms = (0.5 * rng.choice(resid, size=(rows, 3 * photos)) ** 2).astype(np.float32)
    exact = np.array([math.fsum(t.astype(np.float64)) for t in terms])
    sums = {name: np.abs(streamed_sums(terms, method, device) - exact) / np.abs(exact)
            for name, method in (("fp32", "fp32"), ("kahan", "fp32_kahan"), ("fp64", "fp64"))}
    chosen = resolve_accumulate("auto", photos)
    return {"photos": photos, "terms_per_texel": 3 * photos, "residual_rms": float(np.sqrt(np.mean(resid ** 2))),
            "fit_photos": len(sc.frames), "auto_choice": chosen, "fp32_safe_photos": FP32_SAFE_PHOTOS,
            "rel_error_E": {k: float(v.max()) for k, v in sums.items()},
            "rel_error_E_auto": float(sums[chosen].max()),
            "nonfinite": _nonfinite(*[v for v in sums.values()]), "out_of_bounds_texels": 0,
            "test": {"accumulate": chosen}, "reference": {"accumulate": "exact (math.fsum)"}}


def run_case(case: StiffCase, size: str = "ci", device: str = "cpu", iterations: int | None = None) -> dict:
    """Run one case; returns its record (``ok`` when it met every check)."""
    if size not in SIZES:
        raise ConfigError(f"suite size {size!r} unknown", fix="use ci or full")
    iters = iterations or (25 if size == "ci" else 60)
    t0 = time.perf_counter()
    run = {"fit": _run_fit_case, "lfm": _run_lfm_case, "accumulation": _run_accumulation_case}[case.kind]
    rec = run(case, size, device, iters)
    rec.update(name=case.name, regime=case.regime, safeguard=case.safeguard, kind=case.kind, size=size,
               device=device, tolerance_db=case.tolerance_db, wall_s=time.perf_counter() - t0)
    failures = []
    if rec["nonfinite"]:
        failures.append(f"{rec['nonfinite']} non-finite values")
    if rec.get("out_of_bounds_texels"):
        failures.append(f"{rec['out_of_bounds_texels']} texels out of bounds")
    if case.kind == "accumulation":
        if not rec["rel_error_E_auto"] < 1e-5:
            failures.append(f"relative error of E {rec['rel_error_E_auto']:.2g} >= 1e-5 with the automatic choice")
    elif not rec["shortfall_db"] <= case.tolerance_db:
        failures.append(f"fits the samples {rec['shortfall_db']:.3f} dB worse than the reference (tolerance "
                        f"{case.tolerance_db} dB)")
    if rec.get("render_peak_over_photo_peak", 0.0) > 100.0:
        failures.append(f"renders reach {rec['render_peak_over_photo_peak']:.3g}x the photos' peak")
    rec["failures"] = failures
    rec["ok"] = not failures
    return rec


def select_cases(names: list[str] | None) -> list[StiffCase]:
    cases = default_cases()
    if not names:
        return cases
    known = {c.name: c for c in cases}
    bad = [n for n in names if n not in known]
    if bad:
        raise ConfigError(f"unknown stiffcheck case(s) {', '.join(bad)}", fix=f"choose from {', '.join(known)}")
    return [known[n] for n in names]


def markdown_table(records: list[dict]) -> str:
    """The suite's summary table (docs/numerics.md layout)."""
    lines = ["| case | regime | test precision | texels seen | iterations (test / fp64) | E end / start | "
             "shortfall vs fp64 | tolerance | NaN/Inf | out of bounds | truth PSNR | safeguard |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in records:
        t, ref = r.get("test", {}), r.get("reference", {})
        if r["kind"] == "accumulation":
            prec = f"auto -> {r['auto_choice']}"
            its = "-"
            short = (f"rel. error of E {r['rel_error_E_auto']:.1e} (fp32 {r['rel_error_E']['fp32']:.1e}, "
                     f"Kahan {r['rel_error_E']['kahan']:.1e})")
            tol = "1e-5"
        else:
            prec = t.get("method") or f"{t.get('accumulate')} sums, {t.get('storage')} storage"
            its = f"{t.get('iterations', '-')} / {ref.get('iterations', '-')}"
            short = f"{r['shortfall_db']:+.3f} dB"
            tol = f"{r['tolerance_db']} dB"
        truth = f"{r['truth_psnr_db']:.1f} dB" if "truth_psnr_db" in r else "-"
        seen = f"{r['texels_seen']} / {r['texels']}" if "texels_seen" in r else str(r.get("texels", "-"))
        ratio = f"{t['objective_ratio']:.2g}" if "objective_ratio" in t else "-"
        lines.append(f"| {r['name']} | {r['regime']} | {prec} | {seen} | {its} | {ratio} | {short} | {tol} | {r['nonfinite']} | "
                     f"{r.get('out_of_bounds_texels', 0)} | {truth} | {r['safeguard']} |")
    return "\n".join(lines)


@dataclasses.dataclass
class StiffcheckConfig:
    """What ``texstream stiffcheck`` runs."""

    device: str = option("cpu", "Warp device of the fits (cpu, cuda:0, ...)")
    size: str = option("ci", "ci: small captures, seconds per case (the test suite's); full: the documented run",
                       choices=SIZES)
    cases: str = option("", "comma-separated case names (empty: all)")
    iterations: int = option(0, "iteration cap of every fit (0: 25 at ci size, 60 at full)", min=0)


def run_suite(cfg: StiffcheckConfig, log=None) -> dict:
    """Every selected case; ``log(record)`` after each."""
    names = [n.strip() for n in cfg.cases.split(",") if n.strip()]
    records = []
    for case in select_cases(names):
        rec = run_case(case, cfg.size, cfg.device, cfg.iterations or None)
        records.append(rec)
        if log is not None:
            log(rec)
    return {"config": dataclasses.asdict(cfg), "cases": records, "ok": all(r["ok"] for r in records)}


def write_report(result: dict, out_dir) -> tuple:
    """``stiffcheck.json`` and ``stiffcheck.md`` in ``out_dir``, each written atomically."""
    from pathlib import Path

    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InputError("output path exists and is not a folder", out, "choose another -o folder")
    write_json_atomic(out / "stiffcheck.json", result)
    text = markdown_table(result["cases"]) + "\n"
    write_atomic_with(out / "stiffcheck.md", lambda fh: fh.write(text.encode()))
    return out / "stiffcheck.json", out / "stiffcheck.md"


# ------------------------------------------------------------------------------- the fit's one-line warnings

"""below this a float16 photo value is subnormal: fewer than 11 significant bits"""


