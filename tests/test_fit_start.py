"""The fit's starting point is made on the device (fitter.fit_start, FitState.create): the same float64
operations as the NumPy definitions (models.energy_bound_numpy, the percentile guess), so the same bits."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from texstream.capture.synthetic.synth import SynthConfig, render_scene
from texstream.fit.optim.fitter import FitConfig
from texstream.fit.kernels import optim_kernels as K
from texstream.render.layout import ModelLayout, energy_bound_numpy
from texstream.fit.optim.base import FitState
from texstream.fit.stream.config import StreamConfig
from texstream.fit.stages.stage import build_problem

from conftest import SCENE_DEVICE


@pytest.fixture(scope="module")
def sphere():
    return render_scene("sphere", SynthConfig(scale=0.05, photos=6, image_size=32, progress=False, device=SCENE_DEVICE))


def reference_guess(lay: ModelLayout, low: np.ndarray, high: np.ndarray, count: np.ndarray,
                    percentile: bool) -> np.ndarray:
    """The starting parameters as NumPy defines them (float64)."""
    lo, hi = low.astype(np.float64), high.astype(np.float64)
    p = np.tile(lay.defaults(), (len(count), 1))
    if percentile:
        seen = count > 0
        p[seen, 0:3] = np.clip(lo[seen], lay.lower()[0:3], lay.upper()[0:3])
        for j in range(lay.n_lobes):
            o = lay.lobe_offset(j)
            p[seen, o:o + 3] = np.clip(hi[seen] - lo[seen], 0.05, None) / (j + 1)
    return p


@pytest.mark.parametrize("kind,lobes", [("lafortune", 2), ("radiance", 0), ("view_radiance", 0)])
@pytest.mark.parametrize("percentile", [True, False])
def test_guess_kernel_equals_the_numpy_definition(device, kind, lobes, percentile):
    lay = ModelLayout(kind=kind, n_lobes=lobes)
    rng = np.random.default_rng(3)
    n = 4000
    # samples beyond the bounds (negative, above rho_d's 10), excesses below 0.05, unseen texels
    low = rng.uniform(-1.0, 12.0, (n, 3)).astype(np.float32)
    high = (low + rng.uniform(-0.1, 3.0, (n, 3))).astype(np.float32)
    count = rng.integers(0, 4, n).astype(np.int32)
    guess = wp.empty((n, lay.n_params), dtype=wp.float64, device=device)
    f64 = {k: wp.array(v, dtype=wp.float64, device=device) for k, v in
           (("d", lay.defaults()), ("lo", lay.lower()), ("hi", lay.upper()))}
    wp.launch(K.guess_from_samples_kernel, dim=n, device=device,
              inputs=[wp.array(low, dtype=wp.vec3, device=device), wp.array(high, dtype=wp.vec3, device=device),
                      wp.array(count, dtype=wp.int32, device=device), f64["d"], f64["lo"], f64["hi"],
                      int(percentile), lay.n_lobes, lay.lobe_stride, wp.float64(0.05)], outputs=[guess])
    # bit for bit: one float64 subtraction, maximum, clip and division each, in NumPy's order
    np.testing.assert_array_equal(guess.numpy(), reference_guess(lay, low, high, count, percentile))


@pytest.mark.parametrize("storage,accumulate", [("fp16", "fp32"), ("fp32", "fp32"), ("fp64", "fp64"),
                                                ("fp64", "fp32")])
@pytest.mark.parametrize("albedo_max", [0.0, 1.0])
def test_first_point_is_the_float64_projection(device, sphere, storage, accumulate, albedo_max):
    cfg = FitConfig(optimizer="lm", stream=StreamConfig(storage=storage, accumulate=accumulate))
    sc = sphere
    pr = build_problem(sc.mesh, sc.bake, sc.frames, sc.images, sc.masks, cfg, device)
    lay = pr.layout
    rng = np.random.default_rng(7)
    lo, hi = lay.lower(), lay.upper()
    # within and beyond every bound, lobes bright enough for the energy bound to bite
    p0 = rng.uniform(lo - 0.5 * (hi - lo) - 1.0, hi + 0.5 * (hi - lo) + 1.0, (pr.n, lay.n_params))
    p0[:, lay.lobe_offset(0) + lay.lobe_stride - 1] = rng.uniform(0.0, 50.0, pr.n)  # exponents near the cap
    counts = rng.integers(0, 3, pr.n).astype(np.int32)
    st = FitState.create(pr, p0, ~lay.frozen(), lobe_albedo_max=albedo_max,
                         counts=wp.array(counts, dtype=wp.int32, device=device))
    want = energy_bound_numpy(np.clip(p0, lo, hi), lay, albedo_max)
    compute = np.float64 if pr.accumulate == "fp64" else np.float32
    got = st.p.numpy().reshape(pr.n, -1)[:, :lay.n_params]
    # bit for bit: the kernel's clip and energy bound are NumPy's float64 operations, then one rounding
    np.testing.assert_array_equal(got, want.astype(compute))
    # the storage precision is rounded from float64 directly, except half floats: through float32, as Warp converts
    with np.errstate(over="ignore"):  # rho_s up to 1e5 is beyond half floats: inf, in both
        stored = want.astype(np.float32).astype(np.float16) if storage == "fp16" else want.astype(
            {"fp32": np.float32, "fp64": np.float64}[storage])
    np.testing.assert_array_equal(st.storage.numpy(), stored)
    np.testing.assert_array_equal(st.valid.numpy(), (counts > 0).astype(np.int32))
    np.testing.assert_array_equal(st.trial.numpy(), st.p.numpy())
