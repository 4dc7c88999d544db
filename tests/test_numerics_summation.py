"""The summation study's kernels and the automatic accumulation choice (``StreamConfig.accumulate`` "auto").

Issue 20's done-when: the automatic choice keeps the relative error of E below 1e-5 at the largest photo
count the study covers (benchmarks/summation.py: 10^7 terms, 3 per photo). Exact sums: ``math.fsum`` (the
correctly rounded float64 of the exact sum, 1.1e-16 relative, far below the 1e-5 asserted).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from conftest import DEVICES

from texstream.core.errors import ConfigError
from texstream.fit.kernels.summation import ERROR_SUMS, streamed_sums, study_terms
from texstream.fit.stream.config import FP32_SAFE_PHOTOS, FP32_SAFE_TOLERANCE, StreamConfig, resolve_accumulate

ROOT = Path(__file__).resolve().parent.parent
STUDY = ROOT / "benchmarks" / "results" / "summation_cpu" / "summation.json"
E_TOLERANCE = 1e-5  # issue 20's bound on the relative error of E


def relative_errors(terms: np.ndarray, method: str, device: str) -> np.ndarray:
    exact = np.array([math.fsum(row.astype(np.float64).tolist()) for row in terms])
    return np.abs(streamed_sums(terms, method, device) - exact) / np.abs(exact)


def test_resolve_accumulate():
    assert StreamConfig().accumulate == "auto"
    assert resolve_accumulate("auto", FP32_SAFE_PHOTOS) == "fp32"
    assert resolve_accumulate("auto", FP32_SAFE_PHOTOS + 1) == "fp64"
    assert resolve_accumulate("fp32", 10 ** 7) == "fp32" and resolve_accumulate("fp64", 1) == "fp64"
    with pytest.raises(ConfigError):
        resolve_accumulate("fp16", 10)


def test_threshold_is_the_recorded_study_s():
    # the constant in fit/problem.py is the one the recorded study derived (rerun it after changing either)
    study = json.loads(STUDY.read_text())
    assert study["fp32_safe_photos_measured"] == FP32_SAFE_PHOTOS
    assert study["fp32_safe_tolerance"] == FP32_SAFE_TOLERANCE


def test_auto_choice_keeps_e_within_1e5_at_the_largest_photo_count(device):
    terms_max = json.loads(STUDY.read_text())["sizes"][-1]  # 10^7 terms
    photos = terms_max // 3
    method = resolve_accumulate("auto", photos)
    for k, kind in enumerate(ERROR_SUMS):
        terms = study_terms(kind, 1, terms_max, seed=424242 + k)  # not the study's seeds
        err = relative_errors(terms, method, device)
        assert err.max() < E_TOLERANCE, (kind, method, err)
    # and naive float32 there would not: the choice matters (measured 7.8e-3 to 5.1e-2)
    naive = relative_errors(study_terms("error_near_constant", 1, terms_max, seed=424242), "fp32", device)
    assert naive.max() > E_TOLERANCE


def test_fp32_is_within_1e5_up_to_the_threshold(device):
    # a fresh draw at the threshold: the study measured at most 2.75e-6 there; 1e-5 leaves a factor 3.6
    for k, kind in enumerate(ERROR_SUMS):
        terms = study_terms(kind, 8, 3 * FP32_SAFE_PHOTOS, seed=99 + k)
        assert relative_errors(terms, "fp32", device).max() < E_TOLERANCE, kind


def test_kahan_and_pairwise_float32_stay_near_float32_rounding(device):
    # Kahan: |delta_i| < 2 eps per term (seed eq. 6.10), so about 2 * 6e-8 relative for positive sums at
    # any length; pairwise: eps log2(n). 3e-7 bounds both at 10^5 terms
    terms = study_terms("error_wide", 2, 100_000, seed=5)
    for method in ("fp32_kahan", "pairwise"):
        assert relative_errors(terms, method, device).max() < 3e-7, method


def test_problem_uses_the_resolved_precision(monkeypatch):
    import warp as wp

    from test_fit_gradients import plane_problem

    from texstream.fit.stream import config as problem_module  # the threshold resolve_accumulate reads
    from texstream.render.layout import ModelLayout

    monkeypatch.setattr(problem_module, "FP32_SAFE_PHOTOS", 2)  # a threshold small photo sets cross
    many, _ = plane_problem(DEVICES[0], ModelLayout(), n_photos=3, grid=2, acc="auto")
    few, _ = plane_problem(DEVICES[0], ModelLayout(), n_photos=2, grid=2, acc="auto")
    assert many.accumulate == "fp64" and many.scalar is wp.float64
    assert few.accumulate == "fp32" and few.scalar is wp.float32
