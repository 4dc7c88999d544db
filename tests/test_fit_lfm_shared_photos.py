"""Light field mapping without repeated work (issue 40): on the model choice's shared photo set (fit/common/inputs.py
SharedPhotoSet) after a radiance fit of the same capture, the LFM fit takes that fit's photos and maps instead of
decoding, uploading and mapping them again; on the CPU its samples are kept after the first pass
(fit/models/lfm/problem.py sample_cache_budget) instead of being distributed from the photos at every pass. Either
way its parameters are those of a fit that does the work again, to the bit (the same arithmetic on the same
bytes)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from texstream.pipelines.cli import main


@pytest.fixture(scope="module")
def star(tmp_path_factory):
    cap = tmp_path_factory.mktemp("lfm_shared") / "cap"
    # the tiny star of test_fit_lfm_cli.py: 24 photos of 48x48, a 58x29 atlas
    assert main(["synth", "star", "-o", str(cap), "--scale", "0.01", "--photos", "24", "--image-size", "48",
                 "--no-preview", "--no-progress"]) == 0
    return cap


def test_lfm_on_shared_photos_or_kept_samples_gives_the_same_model(star, tmp_path):
    from texstream.core.progress import reporting
    from texstream.fit.common.inputs import SharedPhotoSet
    from texstream.fit.models.lfm.problem import CPU_SAMPLE_CACHE_BYTES, sample_cache_budget
    from texstream.fit.optim.fitter import FitConfig
    from texstream.fit.optim.lfm_config import LFMConfig
    from texstream.fit.stages.stage import FitStageConfig, fit_model

    def cfg(model, sample_cache="auto"):
        return FitStageConfig(device="cpu", holdout_every=8, renders=0,
                              fit=FitConfig(model=model, max_iterations=3,
                                            lfm=LFMConfig(iterations=5, sample_cache=sample_cache)))

    mesh = star / "ground_truth"
    SharedPhotoSet.release()
    try:
        fit_model(star, mesh, tmp_path / "alone", cfg("lfm"), progress=False)
        SharedPhotoSet.release()
        fit_model(star, mesh, tmp_path / "distributed", cfg("lfm", "off"), progress=False)
        SharedPhotoSet.release()
        fit_model(star, mesh, tmp_path / "radiance", cfg("radiance"), progress=False)
        said = []
        with reporting(said.append):
            fit_model(star, mesh, tmp_path / "shared", cfg("lfm"), progress=False)
    finally:
        SharedPhotoSet.release()
    assert any("shared with the previous fit" in line for line in said), said
    models = {k: np.load(tmp_path / k / "lfm.npz") for k in ("alone", "distributed", "shared")}
    for name in ("diffuse", "G", "H"):
        np.testing.assert_array_equal(models["alone"][name], models["shared"][name])
        np.testing.assert_array_equal(models["alone"][name], models["distributed"][name])
    assert json.loads((tmp_path / "alone" / "model.json").read_text())["lfm"]["sample_cache"] is True
    assert json.loads((tmp_path / "distributed" / "model.json").read_text())["lfm"]["sample_cache"] is False
    # the temple's case: 105 MB of samples against 43 MB of photos are kept on the CPU (a GPU keeps no more
    # samples than photos)
    assert sample_cache_budget(43 << 20, "cpu") == CPU_SAMPLE_CACHE_BYTES > 105 << 20
