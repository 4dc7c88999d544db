"""Fit of 8-bit, noisy photos reaches the noise floor (issue 3 done-when).

"With 8-bit photos and camera noise, PSNR within 1 dB of the noise floor (the PSNR of the noisy
photos against the clean renders)". Precisely, as measured here:

- Photos: the sphere scene developed with Gaussian camera noise (sigma = 0.01 in linear units,
  after exposure) and then quantised to 8-bit sRGB codes (capture/synthetic/synth.py ``develop``); the
  exposure (0.8) keeps every clean pixel below 1, so nothing clips and the floor is noise plus
  quantisation only. ``save_clean`` keeps the noise-free float renders.
- Pixels: the foreground of every view, i.e. the photo's object mask intersected with the fitted
  render's coverage (the same mesh, so in practice the mask), all three channels, pooled over
  the views of a set: MSE = mean over those pixel values, PSNR = 10 log10(1 / MSE) with peak 1
  (8-bit white in linear units), as ``fit.stage.image_metrics`` defines it.
- Noise floor = PSNR(noisy photos, clean renders). The done-when's "PSNR" is the fitted model's
  render against the noisy photos: a model that reproduces the signal but not the noise has a
  residual that is the noise, so it sits at the floor; a model that fits the noise (overfits)
  sits above it on the training views and below it elsewhere; one that misses signal sits below.
  Asserted within 1 dB, on the training views and on held-out views (cameras turned 7 degrees,
  independent noise).
- Also the fitted render against the clean renders must be at least as good as the floor: the fit
  averages the noise of many photos, so its error to the truth is below the noise level.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from texstream.capture.synthetic.synth import SynthConfig, render_scene
from texstream.fit.optim.fitter import FitConfig, run_fit
from texstream.fit.stream.penalties import PenaltyConfig
from texstream.fit.stream.config import StreamConfig
from texstream.fit.stages.stage import build_problem, params_to_grid, render_model

from conftest import SCENE_DEVICE

# 360 photos of 48 px, ~400 texels: ~36 samples per texel (9 parameters) keeps the lobe estimates'
# noise well below the photo noise (with 120 photos the held-out renders were 6 dB under the floor)
NOISY = dict(scale=0.05, image_size=48, noise=0.01, bits=8, exposure=0.8, save_clean=True, progress=False,
             device=SCENE_DEVICE)


@pytest.fixture(scope="module")
def noisy_sphere():
    train = render_scene("sphere", SynthConfig(**NOISY, photos=360))
    held = render_scene("sphere", SynthConfig(**NOISY, photos=8, azimuth_offset=7.0, seed=1))
    return train, held


def pooled_psnr(pairs) -> float:
    """PSNR (dB, peak 1) of the pooled squared error over (a, b, mask) triples."""
    se, count = 0.0, 0
    for a, b, m in pairs:
        d = (a[m] - b[m]).astype(np.float64)
        se += float((d * d).sum())
        count += d.size
    return 10 * math.log10(count / se)


def floor_and_fit(scene, mesh, grid, layout, device) -> tuple[float, float, float]:
    """(noise floor, fit vs noisy, fit vs clean) PSNRs over a scene's views (module doc)."""
    floor, vs_noisy, vs_clean = [], [], []
    for fr, photo, clean, mask in zip(scene.frames, scene.images, scene.clean, scene.masks):
        render, rmask = render_model(mesh, grid, layout, fr, device)
        m = mask & rmask.astype(bool)
        floor.append((photo, clean, m))
        vs_noisy.append((render, photo, m))
        vs_clean.append((render, clean, m))
    return pooled_psnr(floor), pooled_psnr(vs_noisy), pooled_psnr(vs_clean)


def test_noisy_8bit_fit_reaches_the_noise_floor(noisy_sphere, device):
    train, held = noisy_sphere
    for sc in (train, held):
        assert max(float(c[m].max()) for c, m in zip(sc.clean, sc.masks)) < 1.0  # no clipping
    # LM with the edge-aware shape smoothness (fit/optim/lm.py): without it single texels fit
    # lobes to the noise of their few highlight samples (measured 2.6 dB under the floor on the
    # training renders). The sphere is convex, so no cast shadows: shadow maps off (they would
    # be 360 ray-cast 512^2 maps, ~20 s of setup).
    cfg = FitConfig(optimizer="lm", max_iterations=20, sync_every=1000,
                    penalties=PenaltyConfig(smooth_weight=1e-2, smooth_params="shape"),
                    stream=StreamConfig(shadow_map_size=0))
    prob = build_problem(train.mesh, train.bake, train.frames, train.images, train.masks, cfg, device)
    res = run_fit(prob, cfg)
    assert np.all(np.isfinite(res.params))
    grid = params_to_grid(res, prob, train.bake)
    for name, sc in (("train", train), ("held-out", held)):
        floor, vs_noisy, vs_clean = floor_and_fit(sc, train.mesh, grid, res.layout, device)
        print(f"{name}: floor {floor:.2f} dB, fit vs noisy {vs_noisy:.2f} dB, fit vs clean {vs_clean:.2f} dB")
        # sigma 0.01 plus 8-bit steps: the floor is ~40.3 dB (measured 40.33 train, 40.25 held-out)
        assert 39.0 < floor < 41.5, (name, floor)
        # the target, 1 dB (measured with filtered sampling 0.59 dB under the floor on train,
        # 0.49 held-out; bilinear 0.34 / 0.39)
        assert abs(vs_noisy - floor) <= 1.0, (name, floor, vs_noisy)
        # the model is closer to the truth than the photos are (measured 48.7 dB train, 49.3 held-out;
        # bilinear 51.1 / 50.5)
        assert vs_clean >= floor, (name, floor, vs_clean)
