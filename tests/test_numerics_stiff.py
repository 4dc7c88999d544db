"""The stiff and extreme fitting suite at CI size (fit/stiffcheck.py; issue 20 part 3).

Each case fits a synthetic capture at one extreme in the precision the fit would use and again in float64;
the suite's own checks are asserted: no NaN or Inf in parameters, traces or renders, every texel within its
bounds, the fit under test within the case's tolerance of the float64 reference (dB of sample PSNR; a
tolerance per case in fit/stiffcheck.py with its reason), and at a million photos per texel the automatic
accumulation keeps the relative error of E below 1e-5.
"""

from __future__ import annotations

import pytest

from texstream.fit.diagnostics.stiffcheck import default_cases, run_case

CASES = default_cases()


@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_stiff_case_meets_its_checks(case, device):
    rec = run_case(case, "ci", device)
    assert rec["nonfinite"] == 0
    assert rec["out_of_bounds_texels"] == 0
    assert rec["ok"], rec["failures"]


def test_each_regime_is_exercised():
    """The cases really reach their extremes (a suite whose captures drifted to easy ones would pass
    vacuously)."""
    by = {c.name: c for c in CASES}
    hdr = run_case(by["hdr_range"], "ci", "cpu")
    # photo values span more than six decades within the foreground
    assert hdr["photo_peak"] / hdr["photo_min_foreground"] > 1e6
    few = run_case(by["few_photos"], "ci", "cpu")
    # texels seen by none, one and two of the three photos
    assert few["photos"] == 3 and all(few["texels_by_photo_count"].get(k, 0) > 0 for k in (0, 1, 2))
    acc = run_case(by["million_photos"], "ci", "cpu")
    # the naive float32 sum of the same terms misses 1e-5: the automatic choice is what keeps E accurate
    assert acc["auto_choice"] == "fp64" and acc["rel_error_E"]["fp32"] > 1e-5
    graze = run_case(by["grazing_light"], "ci", "cpu")
    assert graze["texels_seen"] > 0  # with rejection off the grazing samples do reach the fit


def test_fit_warns_where_the_suite_found_the_precision_unsafe():
    import numpy as np

    from texstream.fit.stream.config import FP32_SAFE_PHOTOS, StreamConfig
    from texstream.fit.diagnostics.stiffcheck import numerics_warnings

    assert numerics_warnings(StreamConfig(), 10 * FP32_SAFE_PHOTOS) == []  # auto: fp64 sums there
    many = numerics_warnings(StreamConfig(accumulate="fp32"), FP32_SAFE_PHOTOS + 1)
    assert len(many) == 1 and "--stream.accumulate auto" in many[0]
    assert numerics_warnings(StreamConfig(accumulate="fp32", kahan=True), FP32_SAFE_PHOTOS + 1) == []
    mask = np.ones((4, 4), bool)
    hdr = [np.full((4, 4, 3), 1.0e5, np.float32)]
    assert "exceed float16" in numerics_warnings(StreamConfig(image_precision="fp16"), 1, hdr, [mask])[0]
    assert numerics_warnings(StreamConfig(), 1, hdr, [mask]) == []  # float32 photos hold 1e5
    dark = [np.full((4, 4, 3), 1.0e-6, np.float32)]
    assert "smallest normal" in numerics_warnings(StreamConfig(image_precision="fp16"), 1, dark, [mask])[0]


def test_fit_stage_records_the_numerics_warning(tmp_path):
    """`texstream fit` with hand-picked float32 sums past the safe photo count writes the one-line warning
    into model.json (which the report lists); the safe count is lowered so a tiny capture crosses it."""
    import json
    from unittest import mock

    from conftest import tiny_sphere_capture
    from texstream.fit.stages.stage import FitStageConfig, fit_stage

    cap = tiny_sphere_capture(tmp_path, photos=6)
    cfg = FitStageConfig()
    cfg.fit.max_iterations = 2
    cfg.fit.stream.accumulate = "fp32"
    cfg.materials.mode = "off"
    with mock.patch("texstream.fit.stream.config.FP32_SAFE_PHOTOS", 3):
        res = fit_stage(cap, cap / "ground_truth", tmp_path / "model", cfg, progress=False)
    man = json.loads((tmp_path / "model" / "model.json").read_text())
    assert any(w.startswith("numerics: float32 sums") for w in man["warnings"])
    assert any(w.startswith("numerics:") for w in res.summary["warnings"])
