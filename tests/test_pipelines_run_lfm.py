"""``texstream run`` under one fixed, unknown light: light field mapping joins the radiance models when
view dependence matters (judged on a validation split of the fitted photos), the decision printed and
recorded with its reason and overridable (RunConfig.lfm, lfm_min_gain_db); an LFM model goes through export
and report."""

from __future__ import annotations

import dataclasses
import json

import pytest

from conftest import SCENE_DEVICE  # noqa: E402
from lfm_scenes import fixed_light_sphere_capture  # noqa: E402

from texstream.fit.models.radiance.choice import lfm_decision  # noqa: E402
from texstream.pipelines.run import RUN_LFM_ITERATIONS, RunConfig, run_pipeline  # noqa: E402


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    return fixed_light_sphere_capture(tmp_path_factory.mktemp("run_lfm"), device=SCENE_DEVICE)


def tiny_config(**top) -> RunConfig:
    cfg = RunConfig(device=SCENE_DEVICE, progress=False, **top)
    lfm = dataclasses.replace(cfg.fit.fit.lfm, iterations=20)
    fit = dataclasses.replace(cfg.fit.fit, max_iterations=5, lfm=lfm)
    cfg.fit = dataclasses.replace(cfg.fit, renders=1, fit=fit)
    return cfg


def test_lfm_decision_rules():
    assert RunConfig().fit.fit.lfm.iterations == RUN_LFM_ITERATIONS  # the run's cap on the LFM fit
    kinds, why = lfm_decision({"radiance": 20.0, "view_radiance": 22.0})
    assert kinds == ("lfm",) and "view dependence matters" in why and "+2.00 dB" in why
    kinds, why = lfm_decision({"radiance": 20.0, "view_radiance": 20.3})
    assert kinds == () and "does not matter" in why and "+0.30 dB" in why
    assert lfm_decision({"radiance": 20.0, "view_radiance": 20.3}, min_gain_db=0.2)[0] == ("lfm",)
    assert lfm_decision({"radiance": 20.0, "view_radiance": 30.0}, mode="never")[0] == ()
    assert lfm_decision({"radiance": 30.0, "view_radiance": 20.0}, mode="always")[0] == ("lfm",)
    kinds, why = lfm_decision({"radiance": None, "view_radiance": None})
    assert kinds == () and "no validation score" in why


def test_view_dependence_brings_in_lfm_and_the_best_validated_model_is_kept(capture, tmp_path):
    out = tmp_path / "out"
    lines: list[str] = []
    cfg = tiny_config(mesh_file=str(capture / "ground_truth"))
    summary = run_pipeline(capture, out, cfg, log=lines.append)
    sel = summary["fit"]["selection"]
    scores = {k: v["pooled_psnr_db"] for k, v in sel["validation"].items()}
    # the highlight moves with the camera under the fixed light: view_radiance beats radiance on the validation
    # photos (every 8th fitted photo) by more than the 0.5 dB bar, so light field mapping is fitted too
    assert scores["view_radiance"] - scores["radiance"] > 0.5
    assert set(scores) == {"radiance", "view_radiance", "lfm"}
    assert "view dependence matters" in sel["lfm"] and sel["lfm"] in summary["model_reason"]
    assert any("view dependence matters" in m for m in lines)  # printed
    assert sel["chosen"] == max(scores, key=scores.get) == summary["model"]
    # choice.stop_hopeless: the LFM validation fit was given the radiance models' best score and checked its own
    # on the rendered validation photos from iteration 10 on (two checks of its 20 iterations: no bound yet)
    stop = sel["validation"]["lfm"]["stop"]
    assert stop["beat_db"] == max(scores["radiance"], scores["view_radiance"]) and stop["stopped"] is None
    assert [i for i, _ in stop["checks"]] == [10, 15] and all(15 < db < 60 for _, db in stop["checks"])
    man = json.loads((out / "model" / "model.json").read_text())
    assert man["layout"]["kind"] == summary["model"]
    assert not list(out.glob("model_*"))  # the others had validation fits only, removed after the choice
    assert (out / "export" / "model.glb").is_file() and (out / "report" / "index.html").is_file()
    assert json.loads((out / "run.json").read_text())["fit"]["selection"]["lfm"] == sel["lfm"]


def test_lfm_candidate_overrides_and_an_lfm_model_through_export_and_report(capture, tmp_path):
    # never: the two radiance models only, the reason recorded
    cfg = tiny_config(mesh_file=str(capture / "ground_truth"), lfm="never")
    s = run_pipeline(capture, tmp_path / "never", cfg, log=lambda m: None)
    assert set(s["fit"]["selection"]["validation"]) == {"radiance", "view_radiance"}
    assert "lfm = never" in s["fit"]["selection"]["lfm"]
    # model lfm, asked for: no selection; export writes the unlit glTF, the report the LFM viewer
    out = tmp_path / "lfm"
    s = run_pipeline(capture, out, tiny_config(mesh_file=str(capture / "ground_truth"), model="lfm"),
                     log=lambda m: None)
    assert s["model"] == "lfm" and s["model_reason"] == "requested" and s["heldout"]["views"] == 6
    exp = json.loads((out / "export" / "export.json").read_text())
    assert exp["model_kind"] == "lfm" and "maps/view_k0.exr" in exp["maps"]
    html = (out / "report" / "index.html").read_text()
    assert '"kind":"lfm"' in html and "Light field mapping model" in html


def test_an_lfm_candidate_the_capture_cannot_take_is_left_out_with_the_reason(capture, tmp_path):
    """Photos streamed in windows (stream.photos_per_window > 0) suit the radiance fits but not the LFM fit,
    which keeps every photo on the device: the run keeps going without it and says why."""
    cfg = tiny_config(mesh_file=str(capture / "ground_truth"), lfm="always")
    windows = dataclasses.replace(cfg.fit.fit.stream, photos_per_window=8)
    cfg.fit.fit = dataclasses.replace(cfg.fit.fit, stream=windows)
    s = run_pipeline(capture, tmp_path / "out", cfg, log=lambda m: None)
    sel = s["fit"]["selection"]
    assert set(sel["validation"]) == {"radiance", "view_radiance"} and "lfm" in sel["left_out"]
    assert "lfm could not be fitted" in sel["lfm"] and "photo" in sel["lfm"]
    assert s["model"] in ("radiance", "view_radiance")
