"""Fit accuracy against ground truth on synthetic captures (issue 3's targets), CPU and CUDA.

The sphere scene is made dense in photos (480 views) and small in texels (800), so a fair share of
texels sees its highlight in five or more photos; held-out views sit between the training views
(cameras turned 7 degrees about the vertical axis). The small ornament (scale 0.01: 968 texels,
its full 1,760 photos at 160x160) has three materials, narrow lobes (n = 60, 200) and material edges.
Both use the default filtered photo sampling (fit/kernels/stream.py ``observe``).
"""

from __future__ import annotations

import numpy as np
import pytest

from texstream.capture.synthetic.synth import SynthConfig, render_scene
from texstream.fit.diagnostics.accuracy import highlight_counts, interior_texels, relative_errors
from texstream.fit.optim.fitter import FitConfig
from texstream.fit.stream.penalties import PenaltyConfig
from texstream.fit.stream.config import StreamConfig
from texstream.fit.stages.stage import build_problem, fit_synthetic

from conftest import SCENE_DEVICE

SPHERE = dict(scale=0.1, photos=480, image_size=96, progress=False, device=SCENE_DEVICE)


@pytest.fixture(scope="module")
def sphere():
    train = render_scene("sphere", SynthConfig(**SPHERE))
    held = render_scene("sphere", SynthConfig(**{**SPHERE, "photos": 8}, azimuth_offset=7.0))
    return train, held


def fit_and_score(train, held, cfg, device, photos=None):
    """LM fit of ``train``; (result, problem, pooled held-out PSNR, true params of the fitted texels,
    seen texels, relative errors, highlight texels: lobe seen at >= 10% of its peak in 5+ photos)."""
    fit = fit_synthetic(train, held, cfg, device, photos)
    res, prob, held_psnr = fit.result, fit.problem, fit.heldout_pooled_db
    gt = train.params.reshape(-1, train.params.shape[-1])[prob.texels.grid_index]
    seen = res.samples > 0
    o = res.layout.lobe_offset(0)
    # white texels have no lobe (rho_s = 0): no relative error to speak of
    hi = seen & (highlight_counts(train.frames, prob.texels.position, prob.texels.normal, gt, o) >= 5) \
        & (gt[:, o:o + 3].max(axis=1) > 0)
    return res, prob, held_psnr, gt, seen, relative_errors(res.params, gt), hi


def test_sphere_fit_meets_the_accuracy_targets(sphere, device):
    train, held = sphere
    cfg = FitConfig(optimizer="lm", max_iterations=200, sync_every=1000,
                    penalties=PenaltyConfig(smooth_weight=1e-3, smooth_params="shape"))
    res, prob, held_psnr, gt, seen, rel, hi = fit_and_score(train, held, cfg, device)
    # issue target 45 dB on noise-free float photos (measured 77.5 dB on the CPU, commit c438de4)
    assert held_psnr >= 45.0, held_psnr
    # diffuse albedo: target 1% (measured median 0.08%, p90 0.17%)
    assert np.percentile(rel[seen, 0:3], 90) < 0.01
    assert hi.sum() >= 50  # 120 of 800 texels here
    o = res.layout.lobe_offset(0)
    # specular albedo 3% and exponent 5% (issue targets): medians measured 0.03% and 0.04%
    assert np.median(rel[hi, o:o + 3]) < 0.03
    assert np.median(rel[hi, o + 5]) < 0.05
    # per texel, the bounds on every highlight texel: the light rides beside the camera, so
    # lobe_shape "auto" holds c_z at 1 (fit/models.py "Lobe shape"; with c_z free 8% of these texels
    # missed 3%, p90 2.9%). Measured on the CPU: worst texels diffuse 0.27%, rho_s 0.24%, n 0.18%
    assert res.layout.lobe_shape == "phong"
    worst = rel[hi, 0:3].max(), rel[hi, o:o + 3].max(), rel[hi, o + 5].max()
    assert worst[0] <= 0.01 and worst[1] <= 0.03 and worst[2] <= 0.05, worst
    assert np.all(np.isfinite(res.params))


ORNAMENT = dict(scale=0.01, photos=1760, image_size=160, progress=False, device=SCENE_DEVICE)


@pytest.fixture(scope="module")
def ornament():
    # the full 1,760 photos: with 880 the held-out views fall to 38 dB and only 81 texels see their
    # highlight 5 times (the lobes are narrow); rendering takes ~25 s on the 2-core CPU
    train = render_scene("ornament", SynthConfig(**ORNAMENT))
    held = render_scene("ornament", SynthConfig(**{**ORNAMENT, "photos": 8}, azimuth_offset=3.0))
    return train, held


@pytest.fixture(scope="module")
def ornament_photos(ornament):
    """The training photos on each device with their depth and shadow maps, built once per device
    and shared by the ornament tests (building it is most of their set-up: 1,760 shadow maps of
    512x512 against 1,760 depth maps of 160x160 by ray count)."""
    built = {}

    def on(device):
        if device not in built:
            train = ornament[0]
            built[device] = build_problem(train.mesh, train.bake, train.frames, train.images, train.masks,
                                          FitConfig(), device).photos
        return built[device]
    return on


def test_small_ornament_fit_meets_the_accuracy_targets(ornament, ornament_photos, device):
    """The seed's per-texel model (the default): held-out PSNR and medians; its tails at material
    edges are what the renderer's lookup below removes. With the shared photo set's build, 103.5 s
    on the 2-core CPU (``pytest --durations``)."""
    train, held = ornament
    cfg = FitConfig(optimizer="lm", max_iterations=40, sync_every=1000)
    res, prob, held_psnr, gt, seen, rel, hi = fit_and_score(train, held, cfg, device, ornament_photos(device))
    # issue target 45 dB (measured 52.4 dB after 60 iterations, benchmarks/fit_accuracy.py)
    assert held_psnr >= 45.0, held_psnr
    material = train.material_id.reshape(-1)[prob.texels.grid_index]
    interior = seen & interior_texels(material, prob.texels.neighbors)
    # diffuse 1% on texels inside a material (measured median 0.08%, p90 0.25%); texels on a material
    # edge fit photos that blend two BRDFs (the renderer's bilinear texture lookup) and miss (p90 15%)
    assert np.percentile(rel[interior, 0:3], 90) < 0.01
    o = res.layout.lobe_offset(0)
    assert hi.sum() >= 200  # 326 of 968 texels
    # specular albedo 3% and exponent 5% as medians over highlight texels (measured 1.5% and 0.70% after
    # 60 iterations; with the seed's bilinear sampling 5.6% and 1.3%); tails in the README
    assert np.median(rel[hi, o:o + 3]) < 0.03
    assert np.median(rel[hi, o + 5]) < 0.05
    # per texel: the light rides beside the camera, so every highlight is seen near one incidence
    # angle, which fixes the lobe's height there but not rho_s and c_z apart; lobe_shape "auto" sees
    # that and holds c_z at 1 (fit/models.py "Lobe shape"). Measured on the CPU, 40 iterations as
    # here and 60 alike: 92.6% of highlight texels within 3%, p90 2.6% (with c_z free: 76%, p90 16%);
    # the misses sit mostly at material edges. 85% and 5% leave room for the CUDA run's float
    # differences, which tip a few texels' accept decisions
    assert res.layout.lobe_shape == "phong"
    err = rel[hi, o:o + 3].max(axis=1)
    assert np.mean(err <= 0.03) >= 0.85, np.mean(err <= 0.03)
    assert np.percentile(rel[hi, o:o + 3], 90) < 0.05, np.percentile(rel[hi, o:o + 3], 90)
    assert np.all(np.isfinite(res.params))


def test_small_ornament_fit_with_the_renderers_lookup_meets_every_bound(ornament, ornament_photos, device):
    """The renderer's model in the fit (``model_lookup`` bilinear, ``tap_geometry`` mesh): each
    filtered tap is traced to the mesh and blends its neighbours' BRDFs as the renderer does, so
    the truth explains its noise-free photos exactly (objective 6e-8) and the fit recovers it.
    Measured on the CPU (benchmarks/fit_accuracy.py, 20 iterations as here, 86 s of LM): held-out
    96.8 dB; every one of the 326 highlight texels within the issue's bounds, p90 errors 0.016%
    (rho_s) and 0.011% (n), diffuse p90 0.025% over all seen texels; after 60 iterations 126 dB.
    The bounds are the issue's, per texel; CUDA's float differences move the errors by far less
    than the margin."""
    train, held = ornament
    # 20 iterations: after 10 the worst texels still miss (rho_s 6%, diffuse 1.6%, measured)
    cfg = FitConfig(optimizer="lm", max_iterations=20, sync_every=1000,
                    stream=StreamConfig(model_lookup="bilinear", tap_geometry="mesh"))
    res, prob, held_psnr, gt, seen, rel, hi = fit_and_score(train, held, cfg, device, ornament_photos(device))
    assert held_psnr >= 45.0, held_psnr
    o = res.layout.lobe_offset(0)
    assert hi.sum() >= 200  # 326 of 968 texels
    worst = rel[hi, 0:3].max(), rel[hi, o:o + 3].max(), rel[hi, o + 5].max()
    assert worst[0] <= 0.01 and worst[1] <= 0.03 and worst[2] <= 0.05, worst
    # diffuse on every seen texel: p90 (a few texels seen in a handful of grazing photos miss 1%)
    assert np.percentile(rel[seen, 0:3], 90) < 0.01, np.percentile(rel[seen, 0:3], 90)
    assert np.all(np.isfinite(res.params))
