"""A fit interrupted (Ctrl-C, a killed process) resumes from its checkpoint to the same result, to the
last bit, as an uninterrupted fit on the same device (Levenberg-Marquardt, the default)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from texstream.core.progress import reporting
from texstream.fit.optim.fitter import FitConfig
from texstream.fit.stages.stage import FitStageConfig, fit_stage

from conftest import SCENE_DEVICE, tiny_sphere_capture  # noqa: E402


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    return tiny_sphere_capture(tmp_path_factory.mktemp("resume"), photos=12)


def config() -> FitStageConfig:
    # sync every 2 iterations: checkpoints at 2, 4 and 6; rel_tol 0 so both fits run all 8
    return FitStageConfig(device=SCENE_DEVICE, renders=1, fit=FitConfig(max_iterations=8, sync_every=2, rel_tol=0.0))


def maps(model):
    from texstream.capture.synthetic.param_maps import read_param_maps
    from texstream.render.layout import ModelLayout

    lay = ModelLayout.from_json(json.loads((model / "model.json").read_text())["layout"])
    return read_param_maps(model, lay)


def test_an_interrupted_fit_resumes_to_the_uninterrupted_result(capture, tmp_path, monkeypatch):
    import texstream.fit.common.setup as stage

    gt = capture / "ground_truth"
    whole = fit_stage(capture, gt, tmp_path / "whole", config(), progress=False)
    assert whole.summary["resumed_from"] is None
    real = stage.run_fit

    def interrupted(problem, fit, progress=None, **kw):
        def stop_at_5(it):
            if it == 5:
                raise KeyboardInterrupt
        return real(problem, fit, progress=stop_at_5, **kw)

    monkeypatch.setattr(stage, "run_fit", interrupted)
    with pytest.raises(KeyboardInterrupt):
        fit_stage(capture, gt, tmp_path / "resumed", config(), progress=False)
    checkpoint = tmp_path / ".resumed.checkpoint.npz"
    assert checkpoint.is_file() and not (tmp_path / "resumed").exists()
    monkeypatch.setattr(stage, "run_fit", real)
    lines = []
    with reporting(lines.append, bars=False):
        again = fit_stage(capture, gt, tmp_path / "resumed", config(), progress=False)
    assert again.summary["resumed_from"] == 4 and not checkpoint.exists()
    assert any(f"resuming from checkpoint {checkpoint}: 4 iterations done" in line for line in lines), lines
    np.testing.assert_array_equal(maps(tmp_path / "resumed"), maps(tmp_path / "whole"))
    t_whole = json.loads((tmp_path / "whole" / "trace.json").read_text())
    t_again = json.loads((tmp_path / "resumed" / "trace.json").read_text())
    assert [r["objective"] for r in t_again] == [r["objective"] for r in t_whole]
    assert len([r for r in t_whole if r.get("stage") != "traced polish"]) == 9  # then the traced polish's rows


def test_a_checkpoint_of_other_options_is_not_used(capture, tmp_path, monkeypatch):
    import dataclasses

    import texstream.fit.common.setup as stage

    gt = capture / "ground_truth"
    ck = stage.Checkpoint(tmp_path / "m", {"other": "options"})
    ck.save({"iteration": 6, "p": np.zeros((1, 1)), "lam": np.zeros(1), "trace": np.zeros((7, 8)),
             "times": np.zeros(7), "last_obj": 0.0, "robust_scale": 0.0})
    cfg = dataclasses.replace(config(), fit=dataclasses.replace(config().fit, max_iterations=3))
    lines = []
    with reporting(lines.append, bars=False):
        res = fit_stage(capture, gt, tmp_path / "m", cfg, progress=False)
    assert any("is of other inputs or options: ignored, starting afresh" in line for line in lines), lines
    trace = json.loads((tmp_path / "m" / "trace.json").read_text())
    fitted = [r for r in trace if r.get("stage") != "traced polish"]
    assert res.summary["resumed_from"] is None and fitted[-1]["iteration"] == 3


def test_an_interrupted_model_choice_keeps_its_finished_candidates(capture, tmp_path, monkeypatch):
    """--model auto fits candidates one after another (fit/stages/choice.py); killed during the second, the rerun
    keeps the first (stage.fit_candidate: same inputs and options), fits the rest and chooses as an uninterrupted
    choice does, the kept model's maps identical to the last bit."""
    import dataclasses

    import texstream.fit.stages.stage as stage
    from texstream.fit.models.materials import MaterialConfig
    from texstream.fit.stages.choice import ModelChoiceConfig

    gt = capture / "ground_truth"
    # two short candidates (no traced polish, no shared materials, 2 iterations): the choice, not the fit, is tested
    cfg = dataclasses.replace(config(), holdout_every=4, traced_polish=0, renders=0,
                              materials=MaterialConfig(mode="off"), choice=ModelChoiceConfig(second_lobe=False),
                              fit=dataclasses.replace(config().fit, model="auto", max_iterations=2))
    whole = fit_stage(capture, gt, tmp_path / "whole", cfg, progress=False)
    assert set(whole.summary["selection"]["validation"]) == {"lafortune", "diffuse"}  # both judged
    real, fitted = stage.fit_model, []

    def killed_in_the_second(capture_dir, mesh_path, out_dir, c, progress=True):
        fitted.append(c.fit.model)
        if len(fitted) == 2:
            raise KeyboardInterrupt
        return real(capture_dir, mesh_path, out_dir, c, progress)

    monkeypatch.setattr(stage, "fit_model", killed_in_the_second)
    with pytest.raises(KeyboardInterrupt):
        fit_stage(capture, gt, tmp_path / "again", cfg, progress=False)
    monkeypatch.undo()
    lines = []
    with reporting(lines.append, bars=False):
        again = fit_stage(capture, gt, tmp_path / "again", cfg, progress=False)
    kept = [line for line in lines if "was fitted before with the same inputs and options" in line]
    assert len(kept) == 1 and f"{fitted[0]}:" in kept[0], lines
    assert without_seconds(again.summary["selection"]) == without_seconds(whole.summary["selection"])
    np.testing.assert_array_equal(maps(tmp_path / "again"), maps(tmp_path / "whole"))
    assert not list(tmp_path.rglob(stage.CANDIDATE_STAMP))  # the finished choice forgets its candidates


def without_seconds(record):
    """A choice's record less the seconds it took (the same choice, another clock)."""
    if isinstance(record, dict):
        return {k: without_seconds(v) for k, v in record.items() if k != "seconds"}
    return record
