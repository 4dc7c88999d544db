"""The automatic model choice (fit/stages/choice.py) decides on a validation split of the fitted photos only:
its candidates' fits are stand-ins here (no Warp), each writing a model folder whose scores are made up so that
the held-out photos would choose differently from the validation photos; the choice must follow the validation
photos, fit the kept model to every fitted photo, leave out a candidate the photos cannot support unfitted, and
record what it did in the summary and model.json. The fits themselves are tested by the run's tests
(tests/test_pipelines_run.py) and the materials choice's (tests/test_fit_materials_choice.py)."""

from __future__ import annotations

import json

from texstream.core.outputs import StageResult
from texstream.fit.models.lafortune.choice import TWO_LOBES, candidates, second_lobe_supported
from texstream.fit.stages.choice import ChoicePlan, fit_choice
from texstream.fit.stages.stage import FitStageConfig


def fake_fits(validation: dict, heldout: dict, constrained_share: float = 0.1, highlight_share: float = 0.3):
    """A stand-in for the fit stage: pooled PSNR ``validation[name]`` on the validation photos (from the
    materials choice of a Lafortune fit of every photo, or from a validation fit) and ``heldout[name]`` on the
    held-out photos, a diffuse fit's photos showing highlights on ``highlight_share`` of 1,000 texels; the calls
    made, as (name, validation fit?)."""
    calls = []

    def fit_one(capture_dir, mesh_path, out, cfg):
        name = out.name.removeprefix("model_").removesuffix("_validation")
        calls.append((name, cfg.choice.validation_fit))
        out.mkdir(parents=True, exist_ok=True)
        (out / "model.json").write_text(json.dumps({"kind": cfg.fit.model}))
        score = {"views": 2, "pooled_psnr_db": validation[name] if cfg.choice.validation_fit else heldout[name],
                 "worst_psnr_db": 20.0}
        summary = {"heldout": score, "materials": None}
        if cfg.fit.model == "diffuse":
            summary["highlights"] = {"seen_texels": 1000, "highlight_texels": int(1000 * highlight_share)}
        if cfg.fit.model == "lafortune" and not cfg.choice.validation_fit:
            summary["materials"] = {
                "chosen": "mixed", "k": 2,
                "candidates": [{"model": "per-texel", "pooled_psnr_db": validation[name] - 5, "worst_psnr_db": 1.0},
                               {"model": "mixed", "k": 2, "pooled_psnr_db": validation[name], "worst_psnr_db": 21.0}],
                "uncertainty": {"constrained_texels": int(1000 * constrained_share), "seen_texels": 1000}}
        return StageResult(out, summary)

    return fit_one, calls


def plan(cfg) -> ChoicePlan:
    return ChoicePlan("lafortune", "known lights", candidates(None, cfg))


def test_the_validation_photos_choose_and_the_held_out_ones_only_score(tmp_path):
    """Diffuse would win on the held-out photos (45 against 30 dB) and loses on the validation photos (35 against
    40 dB): Lafortune is kept, judged by its own materials choice on the split (the mixed K=2 score), and fitted
    once; diffuse gets a validation fit only (first: its photos' highlights decide whether Lafortune is fitted),
    removed afterwards. The two-lobe candidate is left out unfitted
    (10% of the texels constrained < 30%). The summary and model.json record the validation scores, the reason
    and the kept model's held-out score."""
    cfg = FitStageConfig(holdout_every=8)
    fit_one, calls = fake_fits({"lafortune": 40.0, "diffuse": 35.0}, {"lafortune": 30.0, "diffuse": 45.0})
    res = fit_choice(tmp_path, tmp_path, tmp_path / "model", cfg, plan(cfg), fit_one, log=lambda line: None)
    assert calls == [("diffuse", True), ("lafortune", False)]
    sel = res.summary["selection"]
    assert sel["chosen"] == "lafortune" and res.output == tmp_path / "model"
    assert sel["validation"]["lafortune"]["pooled_psnr_db"] == 40.0
    assert "materials choice" in sel["validation"]["lafortune"]["judged_by"]
    assert sel["validation"]["diffuse"]["judged_by"] == "a fit of the validation split"
    assert sel["heldout_pooled_db"] == 30.0 and sel["refit"] is None
    assert set(sel["left_out"]) == {TWO_LOBES} and "too few to pin a second lobe" in sel["left_out"][TWO_LOBES]
    assert "diffuse 35.00 dB, lafortune 40.00 dB" in sel["reason"] and f"{TWO_LOBES} left out" in sel["reason"]
    assert json.loads((tmp_path / "model" / "model.json").read_text())["selection"]["chosen"] == "lafortune"
    assert not (tmp_path / "model_diffuse_validation").exists()


def test_a_candidate_kept_on_its_validation_fit_is_then_fitted_to_every_photo(tmp_path):
    """Diffuse validates better (42 against 40 dB): it is fitted again to every fitted photo and kept; with the
    one-lobe fit constraining most texels' lobes (60%) the two-lobe candidate is fitted and judged too."""
    cfg = FitStageConfig(holdout_every=8)
    scores = {"lafortune": 40.0, "diffuse": 42.0, TWO_LOBES: 39.0}
    fit_one, calls = fake_fits(scores, {"lafortune": 30.0, "diffuse": 31.0, TWO_LOBES: 29.0}, constrained_share=0.6)
    res = fit_choice(tmp_path, tmp_path, tmp_path / "model", cfg, plan(cfg), fit_one, log=lambda line: None)
    assert calls == [("diffuse", True), ("lafortune", False), (TWO_LOBES, False), ("diffuse", False)]
    sel = res.summary["selection"]
    assert sel["chosen"] == "diffuse" and sel["heldout_pooled_db"] == 31.0 and sel["refit"]
    assert sel["left_out"] == {} and set(sel["validation"]) == set(scores)
    assert (tmp_path / "model_lafortune" / "model.json").is_file()  # the full fits not kept stay beside


def test_no_lobe_is_fitted_where_the_diffuse_fit_saw_no_highlight(tmp_path):
    """The diffuse fit's photos show a highlight on none of the texels (a matte facade): Lafortune and the two-lobe
    model are left out unfitted with the reason (choice.lobe_min_highlight_share), diffuse is fitted to every
    photo and kept; at 0.2% (over the 0.1% share) Lafortune is fitted; with the option 0, always."""
    import dataclasses

    from texstream.fit.models.lafortune.choice import lobes_supported

    cfg = FitStageConfig(holdout_every=8)
    fit_one, calls = fake_fits({"lafortune": 40.0, "diffuse": 35.0}, {"lafortune": 30.0, "diffuse": 45.0},
                               highlight_share=0.0)
    res = fit_choice(tmp_path, tmp_path, tmp_path / "model", cfg, plan(cfg), fit_one, log=lambda line: None)
    assert calls == [("diffuse", True), ("diffuse", False)]
    sel = res.summary["selection"]
    assert sel["chosen"] == "diffuse" and set(sel["left_out"]) == {"lafortune", TWO_LOBES}
    assert "no highlight for a lobe to explain" in sel["left_out"]["lafortune"]
    seen = {"diffuse": {"highlights": {"seen_texels": 10_000, "highlight_texels": 20}}}
    assert lobes_supported(seen, cfg) is None
    seen["diffuse"]["highlights"]["highlight_texels"] = 5
    assert "5 of 10,000" in lobes_supported(seen, cfg)
    off = dataclasses.replace(cfg, choice=dataclasses.replace(cfg.choice, lobe_min_highlight_share=0.0))
    assert lobes_supported(seen, off) is None
    assert lobes_supported({"diffuse": {"highlights": None}}, cfg) is None  # no count: fitted


def test_the_second_lobe_is_fitted_only_where_the_photos_can_support_it():
    """The rule of fit/models/lafortune/choice.py: the one-lobe fit's share of constrained texels against
    choice.second_lobe_min_constrained; without its evidence (materials off) or with the option 0, fitted."""
    cfg = FitStageConfig()
    fitted = {"lafortune": {"materials": {"uncertainty": {"constrained_texels": 971, "seen_texels": 9580}}}}
    assert "971 of 9,580" in second_lobe_supported(fitted, cfg)
    fitted["lafortune"]["materials"]["uncertainty"]["constrained_texels"] = 5000
    assert second_lobe_supported(fitted, cfg) is None
    assert second_lobe_supported({"lafortune": {"materials": None}}, cfg) is None


def radiance_plan(cfg) -> ChoicePlan:
    from texstream.fit.models.radiance.choice import candidates as radiance_candidates

    return ChoicePlan("radiance", "no lights", radiance_candidates(None, cfg))


def test_a_relightable_model_is_kept_within_its_margin_and_only_when_asked(tmp_path):
    """``choice.relightable``: env_diffuse (the registry's relightable model) is fitted beside the radiance models
    (a validation fit, then every fitted photo when kept) and kept 0.6 dB below the best, inside the 1 dB margin;
    1.5 dB below it is not kept, and the reason says so; without the option it is never fitted. lfm never, so
    the escalation adds nothing."""
    import dataclasses

    from texstream.fit.stages.choice import ModelChoiceConfig

    scores = {"radiance": 30.0, "view_radiance": 31.0, "env_diffuse": 30.4}
    for relightable, env_db, kept in ((True, 30.4, "env_diffuse"), (True, 29.5, "view_radiance"),
                                      (False, 30.4, "view_radiance")):
        cfg = FitStageConfig(holdout_every=8, choice=ModelChoiceConfig(lfm="never", relightable=relightable))
        fit_one, calls = fake_fits(dict(scores, env_diffuse=env_db), dict.fromkeys(scores, 25.0))
        out = tmp_path / f"{relightable}_{env_db}" / "model"
        out.parent.mkdir()
        res = fit_choice(out.parent, out.parent, out, dataclasses.replace(cfg), radiance_plan(cfg), fit_one,
                         log=lambda line: None)
        sel = res.summary["selection"]
        assert sel["chosen"] == kept, (relightable, env_db, sel["reason"])
        assert (("env_diffuse", True) in calls) == relightable
        if relightable and kept != "env_diffuse":
            assert "relightable env_diffuse not kept" in sel["reason"]
        if kept == "env_diffuse":
            assert "within relightable_margin_db 1" in sel["reason"] and calls[-1] == ("env_diffuse", False)


def test_the_lfm_validation_fit_is_told_the_score_to_beat_and_its_stop_is_recorded(tmp_path):
    """``choice.stop_hopeless``: the LFM candidate's validation fit gets the best validation score of the
    candidates judged before it (view_radiance's 31 dB) as ``choice.beat_db``, the first candidate none and a
    fit of every fitted photo none; a fit that stopped says so in its ``judged_by`` and its checks are recorded.
    Off: no score to beat."""
    import dataclasses

    from texstream.fit.stages.choice import ModelChoiceConfig

    for stop in (True, False):
        cfg = FitStageConfig(holdout_every=8, choice=ModelChoiceConfig(lfm="always", stop_hopeless=stop))
        fit_one, calls = fake_fits({"radiance": 30.0, "view_radiance": 31.0, "lfm": 30.5}, dict.fromkeys(
            ("radiance", "view_radiance", "lfm"), 25.0))
        beats = []

        def recording(capture_dir, mesh_path, out, c):
            beats.append((c.fit.model, c.choice.validation_fit, c.choice.beat_db))
            res = fit_one(capture_dir, mesh_path, out, c)
            if c.fit.model == "lfm" and c.choice.beat_db:
                res.summary["stop"] = {"stopped": "stopped at iteration 30 of 50: below the 31.00 dB to beat",
                                       "beat_db": c.choice.beat_db, "checks": [[10, 29.0]], "checks_s": 1.0}
            return res

        out = tmp_path / str(stop) / "model"
        out.parent.mkdir()
        sel = fit_choice(out.parent, out.parent, out, dataclasses.replace(cfg), radiance_plan(cfg), recording,
                         log=lambda line: None).summary["selection"]
        assert sel["chosen"] == "view_radiance"
        expected = [("radiance", True, 0.0), ("view_radiance", True, 30.0 if stop else 0.0),
                    ("lfm", True, 31.0 if stop else 0.0), ("view_radiance", False, 0.0)]
        assert beats == expected
        assert ("stopped at iteration 30" in sel["validation"]["lfm"]["judged_by"]) == stop
        assert ("stop" in sel["validation"]["lfm"]) == stop  # the checks recorded beside the score


def test_a_per_texel_validation_fit_writes_its_scores_only(tmp_path):
    """The model choice's validation fit of a per-texel model (``choice.validation_fit``) is judged by its scores and
    then removed (fit/stages/choice.py), so it writes model.json with the validation photos' scores and no maps,
    mesh, bake or plot (2-3 s of each of the temple's candidates)."""
    import dataclasses

    from conftest import SCENE_DEVICE, tiny_sphere_capture
    from texstream.fit.optim.fitter import FitConfig
    from texstream.fit.stages.stage import fit_stage

    cap = tiny_sphere_capture(tmp_path, photos=8)
    cfg = FitStageConfig(device=SCENE_DEVICE, holdout_every=4, checkpoint=False, fit=FitConfig(model="diffuse",
                                                                                                max_iterations=2))
    cfg = dataclasses.replace(cfg, choice=dataclasses.replace(cfg.choice, validation_fit=True))
    res = fit_stage(cap, cap / "ground_truth", tmp_path / "val", cfg, progress=False)
    written = sorted(p.name for p in (tmp_path / "val").iterdir())
    manifest = json.loads((tmp_path / "val" / "model.json").read_text())
    assert manifest["scores_only"] and manifest["maps"] == {} and res.summary["heldout"]["views"] > 0
    assert not {"rho_d.exr", "mesh.obj", "bake.npz", "seen.png", "error_vs_time.png"} & set(written), written


def test_candidates_that_saw_the_same_texels_share_the_nearest_seen_texels():
    """The per-texel fit fills each texel no photo saw from the nearest seen one; the model choice's radiance and
    view_radiance validation fits see the same texels, so the second takes the first's sources (the same arrays
    as computed afresh); another seen set computes its own."""
    import types

    import numpy as np

    from texstream.fit.common.setup import unseen_sources
    from texstream.fit.models.per_texel import fit as per_texel

    rng = np.random.default_rng(0)
    texels = types.SimpleNamespace(grid_index=np.arange(300) * 2, position=rng.uniform(size=(300, 3)))
    problem = types.SimpleNamespace(texels=texels)
    first = types.SimpleNamespace(samples=(rng.uniform(size=300) > 0.3).astype(np.int32))
    second = types.SimpleNamespace(samples=first.samples * 7)  # other counts, the same texels seen
    shared = per_texel._unseen_sources(problem, first)
    assert per_texel._unseen_sources(problem, second) is shared
    for a, b in zip(shared, unseen_sources(problem, first)):
        assert np.array_equal(a, b)
    other = types.SimpleNamespace(samples=np.ones(300, np.int32))
    assert per_texel._unseen_sources(problem, other)[0].size == 0
