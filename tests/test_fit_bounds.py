"""Optimizers with texels on a bound: the synthetic lobes have c_z = 1, the upper bound, so many
ornament texels fit with c_z held there.

Regression for a stall: Jacobi-preconditioned L-BFGS mixed the held column into its direction, the
projected trial lost the descent, and a rejected texel rebuilt the same direction every iteration
(on the 0.02 ornament it ended 5% above LM after 60 iterations; on the full ornament it froze at 29%
above steepest descent). L-BFGS now drops binding-bound columns and forgets a rejected texel's pairs
(fit/kernels/optim_kernels.py ``unbound``, ``lbfgs_update_kernel``); LM freezes the same columns.
"""

from __future__ import annotations

import numpy as np
import pytest

from texstream.capture.synthetic.synth import SynthConfig, render_scene
from texstream.fit.optim.fitter import FitConfig, run_fit
from texstream.fit.stages.stage import build_problem

from conftest import SCENE_DEVICE


@pytest.fixture(scope="module")
def ornament():
    return render_scene("ornament", SynthConfig(scale=0.02, progress=False, device=SCENE_DEVICE))


def fit(scene, optimizer: str, device: str):
    # c_z free: "auto" would hold it at 1 for this light beside the camera, and the bound under test
    # would never bind
    cfg = FitConfig(optimizer=optimizer, max_iterations=60, sync_every=1000, lobe_shape="free")
    prob = build_problem(scene.mesh, scene.bake, scene.frames, scene.images, scene.masks, cfg, device)
    return run_fit(prob, cfg)


def test_lbfgs_keeps_descending_with_texels_on_a_bound(ornament, device):
    lm = fit(ornament, "lm", device)
    lbfgs = fit(ornament, "lbfgs", device)
    o = lm.layout.lobe_offset(0)
    lit = lm.params[:, o:o + 3].max(axis=1) > 0.05
    # the situation under test: many texels with a visible lobe end with c_z on its upper bound
    # (51% of 758 on the CPU)
    assert np.mean(lm.params[lit, o + 4] >= 1.0) > 0.3
    f_lm, f_lbfgs = lm.trace[-1]["objective"], lbfgs.trace[-1]["objective"]
    # measured on the CPU: L-BFGS 0.6704, LM 0.6701 (before the fix L-BFGS 0.7055, 5% above); 1% allows
    # for the CUDA run's float differences, which tip a few texels' accept decisions
    assert f_lbfgs <= 1.01 * f_lm, (f_lbfgs, f_lm)
    # and it keeps accepting steps instead of rebuilding rejected directions (77% at the end; before: 26%)
    assert lbfgs.trace[-1]["accepted_fraction"] > 0.5
